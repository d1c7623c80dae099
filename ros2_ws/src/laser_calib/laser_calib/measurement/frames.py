"""Fixed frames around the arm, known roughly and estimated with the D-H errors.

Three frames close the loop from a sensor to what it measures:

    sensor: the sensor in the world frame        (a camera, a laser tracker)
    base:   the robot's frame {0} in the world   (often known: fix it)
    target: the target (or marker) in the tool frame, the end of the robot
            chain (the SLM frame; the last link when the robot file's slm is zero)

Each is an initial guess G (robot file key ``frames``) with a 6-parameter error
on top of it, applied in the frame's own axes:

    frame = parent · G · Trans(x,dx) Trans(y,dy) Trans(z,dz) Rot(x,drx) Rot(y,dry) Rot(z,drz)

Like the D-H errors, each parameter is the argument of one elementary
transform, so its twist is exact at any size (the guess may be rough).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace
from typing import Any, Mapping

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.model.robot import Robot, plausible_length
from laser_calib.measurement.rotations import matrix_to_quaternion, quaternion_to_matrix

FRAMES = ("sensor", "base", "target")
FRAME_PARAMS = ("x", "y", "z", "rx", "ry", "rz")
POSE_KEYS = ("x", "y", "z", "qw", "qx", "qy", "qz")
_FRAME_NAME = re.compile(r"(sensor|base|target\d*)_(" + "|".join(FRAME_PARAMS) + ")")


def is_frame_param(name: str) -> bool:
    """Whole names (sensor_x, target2_rz): a URDF joint may be called base_joint."""
    return _FRAME_NAME.fullmatch(name) is not None


@dataclass(frozen=True)
class Pose:
    """A rigid transform: rotation (3,3) and translation (3,) in m."""

    rotation: np.ndarray
    translation: np.ndarray

    @staticmethod
    def identity() -> "Pose":
        return Pose(np.eye(3), np.zeros(3))

    @staticmethod
    def from_values(values: np.ndarray) -> "Pose":
        """From (x, y, z, qw, qx, qy, qz); the quaternion is normalised."""
        values = np.asarray(values, float)
        return Pose(quaternion_to_matrix(values[3:]), values[:3].copy())

    def values(self) -> np.ndarray:
        """(x, y, z, qw, qx, qy, qz), shape (7,)."""
        return np.concatenate([self.translation, matrix_to_quaternion(self.rotation)])

    def perturbed(self, delta: np.ndarray) -> "Pose":
        """self · E(delta) for one 6-vector delta (the frame with its error applied)."""
        rotation, translation, _ = perturb(self.rotation[None], self.translation[None], Pose.identity(),
                                           np.asarray(delta, float)[None])
        return Pose(rotation[0], translation[0])


def frame_names(frame: str) -> tuple[str, ...]:
    """Parameter names of one frame: 'sensor_x' ... 'sensor_rz'."""
    return tuple(f"{frame}_{p}" for p in FRAME_PARAMS)


def _elementary(axis: int, angle: np.ndarray) -> np.ndarray:
    """Rot(axis, angle) for angles (P,), shape (P,3,3)."""
    c, s = np.cos(angle), np.sin(angle)
    i, j = {0: (1, 2), 1: (2, 0), 2: (0, 1)}[axis]
    out = np.broadcast_to(np.eye(3), angle.shape + (3, 3)).copy()
    out[:, i, i], out[:, i, j], out[:, j, i], out[:, j, j] = c, -s, s, c
    return out


def perturb(parent_rotation: np.ndarray, parent_origin: np.ndarray, guess: Pose,
            delta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The frame parent · guess · E(delta) at P poses, and its twists.

    parent_rotation (P,3,3), parent_origin (P,3) in the reference coordinates;
    delta (P,6) (dx, dy, dz in m; drx, dry, drz in rad). Returns rotation
    (P,3,3), origin (P,3) and twists (P,6,6): the motion (v; w) of the frame's
    origin, in the reference coordinates, per unit of each delta. The rotations
    come after the translations, about axes through the final origin, so they
    do not move it (v = 0).
    """
    rotation = parent_rotation @ guess.rotation
    origin = parent_origin + parent_rotation @ guess.translation + np.einsum("pij,pj->pi", rotation, delta[:, :3])
    n = len(delta)
    twists = np.zeros((n, 6, 6))
    twists[:, :3, :3] = rotation
    for axis in range(3):
        twists[:, 3:, 3 + axis] = rotation[:, :, axis]
        rotation = rotation @ _elementary(axis, delta[:, 3 + axis])
    return rotation, origin, twists


def _pose_from_mapping(where: str, mapping: Any) -> Pose:
    if not isinstance(mapping, Mapping):
        raise InputError(where, f"expected a mapping with keys {', '.join(POSE_KEYS)}")
    values = []
    for key in POSE_KEYS:
        value = mapping.get(key, 1.0 if key == "qw" else 0.0)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(f"{where}.{key}", f"expected a finite number, got {value!r}")
        values.append(plausible_length(f"{where}.{key}", float(value)) if key in ("x", "y", "z") else float(value))
    unknown = set(mapping) - set(POSE_KEYS)
    if unknown:
        raise InputError(where, f"unknown key '{sorted(unknown)[0]}' (expected {', '.join(POSE_KEYS)})")
    norm = np.linalg.norm(values[3:])
    if not 0.5 < norm < 1.5:
        raise InputError(where, f"quaternion norm {norm:.4g} is not near 1")
    return Pose.from_values(np.array(values))


def frame_list(robot: Robot) -> tuple[str, ...]:
    """sensor, base and one target frame per measured tip: target, target2, ... (a tree)."""
    n_tips = 1 if robot.chain is None else len(robot.chain.tips)
    return FRAMES + tuple(f"target{k + 1}" for k in range(1, n_tips))


def target_frame(tip: int) -> str:
    return "target" if tip == 0 else f"target{tip + 1}"


def robot_frames(robot: Robot, source: str = "<robot>") -> dict[str, Pose]:
    """The frame guesses of a robot file (key ``frames``); a missing frame is the identity."""
    data = robot.extra.get("frames", {})
    if not isinstance(data, Mapping):
        raise InputError(f"{source}: frames", "expected a mapping of sensor / base / target poses")
    names = frame_list(robot)
    unknown = set(data) - set(names)
    if unknown:
        raise InputError(f"{source}: frames", f"unknown frame '{sorted(unknown)[0]}' (expected {', '.join(names)})")
    return {name: _pose_from_mapping(f"{source}: frames.{name}", data[name]) if name in data else Pose.identity()
            for name in names}


def with_frames(robot: Robot, frames: Mapping[str, Pose]) -> Robot:
    """The robot with its ``frames`` key replaced (full precision, qw >= 0)."""
    data = {name: dict(zip(POSE_KEYS, map(float, frames[name].values()))) for name in frame_list(robot)
            if name in frames}
    return replace(robot, extra={**robot.extra, "frames": data})
