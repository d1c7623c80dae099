"""Import path for every test: the ROS-free core package (no install needed)."""

import sys
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / "ros2_ws" / "src" / "laser_calib"
if str(CORE) not in sys.path:
    sys.path.insert(0, str(CORE))

import laser_calib  # noqa: E402,F401  (pins BLAS to one thread before any test imports numpy)
