"""A robot's joint readings out of joint_states, each joint found by its name (the sequencer's
rule, laser_calib.hardware.trajectory.joint_order): a driver may list the joints in any order,
and more joints (a gripper). A Sample's joint_positions follow its joint_names by the core's
rule (laser_calib.io.joint_names, which the bag reader applies too)."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import JointState

from laser_calib.hardware.trajectory import joint_order
from laser_calib.io.joint_names import RobotJoints
from laser_calib.model.robot import Robot


class JointStateReader(RobotJoints):
    def __init__(self, robot: Robot, names: list[str], logger):
        """names: the joint_names parameter (empty: the robot's default names)."""
        super().__init__(robot, names, "parameter joint_names")
        self.logger = logger
        self.orders: dict[tuple[str, ...], list[int] | None] = {}  # a message's names -> robot order

    def index(self, names: list[str], count: int) -> list[int] | None:
        """Index into a message of each robot joint, base to tip; None, with one ERROR line per set
        of names, when the robot's joints are not there. The message's own order only for a D-H
        robot without joint_names whose joint_states has exactly its joints under other names."""
        key = tuple(names)
        if key not in self.orders:
            order = None
            try:
                order = joint_order(names, self.names, self.n)
            except ValueError as exc:
                if not self.strict and len(names) in (0, self.n) and count == self.n:
                    order = list(range(self.n))
                else:
                    self.logger.error(f"joint_states ignored: {exc}")
            self.orders[key] = order
        return self.orders[key]

    def read(self, msg: JointState) -> tuple[np.ndarray, np.ndarray | None] | None:
        """The robot's q (N,) and, when the message has them, velocities (N,); None when unusable."""
        index = self.index(list(msg.name), len(msg.position))
        if index is None or msg.name and len(msg.position) != len(msg.name):
            return None
        q = np.array(msg.position, dtype=float)[index]
        v = np.array(msg.velocity, dtype=float)[index] if len(msg.velocity) == len(msg.position) else None
        return q, v
