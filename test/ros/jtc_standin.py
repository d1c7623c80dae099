"""A stand-in for a ros2_control arm: joint_trajectory_controller + joint_state_broadcaster.

    jtc_standin.py ROBOT_YAML JOINT,JOINT,...      (the controller's joints, base to tip)

Like the real pair it
- takes trajectory_msgs/JointTrajectory on /arm_controller/joint_trajectory and refuses,
  with one 'rejected: ...' line, what joint_trajectory_controller's validate_trajectory_msg
  refuses (laser_calib.hardware.trajectory, tested rule by rule in test/core), goals
  outside the joint limits included;
- moves to the last point in its time_from_start (linear in time), not faster;
- publishes /joint_states with the joints in its own order (reversed) plus a gripper joint
  the calibration does not know, as joint_state_broadcaster publishes every joint.
It also publishes /spots (the nominal robot's spots at the current joints) so that a
session runs without camera and detector. Prints 'accepted N' per trajectory.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import rclpy
from rclpy.node import Node
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from laser_calib.hardware.trajectory import TrajectoryPoint, trajectory_goal
from laser_calib.model.kinematics import predict
from laser_calib.model.robot_file import load_robot
from laser_calib_interfaces.msg import Spot, SpotPair
from spin_node import spin_until_interrupted

GRIPPER = "gripper_finger_joint"


def seconds(t) -> float:
    return t.sec + t.nanosec * 1e-9


class StandIn(Node):
    def __init__(self, robot, joints):
        super().__init__("arm_controller")
        self.robot, self.joints = robot, joints
        self.q = np.zeros(len(joints))
        self.start_q, self.goal, self.t0, self.duration = self.q, self.q, 0.0, 0.0
        self.accepted = 0
        self.create_subscription(JointTrajectory, "~/joint_trajectory", self.on_trajectory, 10)
        self.state_pub = self.create_publisher(JointState, "/joint_states", 50)
        self.spot_pub = self.create_publisher(SpotPair, "/spots", 50)
        self.create_timer(0.02, self.on_timer)

    def on_trajectory(self, msg: JointTrajectory) -> None:
        points = [TrajectoryPoint(list(p.positions), seconds(p.time_from_start), list(p.velocities),
                                  list(p.accelerations)) for p in msg.points]
        now = self.get_clock().now().nanoseconds * 1e-9
        try:
            goal = trajectory_goal(list(msg.joint_names), points, self.joints, self.robot.q_min, self.robot.q_max,
                                   seconds(msg.header.stamp), now)
        except ValueError as exc:
            print(f"rejected: {exc}", flush=True)
            return
        self.start_q, self.goal, self.t0 = self.q.copy(), goal, time.monotonic()
        self.duration = points[-1].time_from_start
        self.accepted += 1
        print(f"accepted {self.accepted} in {self.duration:.3f} s", flush=True)

    def on_timer(self) -> None:
        done = 1.0 if self.duration <= 0 else min(1.0, (time.monotonic() - self.t0) / self.duration)
        velocity = np.zeros_like(self.q) if done >= 1.0 else (self.goal - self.start_q) / self.duration
        self.q = self.start_q + done * (self.goal - self.start_q)
        stamp = self.get_clock().now().to_msg()
        order = list(reversed(range(len(self.joints))))
        state = JointState(name=[self.joints[i] for i in order] + [GRIPPER],
                           position=[float(self.q[i]) for i in order] + [0.01],
                           velocity=[float(velocity[i]) for i in order] + [0.0])
        state.header.stamp = stamp
        self.state_pub.publish(state)
        p = predict(self.robot, self.q[None])
        pair = SpotPair(spots=[Spot(y=float(p.spots[0, j, 0]), z=float(p.spots[0, j, 1]), seen=bool(p.hit[0, j]))
                               for j in range(2)])
        pair.header.stamp, pair.header.frame_id = stamp, "screen"
        self.spot_pub.publish(pair)


def main() -> None:
    rclpy.init()
    spin_until_interrupted(StandIn(load_robot(sys.argv[1]), sys.argv[2].split(",")))


if __name__ == "__main__":
    main()
