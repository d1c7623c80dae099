"""Import paths for the hardware tests: the emulator (test/) and the ROS-free package (laser_calib)."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
for path in (ROOT / "test", ROOT / "ros2_ws" / "src" / "laser_calib"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))
