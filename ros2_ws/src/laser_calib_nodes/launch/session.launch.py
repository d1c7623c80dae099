"""A full simulated calibration session (what scripts/run-session runs).

    ros2 launch laser_calib_nodes session.launch.py output_dir:=/tmp/session [poses:=60] [robot:=...]

Starts the simulated arm_driver, camera_sim, spot_detector, the estimator and
the sequencer; when the sequencer has finished (report written), the launch
shuts everything down. Parameters: config/session.yaml of this package.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
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
        DeclareLaunchArgument("robot", default_value=os.path.join(share, "config", "robots", "humanoid_arm_7dof.yaml"),
                              description="Nominal robot model file (YAML)."),
        DeclareLaunchArgument("output_dir", description="Session directory (resumed if partial)."),
        DeclareLaunchArgument("poses", default_value="60", description="Poses to generate."),
        DeclareLaunchArgument("span", default_value="whole", description="'whole' or 'small'."),
        DeclareLaunchArgument("method", default_value="lm", description="Final estimate: 'lm' or 'ekf'."),
    ]
    estimator = Node(package="laser_calib_nodes", executable="estimator", name="estimator", output="screen",
                     parameters=[params, {"robot": robot}])
    arm = Node(package="laser_calib_nodes", executable="arm_driver", name="arm_driver", output="screen",
               parameters=[params, {"robot": robot, "sim.true_robot_out": ParameterValue(
                   PathJoinSubstitution([LaunchConfiguration("output_dir"), "robot_true.yaml"]), value_type=str)}])
    camera = Node(package="laser_calib_nodes", executable="camera_sim", name="camera_sim", output="screen",
                  parameters=[params])
    detector = Node(package="laser_calib_nodes", executable="spot_detector", name="spot_detector",
                    output="screen", parameters=[params])
    sequencer = Node(package="laser_calib_nodes", executable="sequencer", name="sequencer", output="screen",
                     parameters=[params, {"robot": robot, "output_dir": arg("output_dir"),
                                          "poses": arg("poses", int),
                                          "span": arg("span"),
                                          "estimate.method": arg("method")}])
    done = RegisterEventHandler(OnProcessExit(target_action=sequencer,
                                              on_exit=[EmitEvent(event=Shutdown(reason="session finished"))]))
    return LaunchDescription(args + [estimator, arm, camera, detector, sequencer, done])
