"""The robot's joints as messages name them, and a Sample's joint_positions put in the robot's
order by its joint_names (the sequencer's rule, hardware.trajectory.joint_order): the estimator
node's samples and every session bag read (estimate --bag, a resumed session) follow one rule.
A client filling a Sample from joint_states keeps the driver's order (a UR driver lists
shoulder_pan_joint last); taken as they came, those readings would calibrate a different arm
without any error."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from laser_calib.hardware.trajectory import joint_order
from laser_calib.io.errors import InputError
from laser_calib.model.robot import Robot


def default_joint_names(robot: Robot) -> list[str]:
    """A URDF robot's read joints by their URDF names; a D-H robot's joint1..jointN."""
    if robot.chain is not None:
        return list(robot.chain.readings)
    return [f"joint{i + 1}" for i in range(robot.n_joints)]


class RobotJoints:
    def __init__(self, robot: Robot, names: Sequence[str] = (), named_by: str | None = None):
        """names: the robot's joints, base to tip, as messages name them (empty: its default
        names); named_by: where they were given, for error lines (default: the robot)."""
        self.n = robot.n_joints
        self.names = list(names) if names else default_joint_names(robot)
        self.named_by = named_by or f"robot '{robot.name}'"
        # D-H robot, no joint_names given: its joints have no names of their own to insist on
        self.strict = bool(names) or robot.chain is not None
        if len(self.names) != self.n:
            raise InputError(self.named_by, f"{len(self.names)} names, robot '{robot.name}' has {self.n} joints")

    def sample_positions(self, names: Sequence[str], positions: np.ndarray, where: str) -> np.ndarray:
        """A Sample's joint_positions (named by its joint_names, ``names``) as the robot's q (N,),
        base to tip. No names: the positions are the robot's joints in order (conventions.md).
        InputError naming ``where``: a robot joint missing from the names, or names and
        positions of different lengths."""
        names = list(names)
        if not names:
            return positions
        if len(names) != len(positions):
            raise InputError(where, f"{len(names)} joint_names but {len(positions)} joint_positions")
        try:
            order = joint_order(names, self.names, self.n, "the sample's joint_names", self.named_by)
        except ValueError as exc:
            # a D-H robot's joints under the arm's own names are taken in their order; some of the
            # robot's names among others is a mix-up, not another naming
            if self.strict or len(names) != self.n or not set(names).isdisjoint(self.names):
                raise InputError(where, str(exc)) from None
            order = list(range(self.n))
        return positions[order]
