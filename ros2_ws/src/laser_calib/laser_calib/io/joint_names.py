"""The robot's joints as messages name them, and a Sample's joint_positions put in the robot's
order by its joint_names (the sequencer's rule, hardware.trajectory.joint_order): the estimator
node's samples and every session bag read (estimate --bag, a resumed session) follow one rule.
A client filling a Sample from joint_states keeps the driver's order (a UR driver lists
shoulder_pan_joint last); taken as they came, those readings would calibrate a different arm
without any error."""

from __future__ import annotations

import re
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


def named_twice(names: Sequence[str]) -> str | None:
    """The first name the list holds a second time, or None."""
    return next((name for k, name in enumerate(names) if name in names[:k]), None)


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
        twice = named_twice(self.names)
        if twice:  # two robot joints read from one entry: another joint's readings left out
            raise InputError(self.named_by, f"names '{twice}' twice")

    def naming_warnings(self, name_lists: Sequence[Sequence[str]], where: str) -> list[str]:
        """What a set of samples' joint_names (``name_lists``, each sample's) says that is no error but
        must be said: joints named that are none of the robot's, among the samples read by name (a
        gripper in joint_states, or the readings of a longer arm whose first joints' names this one
        shares); samples naming none of a D-H robot's joints, taken in its order, beside samples
        that name them (two sources mixed)."""
        by_name = [bool(names) and (self.strict or not set(names).isdisjoint(self.names)) for names in name_lists]
        unused = dict.fromkeys(name for names, named in zip(name_lists, by_name) if named
                               for name in names if name not in self.names)
        in_order = [k for k, (names, named) in enumerate(zip(name_lists, by_name)) if names and not named]
        said = []
        if unused:
            said.append(f"{where}: the samples also name {', '.join(unused)}, which {self.named_by} does not "
                        "have: those readings are not used (the bag of another arm?)")
        if in_order and any(by_name):
            said.append(f"{where}: {len(in_order)} of {len(name_lists)} samples (the first: sample {in_order[0] + 1}) "
                        f"name none of the joints of {self.named_by} and were taken in its order, while the others "
                        "name them (samples of two sources mixed?)")
        return said

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
        # two readings under one name, whatever the names: taken in order (a D-H robot's under names not
        # its own), the sample's own naming was wrong without a word
        twice = named_twice(names)
        if twice:
            raise InputError(where, f"joint '{twice}' is named twice in the sample's joint_names")
        if not self.strict:  # joint1..jointN: a jointK beyond them is a longer arm's, not a gripper
            beyond = [name for name in names if name not in self.names and re.fullmatch(r"joint\d+", name)]
            if beyond:
                raise InputError(where, f"joint '{beyond[0]}' is beyond the {self.n} joints of {self.named_by} "
                                        f"(joint1 .. joint{self.n}): the readings of a longer arm?")
        try:
            order = joint_order(names, self.names, self.n, "the sample's joint_names", self.named_by)
        except ValueError as exc:
            # a D-H robot's joints under the arm's own names are taken in their order; some of the
            # robot's names among others is a mix-up, not another naming
            if self.strict or len(names) != self.n or not set(names).isdisjoint(self.names):
                raise InputError(where, str(exc)) from None
            order = list(range(self.n))
        return positions[order]
