"""A robot's joint readings out of joint_states and Sample messages, each joint found by its name
(the sequencer's rule, laser_calib.hardware.trajectory.joint_order): a driver may list the joints
in any order, and more joints (a gripper)."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import JointState

from laser_calib.hardware.trajectory import joint_order
from laser_calib.io import bag
from laser_calib.io.errors import InputError
from laser_calib.model.robot import Robot

from laser_calib_nodes import common
from laser_calib_nodes.parameters import NodeError


class JointStateReader:
    def __init__(self, robot: Robot, names: list[str], logger):
        """names: the joint_names parameter (empty: the robot's default names)."""
        self.n = robot.n_joints
        self.names = list(names) if names else common.default_joint_names(robot)
        # D-H robot, no joint_names given: its joints have no names of their own to insist on
        self.strict = bool(names) or robot.chain is not None
        if len(self.names) != self.n:
            raise NodeError(f"parameter joint_names: {len(self.names)} names, robot '{robot.name}' has "
                            f"{self.n} joints", 2)
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

    def sample_row(self, msg, where: str) -> tuple[int, float, np.ndarray, np.ndarray]:
        """(pose, stamp, q (N,) base to tip, spots (2,2)) of a Sample message, its joint_positions
        put in the robot's order by its joint_names: a client filling a Sample from joint_states
        keeps the driver's order (a UR driver lists shoulder_pan_joint last), and taken as they
        came those readings would calibrate a different arm without any error. No joint_names:
        the positions are the robot's joints, base to tip (conventions.md)."""
        pose, stamp, q, spots = bag.sample_row_from_msg(msg, where)
        names = list(msg.joint_names)
        if not names:
            return pose, stamp, q, spots
        if len(names) != len(q):
            raise InputError(where, f"{len(names)} joint_names but {len(q)} joint_positions")
        try:
            order = joint_order(names, self.names, self.n, "the sample's joint_names")
        except ValueError as exc:
            # a D-H robot's joints under the arm's own names are taken in their order; some of the
            # robot's names among others is a mix-up, not another naming
            if self.strict or len(names) != self.n or not set(names).isdisjoint(self.names):
                raise InputError(where, str(exc)) from None
            order = list(range(self.n))
        return pose, stamp, q[order], spots
