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

from laser_calib_nodes.parameters import NodeError


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


class ArmJointStates:
    """The sequencer's reading of joint_states. The topic may have more than one publisher (the
    arm's broadcaster and a gripper's driver, a second arm): each message's robot joints are found
    by its own names (one order per set of names), and a message without them is another
    publisher's, ignored with one WARN per set of names. Before, the first message's order was
    applied to every message: a gripper's one-joint message ended the session in an IndexError
    traceback, and another publisher's readings under other names were taken for the arm's.
    names: the robot's joint names (joint_names, or a URDF arm's); None: the first message with
    exactly the robot's joint count names them (a D-H robot), and later sets must hold those."""

    def __init__(self, names: list[str] | None, n_joints: int, logger):
        self.names = list(names) if names else None
        self.wanted_by = "parameter joint_names" if names else "the robot's joints"
        self.n, self.logger = n_joints, logger
        self.orders: dict[tuple, list[int] | str] = {}  # (names, positions count) -> order, or why ignored
        self.refused: str | None = None                # why the last message ignored was

    def read(self, msg: JointState) -> tuple[np.ndarray, np.ndarray | None] | None:
        """The robot's q (N,) and velocities (N,) or None (none in the message); None: ignored."""
        names, count = list(msg.name), len(msg.position)
        order = self.orders.get((tuple(names), count))
        if order is None:
            order = self.orders[(tuple(names), count)] = self._order(names, count)
        if isinstance(order, str):
            self.refused = order
            return None
        v = np.array(msg.velocity, dtype=float)[order] if len(msg.velocity) == count else None
        return np.array(msg.position, dtype=float)[order], v

    def _order(self, names: list[str], count: int) -> list[int] | str:
        try:
            if count != len(names):
                raise ValueError(f"joint_states has {len(names)} names and {count} positions")
            order = joint_order(names, self.names, self.n, wanted_by=self.wanted_by)
        except ValueError as exc:
            self.logger.warning(f"joint_states message ignored (another publisher's? said once per set of "
                                f"names): {exc}")
            return str(exc)
        if self.names is None:
            self.names = [names[i] for i in order]
        return order

    def none_read(self, topic: str, timeout: float) -> None:
        """No message with the robot's joints within timeout s: NodeError, exit 2 with why the last
        message was ignored (joint_names missing or wrong), else exit 3 (no joint states at all)."""
        if self.refused is not None:
            raise NodeError(f"{self.refused}; no joint_states on {topic} had the robot's joints in {timeout:g} s", 2)
        raise NodeError(f"no joint states on {topic} after {timeout:g} s (is the arm driver running?)", 3)
