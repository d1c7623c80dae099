"""ROS 2 nodes of laser kinematic calibration: thin adapters over laser_calib.

graph (the node graph of a session, shared by the launch files and
scripts/run-session) is ROS-free; the node modules import rclpy. Each node
module's main() is an executable (bin/node).
"""

__version__ = "0.1.0"
