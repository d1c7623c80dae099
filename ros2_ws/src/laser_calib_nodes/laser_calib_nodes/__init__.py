"""ROS 2 nodes of laser kinematic calibration: thin adapters over laser_calib.

graph (the node graph of a session, shared by the launch files and
scripts/run-session) is ROS-free; the node modules import rclpy.
"""

import signal
import sys
from pathlib import Path

# A Ctrl-C while a node is still importing (numpy, scipy: seconds on a busy machine; a
# launch shut down right after start) ends it quietly with 0, as one after its start
# does; rclpy.init installs its own handler later. Only in this package's executables
# (lib/laser_calib_nodes/NAME): a launch file importing graph keeps launch's handler.
if Path(sys.argv[0]).parent.name == "laser_calib_nodes":
    signal.signal(signal.SIGINT, lambda *_: sys.exit(0))

__version__ = "0.1.0"
