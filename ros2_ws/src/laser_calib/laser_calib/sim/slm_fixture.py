"""Simulated SLM fixture measurements (paper eq. 16): each laser's spot on a plane at known
distances, as `laser-calib slm-calibrate` reads them, for its tests and rate bench."""

from __future__ import annotations

import numpy as np

from laser_calib.model.kinematics import rot_x, rot_y
from laser_calib.model.robot import Robot


def fixture_spots(robot: Robot, seed: int, distances: tuple[float, ...], noise: float) -> list[list]:
    """[laser, distance, u, v] rows (m) of the robot's two beams, each from a random point of the
    fixture within 5 cm of its axis, with Gaussian noise ``noise`` (m) per coordinate."""
    rng = np.random.default_rng(seed)
    rows = []
    for j, (gamma, beta) in enumerate(robot.laser_angles()):
        direction = rot_x(gamma) @ rot_y(beta) @ np.array([0.0, 0.0, 1.0])
        offset = rng.uniform(-0.05, 0.05, 2)
        for distance in distances:
            u, v = offset + distance * direction[:2] / direction[2] + rng.normal(0, noise, 2)
            rows.append([j + 1, distance, float(u), float(v)])
    return rows
