"""ROS 2 nodes of laser kinematic calibration: thin adapters over laser_calib.

ROS-free modules (importable without rclpy): sync (stamp synchronizer),
bag (segmented rosbag2 MCAP writer and session bag reader), poses (pose lists
and session progress). The node modules import rclpy.
"""

__version__ = "0.1.0"
