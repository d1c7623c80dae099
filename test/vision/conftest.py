"""Import path for the vision tests: the ROS-free core package (no install needed); the project's
camera and a detector with its ideal calibration, shared by the test modules."""

import sys
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[2] / "ros2_ws" / "src" / "laser_calib"
if str(CORE) not in sys.path:
    sys.path.insert(0, str(CORE))


@pytest.fixture(scope="module")
def camera():
    from laser_calib.vision import default_camera
    return default_camera()


@pytest.fixture(scope="module")
def detector(camera):
    from laser_calib.vision import SpotDetector
    return SpotDetector(camera.ideal_calibration())
