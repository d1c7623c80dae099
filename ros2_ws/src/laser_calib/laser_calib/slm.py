"""Pre-calibration of the laser angles (paper section V, Fig. 6, eq. 16).

The SLM is held on a fixture with its z axis along the screen normal and its
x, y axes along the screen's u, v axes, at known distances D from the screen.
A laser with T_L = Rot(x, gamma) Rot(y, beta) has the direction
(sin b, -sin g cos b, cos g cos b) in the SLM frame, so its spot moves with
the distance as

    u(D) = u0 + D tan(beta) / cos(gamma),     v(D) = v0 - D tan(gamma).

The offsets u0, v0 (where the fixture puts the laser) are unknown; straight-
line fits over two or more distances give the slopes, hence gamma and beta,
and their standard deviations by first-order propagation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.model.robot import Laser, Robot
from laser_calib.io.read import csv_rows, length_units, parse_int, parse_number, read_text
from laser_calib.io.samples import MAX_DISTANCE

COLUMNS = ("laser", "distance", "u", "v")


@dataclass(frozen=True)
class LaserAngles:
    gamma: float
    beta: float
    gamma_std: float
    beta_std: float
    n: int


def _slope(distance: np.ndarray, value: np.ndarray, sigma: float | None) -> tuple[float, float]:
    """Least-squares slope of value against distance and its std (from sigma, or
    from the residual when there are more than two distances)."""
    design = np.column_stack([distance, np.ones_like(distance)])
    coef, *_ = np.linalg.lstsq(design, value, rcond=None)
    cov_unit = np.linalg.inv(design.T @ design)
    if sigma is None:
        dof = len(distance) - 2
        if dof < 1:
            raise ValueError("with spots at only two distances the slope's error is unknown: give --spot-sigma "
                             "or measure at three or more distances")
        resid = value - design @ coef
        sigma = float(np.sqrt(resid @ resid / dof))
    return float(coef[0]), float(sigma * np.sqrt(cov_unit[0, 0]))


def fit_laser(distance: np.ndarray, uv: np.ndarray, sigma: float | None = None) -> LaserAngles:
    """Angles of one laser from spots uv (K,2) in m at distances (K,) in m."""
    if len(np.unique(distance)) < 2:
        raise ValueError("the spots must be measured at two or more different distances")
    s_u, s_u_std = _slope(distance, uv[:, 0], sigma)
    s_v, s_v_std = _slope(distance, uv[:, 1], sigma)
    gamma = -math.atan(s_v)
    gamma_std = s_v_std / (1 + s_v ** 2)
    t = s_u * math.cos(gamma)                          # tan(beta)
    beta = math.atan(t)
    # d t = cos(gamma) d s_u - s_u sin(gamma) d gamma
    t_std = math.hypot(math.cos(gamma) * s_u_std, s_u * math.sin(gamma) * gamma_std)
    return LaserAngles(gamma, beta, gamma_std, t_std / (1 + t ** 2), len(distance))


def _check_distance(distance: float, where: str) -> None:
    """A fixture distance is positive, and no fixture holds the SLM over MAX_DISTANCE
    (as a sensor's target distance) from the screen: such a value is in millimetres."""
    if distance <= 0:
        raise InputError(where, f"must be positive, got {distance}")
    if distance > MAX_DISTANCE:
        raise InputError(where, f"{distance:g} m is not a plausible fixture distance: distances are in metres "
                                f"(this looks like {length_units(distance, MAX_DISTANCE)})")


def load_measurements(path: str | Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """CSV with header laser,distance,u,v (laser 1 or 2; metres) -> {laser: (D (K,), uv (K,2))}."""
    path = Path(path)
    rows = csv_rows(read_text(path), str(path))
    if not rows or tuple(c.strip() for c in rows[0]) != COLUMNS:
        raise InputError(f"{path}: header", f"expected {','.join(COLUMNS)}")
    data: dict[int, list[tuple[float, float, float]]] = {1: [], 2: []}
    for line, row in enumerate(rows[1:], start=2):
        if not any(cell.strip() for cell in row):
            continue
        if len(row) != 4:
            raise InputError(f"{path}: line {line}", f"{len(row)} fields, expected 4")
        laser = parse_int(row[0], f"{path}: line {line}, field laser")
        if laser not in data:
            raise InputError(f"{path}: line {line}, field laser", f"expected 1 or 2, got {laser}")
        values = [parse_number(cell, f"{path}: line {line}, field {name}") for name, cell in zip(COLUMNS[1:], row[1:])]
        _check_distance(values[0], f"{path}: line {line}, field distance")
        data[laser].append(tuple(values))
    out = {}
    for laser, entries in data.items():
        if len({e[0] for e in entries}) < 2:
            raise InputError(str(path), f"laser {laser} needs spots at two or more different distances")
        arr = np.array(entries)
        out[laser] = (arr[:, 0], arr[:, 1:])
    return out


def calibrate(robot: Robot, measurements: dict[int, tuple[np.ndarray, np.ndarray]],
              sigma: float | None = None) -> tuple[Robot, list[LaserAngles]]:
    """The robot with its laser angles replaced by the fitted ones."""
    angles = [fit_laser(*measurements[j + 1], sigma) for j in range(2)]
    lasers = tuple(Laser(a.gamma, a.beta) for a in angles)
    return replace(robot, lasers=lasers), angles
