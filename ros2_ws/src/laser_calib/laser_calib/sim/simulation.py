"""Simulated calibration sessions (paper sections IV and V), seeded.

A session: a true robot (nominal + errors), joint readings q at poses whose two
beams both hit the screen, the true joints q + disturbance, and the measured
spots (true robot at the true joints, plus spot noise). The noise-free truth at
the readings (true robot at q) is kept beside, to measure estimation error
without the measurement noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from typing import Callable

import numpy as np

from laser_calib.model.kinematics import predict, usable
from laser_calib.model.robot import Robot
from laser_calib.model.robot_file import load_robot
from laser_calib.io.samples import Samples

SMALL_RANGE = np.deg2rad(10.0)
CASES = ("paper-7dof", "paper-4dof")
ROBOT_FILES = {"paper-7dof": "humanoid_arm_7dof.yaml", "paper-4dof": "manipulator_4dof.yaml"}
# Poses per span (small-range, whole-workspace): paper IV-B (7-DOF), V-B (4-DOF).
CASE_POSES = {"paper-7dof": 30, "paper-4dof": 25}


@dataclass(frozen=True)
class NoiseSpec:
    """Half-widths of uniform noise, as in the paper: spot (m), joint disturbance (rad).

    ``sigma`` gives the standard deviations the estimators need (uniform: w / sqrt(3)).
    """

    spot: float = 0.002
    joint: float = float(np.deg2rad(0.1))
    distribution: str = "uniform"

    def draw(self, rng: np.random.Generator, half_width: float, shape) -> np.ndarray:
        if self.distribution == "uniform":
            return rng.uniform(-half_width, half_width, shape)
        return rng.normal(0.0, half_width, shape)

    @property
    def spot_sigma(self) -> float:
        return self.spot / np.sqrt(3) if self.distribution == "uniform" else self.spot

    @property
    def joint_sigma(self) -> float:
        return self.joint / np.sqrt(3) if self.distribution == "uniform" else self.joint


def bundled_robot(case: str) -> Robot:
    """Nominal model of one of the paper's arms, shipped with the package."""
    with resources.as_file(resources.files("laser_calib") / "model" / "robots" / ROBOT_FILES[case]) as path:
        return load_robot(path)


def true_errors(robot: Robot, rng: np.random.Generator | None = None, length: float = 0.010,
                angle: float = float(np.deg2rad(1.0))) -> np.ndarray:
    """The paper's true errors: every length +10 mm and every angle +1 deg; with
    rng, each error uniform in [-size, +size] instead."""
    size = np.where(robot.param_kinds() == "length", length, angle)
    if rng is None:
        return size
    return rng.uniform(-size, size)


def sample_poses(robots: list[Robot], n: int, rng: np.random.Generator, span: str = "whole",
                 margin: float = 0.02, max_tries: int = 200) -> np.ndarray:
    """n joint readings (n,N) uniform in the joint ranges (span 'whole') or within
    +-10 deg of zero (span 'small'; of its range's end nearest zero for a joint whose
    range excludes zero), keeping only poses every given robot can take (kinematics.usable:
    both beams at least ``margin`` m inside the screen's edge, the arm on its side)."""
    robot = robots[0]
    low, high = robot.pose_range()
    if span == "small":
        nearest_zero = np.clip(0.0, low, high)
        low, high = np.maximum(low, nearest_zero - SMALL_RANGE), np.minimum(high, nearest_zero + SMALL_RANGE)
    elif span != "whole":
        raise ValueError(f"unknown span {span!r}")
    chosen: list[np.ndarray] = []
    for _ in range(max_tries):
        q = rng.uniform(low, high, (max(4 * n, 64), robot.n_joints))
        ok = np.ones(len(q), bool)
        for r in robots:
            ok &= usable(r, predict(r, q), margin)
        chosen.extend(q[ok])
        if len(chosen) >= n:
            return np.array(chosen[:n])
    raise RuntimeError(f"found only {len(chosen)} of {n} poses with both beams on the screen ({span})")


# An optional hook for physical effects beyond the geometric model: given the
# true robot and the session context, it returns per-pose error offsets (P,n)
# added to the true errors, and may transform the true spots (P,2,2).
ParamOffsets = Callable[[Robot, Samples], np.ndarray]
SpotTransform = Callable[[Robot, Samples, np.ndarray], np.ndarray]


def measure(true_robot: Robot, q: np.ndarray, rng: np.random.Generator, noise: NoiseSpec,
            stamps: np.ndarray | None = None, extra: dict[str, np.ndarray] | None = None,
            param_offsets: ParamOffsets | None = None, spot_transform: SpotTransform | None = None,
            first_pose: int = 0) -> tuple[Samples, Samples]:
    """Measured samples and the noise-free truth at the readings q (P,N).

    Spots the true beams do not put on the screen are missing (NaN), as a camera
    would report them.
    """
    q = np.asarray(q, dtype=float)
    n = len(q)
    stamps = np.arange(n) * 5.0 if stamps is None else np.asarray(stamps, float)
    context = Samples(np.arange(first_pose, first_pose + n), stamps, q, np.full((n, 2, 2), np.nan),
                      dict(extra or {}))
    offsets = np.zeros((n, true_robot.n_params)) if param_offsets is None else param_offsets(true_robot, context)
    disturbance = noise.draw(rng, noise.joint, q.shape)
    # The arm sits at q + disturbance (a mimic joint follows its source's).
    actual = predict(true_robot, q + disturbance, offsets)
    truth = predict(true_robot, q, offsets)
    actual_spots, truth_spots = actual.spots, truth.spots
    if spot_transform is not None:
        actual_spots = spot_transform(true_robot, context, actual_spots)
        truth_spots = spot_transform(true_robot, context, truth_spots)
    measured = actual_spots + noise.draw(rng, noise.spot, actual_spots.shape)
    measured = np.where(actual.hit[..., None], measured, np.nan)
    truth_spots = np.where(actual.hit[..., None], truth_spots, np.nan)
    return (Samples(context.pose, stamps, q, measured, dict(context.extra)),
            Samples(context.pose, stamps, q, truth_spots, dict(context.extra)))


@dataclass(frozen=True)
class Session:
    """A simulated session: nominal and true robot, all poses (small-range first,
    then whole-workspace), their measurements and noise-free truth, and the
    calibration/test split of each of the paper's cases."""

    nominal: Robot
    true: Robot
    errors: np.ndarray
    samples: Samples
    truth: Samples
    cases: dict[str, tuple[np.ndarray, np.ndarray]]
    noise: NoiseSpec


def paper_cases(n_small: int, n_whole: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Index sets (calibration, test) of the paper's cases over n_small small-range
    poses followed by n_whole whole-workspace poses (section IV-B):
    1: calibrate on the small range, test on the whole workspace;
    2: half of each as calibration, the other halves as test;
    3: everything as calibration, no test set."""
    small = np.arange(n_small)
    whole = n_small + np.arange(n_whole)
    half_s, half_w = n_small // 2, n_whole // 2
    case2_cal = np.concatenate([small[:half_s], whole[:half_w]])
    case2_test = np.concatenate([small[half_s:], whole[half_w:]])
    return {"case1": (small, whole), "case2": (case2_cal, case2_test),
            "case3": (np.concatenate([small, whole]), np.array([], int))}


def paper_session(case: str, seed: int, n_per_span: int | None = None, noise: NoiseSpec = NoiseSpec(),
                  random_errors: bool = False, param_offsets: ParamOffsets | None = None,
                  spot_transform: SpotTransform | None = None) -> Session:
    if case not in CASES:
        raise ValueError(f"unknown case {case!r}; expected one of {', '.join(CASES)}")
    return robot_session(bundled_robot(case), seed, n_per_span or CASE_POSES[case], noise, random_errors,
                         param_offsets, spot_transform)


def robot_session(nominal: Robot, seed: int, n_per_span: int, noise: NoiseSpec = NoiseSpec(),
                  random_errors: bool = False, param_offsets: ParamOffsets | None = None,
                  spot_transform: SpotTransform | None = None) -> Session:
    """The paper's session (n_per_span small-range, then n_per_span whole-workspace
    poses, its cases) of any robot with lasers."""
    rng = np.random.default_rng(seed)
    errors = true_errors(nominal, rng if random_errors else None)
    true = nominal.with_errors(errors)
    q = np.vstack([sample_poses([nominal, true], n_per_span, rng, "small"),
                   sample_poses([nominal, true], n_per_span, rng, "whole")])
    samples, truth = measure(true, q, rng, noise, param_offsets=param_offsets, spot_transform=spot_transform)
    return Session(nominal, true, errors, samples, truth, paper_cases(n_per_span, n_per_span), noise)
