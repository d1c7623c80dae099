"""The goal of a joint trajectory, under the acceptance rules of ros2_control's
joint_trajectory_controller (ROS-free; the arm_driver and the tests' stand-in
controller apply them, the sequencer sends what they accept).

The controller's ~/joint_trajectory topic (trajectory_msgs/JointTrajectory)
rejects a trajectory (joint_trajectory_controller validate_trajectory_msg, Jazzy):
- with joint names empty, or not all of the controller's joints (partial goals
  are off by default), or naming a joint it does not control;
- with no points;
- whose points' time_from_start do not strictly increase;
- whose point's positions are not one per joint name (velocities and
  accelerations: one per joint or none);
- whose last point has a non-zero velocity;
- whose header stamp is non-zero and whose end (stamp + last time_from_start)
  is already in the past.
Beyond the controller, a goal outside the joint limits or not finite is refused
(the hardware's limits; the controller leaves them to the hardware interface).
The arm moves to the last point's positions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


@dataclass(frozen=True)
class TrajectoryPoint:
    positions: Sequence[float]
    time_from_start: float            # s
    velocities: Sequence[float] = ()
    accelerations: Sequence[float] = ()


def trajectory_goal(names: Sequence[str], points: Sequence[TrajectoryPoint], joints: Sequence[str],
                    q_min: np.ndarray, q_max: np.ndarray, start_stamp: float = 0.0, now: float = 0.0) -> np.ndarray:
    """The goal (N,) in the order of ``joints``, or ValueError with the rule broken (one line)."""
    joints = list(joints)
    if not names:
        raise ValueError("empty joint names")
    if len(names) != len(joints) or len(set(names)) != len(names):
        raise ValueError(f"{len(names)} joint names, the controller has {len(joints)} "
                         f"({', '.join(joints)}): partial goals are not accepted")
    unknown = [name for name in names if name not in joints]
    if unknown:
        raise ValueError(f"joint '{unknown[0]}' is not a controller joint ({', '.join(joints)})")
    if not points:
        raise ValueError("empty trajectory (no points)")
    for i, point in enumerate(points):
        if i and not point.time_from_start > points[i - 1].time_from_start:
            raise ValueError(f"time_from_start not strictly increasing at point {i} "
                             f"({points[i - 1].time_from_start:g} s, then {point.time_from_start:g} s)")
        for field in ("positions", "velocities", "accelerations"):
            size = len(getattr(point, field))
            if size != len(names) and not (size == 0 and field != "positions"):
                raise ValueError(f"point {i}: {size} {field} for {len(names)} joint names")
    last = points[-1]
    if any(abs(v) > np.finfo(np.float32).eps for v in last.velocities):
        raise ValueError("the last point's velocity is not zero")
    if start_stamp != 0.0 and start_stamp + last.time_from_start < now:
        raise ValueError(f"the trajectory ends in the past (starts {start_stamp:.3f} s, now {now:.3f} s)")
    goal = np.empty(len(joints))
    for name, value in zip(names, last.positions):
        goal[joints.index(name)] = value
    if not np.isfinite(goal).all():
        raise ValueError(f"goal not finite: {goal.tolist()}")
    outside = (goal < q_min) | (goal > q_max)
    if outside.any():
        i = int(np.argmax(outside))
        raise ValueError(f"goal {joints[i]} = {goal[i]:.6g} rad outside the joint limits "
                         f"[{q_min[i]:.6g}, {q_max[i]:.6g}]")
    return goal


def joint_order(available: Sequence[str], wanted: Sequence[str] | None, n_joints: int,
                source: str = "joint_states", wanted_by: str = "parameter joint_names") -> list[int]:
    """Index into a message's joints (``available``: a joint_states message's, or a Sample's
    joint_names, named ``source`` in errors) of each robot joint, base to tip. ``wanted``: the
    robot's joint names (given by ``wanted_by``: a node's parameter, or the robot file for a
    command); None: ``available`` as it is, which must then hold exactly ``n_joints`` joints.
    ValueError in one line naming what is missing."""
    available = list(available)
    if wanted is None:
        if len(available) != n_joints:
            raise ValueError(f"{source} has {len(available)} joints ({', '.join(available)}), the robot "
                             f"{n_joints}: give parameter joint_names (the robot's joints, base to tip)")
        return list(range(n_joints))
    if len(wanted) != n_joints:
        raise ValueError(f"parameter joint_names: {len(wanted)} names, the robot has {n_joints} joints")
    missing = [name for name in wanted if name not in available]
    if missing:
        raise ValueError(f"joint '{missing[0]}' ({wanted_by}) is not in {source} "
                         f"({', '.join(available)})")
    # a robot joint named twice has two readings, and nothing tells which is the joint's: the first
    # was taken, silently (a Sample naming joint1 twice calibrated theta1 on the wrong reading)
    twice = [name for name in wanted if available.count(name) > 1]
    if twice:
        raise ValueError(f"joint '{twice[0]}' ({wanted_by}) is named twice in {source} "
                         f"({', '.join(available)}): which reading is it?")
    return [available.index(name) for name in wanted]


def move_time(current: np.ndarray, goal: np.ndarray, joint_speed: float, least: float = 0.1) -> float:
    """time_from_start (s) of a one-point move from current (N,) to goal (N,): the largest joint
    move at joint_speed rad/s, at least ``least`` s (a controller given 0 would jump)."""
    return max(least, float(np.max(np.abs(np.asarray(goal) - np.asarray(current)))) / joint_speed)
