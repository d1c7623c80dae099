"""A calibration session on a real arm: Dynamixel arm_driver, spot_detector on a
camera driver's image topic, estimator and sequencer.

    ros2 launch laser_calib_nodes hardware.launch.py robot:=/path/arm.yaml \
        arm_params:=/path/dynamixel_arm.yaml calibration:=/path/screen_calibration.yaml \
        output_dir:=/data/session image:=/camera/image_raw

The camera driver is yours (any node publishing sensor_msgs/Image bgr8 of the
calibrated camera); its image topic is remapped to camera/image_raw.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def arg(name, kind=str):
    """A launch argument as a typed parameter value (not YAML-guessed)."""
    return ParameterValue(LaunchConfiguration(name), value_type=kind)


def generate_launch_description():
    share = get_package_share_directory("laser_calib_nodes")
    params = os.path.join(share, "config", "session.yaml")
    robot = arg("robot")
    args = [
        DeclareLaunchArgument("robot", description="Nominal robot model file (YAML)."),
        DeclareLaunchArgument("arm_params", default_value=os.path.join(share, "config", "dynamixel_arm.yaml"),
                              description="arm_driver parameters (Dynamixel port, ids, ticks)."),
        DeclareLaunchArgument("calibration", description="Screen calibration file of the camera."),
        DeclareLaunchArgument("image", default_value="/camera/image_raw", description="Camera image topic."),
        DeclareLaunchArgument("output_dir", description="Session directory (resumed if partial)."),
        DeclareLaunchArgument("poses_file", default_value="", description="Pose list; empty: generate."),
        DeclareLaunchArgument("poses", default_value="60", description="Poses to generate."),
    ]
    estimator = Node(package="laser_calib_nodes", executable="estimator", name="estimator", output="screen",
                     parameters=[params, {"robot": robot}])
    arm = Node(package="laser_calib_nodes", executable="arm_driver", name="arm_driver", output="screen",
               parameters=[LaunchConfiguration("arm_params"), {"robot": robot}])
    detector = Node(package="laser_calib_nodes", executable="spot_detector", name="spot_detector",
                    output="screen", parameters=[params, {"calibration": arg("calibration")}],
                    remappings=[("camera/image_raw", LaunchConfiguration("image"))])
    sequencer = Node(package="laser_calib_nodes", executable="sequencer", name="sequencer", output="screen",
                     parameters=[params, {"robot": robot, "output_dir": arg("output_dir"),
                                          "poses_file": arg("poses_file"),
                                          "poses": arg("poses", int)}])
    done = RegisterEventHandler(OnProcessExit(target_action=sequencer,
                                              on_exit=[EmitEvent(event=Shutdown(reason="session finished"))]))
    return LaunchDescription(args + [estimator, arm, detector, sequencer, done])
