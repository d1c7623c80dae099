"""Fixtures of the ROS tests (harness in ros_harness.py)."""

import sys
from pathlib import Path

import pytest

NODES_SRC = Path(__file__).resolve().parents[2] / "ros2_ws" / "src" / "laser_calib_nodes"
if str(NODES_SRC) not in sys.path:
    sys.path.insert(0, str(NODES_SRC))  # the ROS-free modules of laser_calib_nodes (bag, sync, session)

from ros_harness import Ros, workspace_missing  # noqa: E402


@pytest.fixture
def ros(tmp_path):
    reason = workspace_missing()
    if reason:
        pytest.skip(reason)
    handle = Ros(tmp_path)
    yield handle
    handle.stop_all()
