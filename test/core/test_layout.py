"""The layout's rules (docs/architecture.md), checked on the source itself.

The core is ROS-free and never reaches into the nodes package; its subpackages
import on their own, with no import circle; modules stay small enough to read.
"""

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "ros2_ws" / "src"
CORE = SRC / "laser_calib" / "laser_calib"
NODES = SRC / "laser_calib_nodes" / "laser_calib_nodes"
ROS_ONLY = ("rclpy", "laser_calib_nodes", "laser_calib_interfaces", "launch", "launch_ros", "ament_index_python")


def module_name(path: Path) -> str:
    parts = path.relative_to(CORE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> list[tuple[str, int]]:
    """(imported module, line) of every import statement, module level or not."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append((node.module, node.lineno))
            found += [(f"{node.module}.{alias.name}", node.lineno) for alias in node.names]
    return found


CORE_FILES = sorted(CORE.rglob("*.py"))


def test_the_core_imports_nothing_of_ros():
    offending = [f"{path.relative_to(SRC)}:{line} imports {name}"
                 for path in CORE_FILES for name, line in imports(path)
                 if name.split(".")[0] in ROS_ONLY]
    assert not offending, "\n".join(offending)


def test_no_import_circle_in_the_core():
    known = {module_name(p) for p in CORE_FILES}
    graph = {}
    for path in CORE_FILES:
        tree = ast.parse(path.read_text())
        targets = set()
        for node in tree.body:  # module level: what runs at import time
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for name in [node.module] + [f"{node.module}.{a.name}" for a in node.names]:
                    if name in known:
                        targets.add(name)
            elif isinstance(node, ast.Import):
                targets |= {a.name for a in node.names if a.name in known}
        graph[module_name(path)] = targets - {module_name(path)}
    # Packages import their modules through __init__; a module importing its own
    # package's face is not a circle of roles, so only module-to-module edges count.
    packages = {module_name(p) for p in CORE_FILES if p.name == "__init__.py"}
    state, circles = {}, []

    def visit(node, stack):
        state[node] = "open"
        for nxt in graph.get(node, ()):
            if nxt in packages or node in packages:
                continue
            if state.get(nxt) == "open":
                circles.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = "done"

    for start in sorted(graph):
        if start not in state:
            visit(start, [start])
    assert not circles, "import circles: " + "; ".join(" -> ".join(c) for c in circles)


SUBPACKAGES = sorted(p.parent.name for p in CORE.glob("*/__init__.py"))


@pytest.mark.parametrize("package", SUBPACKAGES)
def test_each_subpackage_imports_on_its_own(package):
    modules = sorted(module_name(p) for p in (CORE / package).rglob("*.py") if p.name != "__main__.py")
    code = "import importlib, sys\nfor m in sys.argv[1:]:\n    importlib.import_module(m)\n"
    done = subprocess.run([sys.executable, "-c", code, *modules], capture_output=True, text=True,
                          env={"PYTHONPATH": str(CORE.parent), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr[-2000:]



def node_modules() -> set[str]:
    """The modules that are nodes: the nodes package's executables (links to bin/node, which runs
    the module of the link's name)."""
    return {p.name for p in (SRC / "laser_calib_nodes" / "bin").iterdir() if p.is_symlink()}


def test_modules_stay_readable():
    """At most 400 lines a module, 250 a node: a node only converts and calls the core."""
    nodes = node_modules()
    assert {"sequencer", "estimator", "spot_detector"} <= nodes
    files = [(p, 400) for p in CORE_FILES] + [(p, 250 if p.stem in nodes else 400) for p in sorted(NODES.glob("*.py"))]
    long = [f"{p.relative_to(SRC)}: {n} lines (at most {limit})" for p, limit in files
            if (n := len(p.read_text().splitlines())) > limit]
    assert not long, "\n".join(long)


def test_the_docs_name_modules_that_exist():
    """Every module the documentation names (a path laser_calib[_nodes]/.../x.py, or a dotted name
    in backquotes, the last part possibly a function or class in it) exists: seven had moved away
    under the docs, which still sent readers to laser_calib/real_cli.py and laser_calib/diagnosis.py."""
    root = SRC.parents[1]
    docs = [*sorted((root / "docs").glob("*.md")), root / "README.md", root / "bench" / "README.md",
            SRC / "laser_calib_nodes" / "README.md"]
    missing = []
    for doc in docs:
        text = doc.read_text()
        for path in re.findall(r"(laser_calib(?:_nodes)?/[\w/]+\.py)", text):
            if not (SRC / path.split("/")[0] / path).exists():
                missing.append(f"{doc.name}: {path}")
        for dotted in re.findall(r"`(laser_calib(?:_nodes)?(?:\.\w+)+)", text):
            parts = dotted.split(".")
            # the longest prefix that is a module or package; at most the last part may be a name in it
            found = [k for k in range(len(parts), 0, -1)
                     if (SRC / parts[0]).joinpath(*parts[:k]).with_suffix(".py").exists()
                     or (SRC / parts[0]).joinpath(*parts[:k], "__init__.py").exists()]
            if not found or found[0] < len(parts) - 1:
                missing.append(f"{doc.name}: {dotted}")
    assert not missing, "\n".join(missing)
