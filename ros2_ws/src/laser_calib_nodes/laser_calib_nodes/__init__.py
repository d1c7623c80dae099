"""ROS 2 nodes of laser kinematic calibration: thin adapters over laser_calib.

graph (the node graph of a session, shared by the launch files and
scripts/run-session) is ROS-free; the node modules import rclpy.
"""

import os
import signal
import sys
from pathlib import Path


def _stop_while_starting(_signum, _frame):
    """Exit 0 at once: nothing is started yet that needs cleaning up. An exception would
    surface inside whatever is importing, and rclpy's C extension turns one raised during
    its initialisation into an ImportError naming a missing library (exit 1)."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


# A Ctrl-C while a node is still importing (numpy, scipy: seconds on a busy machine; a
# launch shut down right after start) ends it quietly with 0, as one after its start
# does; common.run (and replay, before rclpy.init) installs the handler that cleans up.
# Only in this package's executables (lib/laser_calib_nodes/NAME): a launch file
# importing graph keeps launch's handler.
if Path(sys.argv[0]).parent.name == "laser_calib_nodes":
    signal.signal(signal.SIGINT, _stop_while_starting)

__version__ = "0.1.0"
