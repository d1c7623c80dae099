"""ROS 2 nodes of laser kinematic calibration: thin adapters over laser_calib.

graph (the node graph of a session, shared by the launch files and
scripts/run-session) is ROS-free; the node modules import rclpy.
"""

import signal
import sys

# A Ctrl-C while a node is still importing (numpy, scipy: seconds on a busy machine; a
# launch shut down right after start) ends it quietly with 0, as one after its start
# does; rclpy.init installs its own handler later.
signal.signal(signal.SIGINT, lambda *_: sys.exit(0))

__version__ = "0.1.0"
