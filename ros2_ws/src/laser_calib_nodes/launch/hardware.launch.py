"""A calibration session on a real arm: Dynamixel arm_driver, spot_detector on a
camera driver's image topic, estimator and sequencer. ``test_poses`` held-out poses over
the whole workspace are measured last and never fitted: the report's before/after.

    ros2 launch laser_calib_nodes hardware.launch.py robot:=/path/arm.yaml \
        arm_params:=/path/dynamixel_arm.yaml calibration:=/path/screen_calibration.yaml \
        output_dir:=/data/session image:=/camera/image_raw test_poses:=20

With ``robot_description_topic:=/robot_description`` the arm's URDF comes from
robot_state_publisher and ``robot`` is the file of base, tip and lasers
(docs/urdf.md). The camera driver is yours (any node publishing sensor_msgs/Image of the
calibrated camera; the QoS spot_detector subscribes with is in the package
README's table); its image topic is remapped to camera/image_raw, and the camera_info beside it
to camera/camera_info. The node graph is
laser_calib_nodes.graph.hardware_nodes; as session.launch.py, the launch takes
the session folder's lock and ends when the sequencer or any node exits.
"""

from laser_calib_nodes import graph


def generate_launch_description():
    return graph.launch_description(graph.HARDWARE_ARGS, graph.hardware_nodes)
