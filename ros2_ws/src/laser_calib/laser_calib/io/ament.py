"""Installed ROS packages' files, found as the ament index finds them, without ROS.

A sourced workspace (or ROS install) lists its install prefixes in
AMENT_PREFIX_PATH; a package's executables are in <prefix>/lib/<package>/ and its
data in <prefix>/share/<package>/ (REP 122 layout, what `ros2 run` and
get_package_share_directory read). A ROS 1 (catkin) user has source packages on
ROS_PACKAGE_PATH instead: folders holding a package.xml, found by walking each
entry as rospack does. ``package_index`` makes both visible to the ament index
(xacro's ``$(find pkg)``) for the length of a block.
"""

from __future__ import annotations

import os
import re
import tempfile
import xml.etree.ElementTree as ElementTree
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

# A folder holding one of these is skipped with everything below it (catkin, colcon, ament).
IGNORE_MARKERS = ("CATKIN_IGNORE", "COLCON_IGNORE", "AMENT_IGNORE")
INDEX = Path("share") / "ament_index" / "resource_index" / "packages"


def installed(relative: str) -> Path | None:
    """The first <prefix>/<relative> that exists, in AMENT_PREFIX_PATH order, else None."""
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix and (Path(prefix) / relative).exists():
            return Path(prefix) / relative
    return None


def _package_name(folder: Path) -> str:
    try:
        name = ElementTree.parse(folder / "package.xml").findtext("name")
    except (ElementTree.ParseError, OSError):
        name = None
    return (name or folder.name).strip()


def ros_packages() -> dict[str, Path]:
    """Package name -> folder of the source packages on ROS_PACKAGE_PATH; of two
    packages of one name, the one on the earlier entry (rospack's rule)."""
    found: dict[str, Path] = {}
    for entry in os.environ.get("ROS_PACKAGE_PATH", "").split(os.pathsep):
        for folder, subfolders, files in os.walk(entry) if entry else ():
            if any(marker in files for marker in IGNORE_MARKERS):
                subfolders[:] = []
            elif "package.xml" in files:
                found.setdefault(_package_name(Path(folder)), Path(folder))
                subfolders[:] = []  # a package holds no packages
            else:
                subfolders[:] = sorted(s for s in subfolders if not s.startswith("."))
    return found


@contextmanager
def package_index() -> Iterator[str]:
    """Within the block, AMENT_PREFIX_PATH ends with a temporary prefix that
    indexes the ROS_PACKAGE_PATH packages as an install would (share/<name> and
    the ament index marker): installed packages are found first, then those.
    Yields the prefix (a path under it is one of the packages' files: in_package)."""
    before = os.environ.get("AMENT_PREFIX_PATH")
    with tempfile.TemporaryDirectory(prefix="ros_package_path_") as prefix:
        (Path(prefix) / INDEX).mkdir(parents=True)
        for name, folder in ros_packages().items():
            (Path(prefix) / INDEX / name).touch()
            (Path(prefix) / "share" / name).symlink_to(folder.resolve(), target_is_directory=True)
        os.environ["AMENT_PREFIX_PATH"] = os.pathsep.join(p for p in (before, prefix) if p)
        try:
            yield prefix
        finally:
            if before is None:
                del os.environ["AMENT_PREFIX_PATH"]
            else:
                os.environ["AMENT_PREFIX_PATH"] = before


def in_package(text: str, prefix: str) -> str:
    """``text`` with the paths under package_index's temporary ``prefix`` written as the package
    folders they stand for: a message naming a file must name one the user can find."""
    if not prefix:
        return text
    packages = ros_packages()
    return re.sub(re.escape(str(Path(prefix) / "share")) + r"/([^/\s'\"]+)",
                  lambda m: str(packages[m[1]].resolve()) if m[1] in packages else m[0], text)
