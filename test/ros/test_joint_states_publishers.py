"""joint_states with more than one publisher, as on a real robot: the arm's broadcaster and a
gripper's driver (or a second arm) on the same topic. The sequencer took the joint order of the
first message it got and applied it to every later one: the gripper's one-joint message ended
the session in an IndexError traceback (exit 1), or, when it came first, in exit 2 asking for
joint_names the arm's messages did not need; a message of other joints, as many, was read as the
arm's. Now each message's joints are found by its own names, and another publisher's are
ignored with one WARN line."""

from __future__ import annotations

import sys

import numpy as np

from ros_harness import ROBOT, start_sim

# a second publisher on /joint_states: a gripper's one joint, at 50 Hz (as often as the arm)
GRIPPER = """
import rclpy
from rclpy.node import Node
from sensor_msgs.msg import JointState
rclpy.init()
node = Node("gripper_driver")
pub = node.create_publisher(JointState, "joint_states", 10)
def tick():
    msg = JointState(name=["gripper_finger_joint"], position=[0.01], velocity=[0.0])
    msg.header.stamp = node.get_clock().now().to_msg()
    pub.publish(msg)
node.create_timer(0.02, tick)
try:
    rclpy.spin(node)
except KeyboardInterrupt:
    pass
"""


def test_a_gripper_publishing_on_joint_states_is_ignored(ros, tmp_path):
    from laser_calib.io.samples import load_samples
    from laser_calib.model.robot_file import load_robot
    from laser_calib.session.poses import load_poses
    out = tmp_path / "out"
    out.mkdir()   # the sim arm writes robot_true.yaml there
    start_sim(ros, out)
    ros.start_command("gripper", [sys.executable, "-c", GRIPPER])
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "poses:=3",
              "-p", "span:=small", "-p", "estimate.mode:=none")
    assert ros.wait_exit("sequencer", 120) == 0, ros.log("sequencer")[-3000:]
    log = ros.log("sequencer")
    assert "Traceback" not in log, log
    assert log.count("joint_states message ignored") == 1, log   # one line per set of names
    assert "gripper_finger_joint" in log, log
    robot = load_robot(ROBOT)
    samples, poses = load_samples(out / "samples.csv", robot), load_poses(out / "poses.csv", robot)
    assert len(samples) == 3
    assert np.all(np.abs(samples.q - poses.q) < 0.003)   # the arm's readings, settle.position_tolerance
