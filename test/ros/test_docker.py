"""docker/Dockerfile builds what scripts/setup builds (Docker cannot run here, so
the file itself is checked): the same colcon packages, every entry point's module
imported by its build-time smoke check, the Python libraries of requirements.txt and the ROS
packages of the package.xml files,
and a build context that keeps what the build needs."""

from __future__ import annotations

import ast
import fnmatch
import re
import xml.etree.ElementTree as ET

from ros_harness import ROOT

DOCKERFILE = (ROOT / "docker" / "Dockerfile").read_text()
SRC = ROOT / "ros2_ws" / "src"
# requirements.txt names that Ubuntu packages under another name
APT_NAMES = {"pyyaml": "python3-yaml"}
# what the ROS image provides instead of a wheel (ROS itself, the build tools) and the test tools
NOT_IN_IMAGE = re.compile(r"^(ros-jazzy-|colcon-|pytest$|pytest-xdist$|hypothesis$)")


def packages() -> set[str]:
    """What scripts/setup's colcon build builds: every package under ros2_ws/src."""
    return {ET.parse(path).findtext("name") for path in SRC.glob("*/package.xml")}


def entry_point_modules() -> set[str]:
    """The console_scripts' modules and the node executables' (links to laser_calib_nodes/bin/node,
    which runs laser_calib_nodes.<link name>)."""
    modules = {f"laser_calib_nodes.{link.name}" for link in (SRC / "laser_calib_nodes" / "bin").iterdir()
               if link.is_symlink()}
    for setup in SRC.glob("*/setup.py"):
        for node in ast.walk(ast.parse(setup.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and " = " in node.value:
                name, target = node.value.split(" = ")
                if re.fullmatch(r"[\w-]+", name) and ":" in target:
                    modules.add(target.split(":")[0].strip())
    return modules


def test_same_packages_as_the_setup():
    selected = re.search(r"colcon build --packages-select ([\w ]+)", DOCKERFILE)
    assert selected, "the Dockerfile's colcon build names no packages"
    assert set(selected.group(1).split()) == packages()


def test_every_entry_point_is_imported_at_build_time():
    smoke = re.search(r'python3 -c "import ([^"]+)"', DOCKERFILE)
    assert smoke, "no import smoke check in the Dockerfile"
    imported = {name.strip() for name in smoke.group(1).split(",")}
    assert entry_point_modules() <= imported, entry_point_modules() - imported
    assert {"laser_calib_interfaces.srv", "laser_calib_interfaces.action"} <= imported
    assert len(entry_point_modules()) >= 7  # laser-calib and the six node executables


def test_python_libraries_of_the_requirements_are_installed():
    missing = []
    for line in (ROOT / "requirements.txt").read_text().splitlines():
        name = re.split(r"[<>=\[; ]", line.strip(), maxsplit=1)[0]
        if not name or name.startswith("#") or NOT_IN_IMAGE.match(name):
            continue
        apt = APT_NAMES.get(name.lower(), f"python3-{name.lower()}")
        if apt not in DOCKERFILE and not re.search(rf"pip3 install[^&]*\b{re.escape(name)}\b", DOCKERFILE):
            missing.append(name)
    assert not missing, f"requirements.txt names {missing}, which docker/Dockerfile does not install"


def test_ros_packages_the_packages_depend_on_are_installed():
    """Each ROS package a package.xml depends on (the nodes' diagnostic_msgs was missing) is in the
    image's apt list, not left to what the base image's variant happens to hold."""
    ours = packages()
    wanted = {element.text for path in SRC.glob("*/package.xml") for element in ET.parse(path).getroot()
              if element.tag in ("depend", "exec_depend") and not element.text.startswith("python3-")}
    missing = sorted(name for name in wanted - ours if f"ros-jazzy-{name.replace('_', '-')}" not in DOCKERFILE)
    assert not missing, f"package.xml files depend on {missing}, which docker/Dockerfile does not install"


def test_build_context_keeps_the_sources():
    assert "COPY . ." in DOCKERFILE
    ignored = [line.strip() for line in (ROOT / "docker" / "Dockerfile.dockerignore").read_text().splitlines()
               if line.strip() and not line.startswith("#")]
    needed = [str(path.relative_to(ROOT)) for folder in ("ros2_ws/src", "config", "scripts")
              for path in (ROOT / folder).rglob("*") if path.is_file() and "__pycache__" not in path.parts]
    assert needed
    dropped = [path for path in needed for pattern in ignored
               if fnmatch.fnmatch(path, pattern) or path.startswith(pattern.rstrip("/") + "/")]
    assert not dropped, dropped[:5]
