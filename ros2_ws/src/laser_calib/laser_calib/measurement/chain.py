"""The closed loop sensor -> world -> robot base -> tool -> target, and its twists.

The target's pose in the sensor frame is

    T_sensor_target = inv(T_world_sensor) · T_world_base · T_base_tool(q) · T_tool_target

with T_base_tool the robot chain (kinematics.forward, either D-H convention)
and the three fixed frames of frames.py. Parameters, in this order:

    x = [robot errors (4N+5), sensor (6), base (6), target (6)]     shape (4N+23,)

(a robot without lasers has 4N robot errors, one of joint placements its own,
joint_chain.py; a tree of several tips one target frame per tip, target2, ...
after target, each pose measuring one tip).

Each parameter's twist is the motion (v; w) of the target frame relative to
the sensor, in sensor coordinates, per unit of that parameter: the robot's
Jac_1 and the frames' elementary twists carried to the target origin with
v' = v + w x (p_target - o), and a sensor motion entering with the opposite sign.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from laser_calib.model.kinematics import forward
from laser_calib.model.robot import Robot
from laser_calib.measurement.frames import Pose, frame_list, frame_names, perturb, target_frame


def chain_names(robot: Robot) -> tuple[str, ...]:
    """Names of the full parameter vector, (n_params + 6 F,) over the F frames of frame_list."""
    return robot.param_names + tuple(n for frame in frame_list(robot) for n in frame_names(frame))


def frame_slice(robot: Robot, frame: str) -> slice:
    start = robot.n_params + 6 * frame_list(robot).index(frame)
    return slice(start, start + 6)


@dataclass(frozen=True)
class TargetState:
    """rotation (P,3,3) and position (P,3) m of the target in the sensor frame;
    twists (P,6,n) or None, n = 4N+23 (see the module docstring)."""

    rotation: np.ndarray
    position: np.ndarray
    twists: np.ndarray | None


def _carry(twists: np.ndarray, lever: np.ndarray) -> np.ndarray:
    """Twists (P,6,k) of a frame at o to those of a point at o + lever (P,3)."""
    out = twists.copy()
    out[:, :3] += np.cross(twists[:, 3:], lever[:, :, None], axis=1)
    return out


def target_in_sensor(robot: Robot, frames: dict[str, Pose], q: np.ndarray, x: np.ndarray,
                     twists: bool = False, tips: np.ndarray | None = None) -> TargetState:
    """The target pose in the sensor frame at joint readings q (P,N) with
    parameters x (n,) or per pose (P,n); tips (P,) which tip of a tree each pose
    measures (its own target frame), None for the first."""
    q = np.atleast_2d(np.asarray(q, float))
    n_poses = len(q)
    x = np.broadcast_to(np.asarray(x, float), (n_poses, len(chain_names(robot))))
    if tips is None:
        return _one_tip(robot, frames, q, x, twists, 0)
    rotation, position = np.empty((n_poses, 3, 3)), np.empty((n_poses, 3))
    jac = np.zeros((n_poses, 6, x.shape[1])) if twists else None
    for tip in np.unique(tips):
        rows = tips == tip
        state = _one_tip(robot, frames, q[rows], x[rows], twists, int(tip))
        rotation[rows], position[rows] = state.rotation, state.position
        if twists:
            jac[rows] = state.twists
    return TargetState(rotation, position, jac)


def _one_tip(robot: Robot, frames: dict[str, Pose], q: np.ndarray, x: np.ndarray, twists: bool,
             tip: int) -> TargetState:
    n_poses = len(q)
    target = target_frame(tip)
    delta = {frame: x[:, frame_slice(robot, frame)] for frame in ("sensor", "base", target)}
    identity = np.broadcast_to(np.eye(3), (n_poses, 3, 3))
    zero = np.zeros((n_poses, 3))

    arm = forward(robot, q, x[:, :robot.n_params], twists=twists, tip=tip)
    base_r, base_o, base_t = perturb(identity, zero, frames["base"], delta["base"])
    tool_r = base_r @ arm.rotation
    tool_o = base_o + np.einsum("pij,pj->pi", base_r, arm.origin)
    target_r, target_o, target_t = perturb(tool_r, tool_o, frames[target], delta[target])
    sensor_r, sensor_o, sensor_t = perturb(identity, zero, frames["sensor"], delta["sensor"])

    to_sensor = sensor_r.transpose(0, 2, 1)
    rotation = to_sensor @ target_r
    position = np.einsum("pij,pj->pi", to_sensor, target_o - sensor_o)
    jac = None
    if twists:
        # Robot twists are in base coordinates at the tool origin: rotate, then carry.
        arm_world = np.concatenate([base_r @ arm.twists[:, :3], base_r @ arm.twists[:, 3:]], axis=1)
        world = np.zeros((n_poses, 6, x.shape[1]))  # other tips' target frames do not move this one
        world[:, :, :robot.n_params] = _carry(arm_world, target_o - tool_o)
        world[:, :, frame_slice(robot, "sensor")] = -_carry(sensor_t, target_o - sensor_o)
        world[:, :, frame_slice(robot, "base")] = _carry(base_t, target_o - base_o)
        world[:, :, frame_slice(robot, target)] = target_t
        jac = np.concatenate([to_sensor @ world[:, :3], to_sensor @ world[:, 3:]], axis=1)
    return TargetState(rotation, position, jac)
