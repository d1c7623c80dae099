"""Installed ROS packages' files, found as the ament index finds them, without ROS.

A sourced workspace (or ROS install) lists its install prefixes in
AMENT_PREFIX_PATH; a package's executables are in <prefix>/lib/<package>/ and its
data in <prefix>/share/<package>/ (REP 122 layout, what `ros2 run` and
get_package_share_directory read).
"""

from __future__ import annotations

import os
from pathlib import Path


def installed(relative: str) -> Path | None:
    """The first <prefix>/<relative> that exists, in AMENT_PREFIX_PATH order, else None."""
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix and (Path(prefix) / relative).exists():
            return Path(prefix) / relative
    return None
