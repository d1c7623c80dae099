"""Import path for the vision tests: the ROS-free core package (no install needed)."""

import sys
from pathlib import Path

CORE = Path(__file__).resolve().parents[2] / "ros2_ws" / "src" / "laser_calib"
if str(CORE) not in sys.path:
    sys.path.insert(0, str(CORE))
