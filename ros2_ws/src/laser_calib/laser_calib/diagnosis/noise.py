"""The noise in a fit's residual: its two components, and the scatter of
repeated poses.

The measurement covariance of a pose is spot^2 I + joint^2 G G^T (G = jac_q,
measurement.NoiseModel): spot noise on each coordinate, and joint-reading noise
moving the pose's spots together. When either is not given, it is estimated
by maximum likelihood from a fit's residuals; poses measured more than once
give the noise without any model (pure error).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
from scipy import optimize
from scipy.spatial import cKDTree

from laser_calib.measurement.base import NoiseModel, Residuals
from laser_calib.diagnosis.structure import Readings

REPEAT_TOLERANCE = 1e-4   # rad: readings this close count as the same pose


def repeat_groups(q: np.ndarray) -> np.ndarray:
    """(P,) group of each pose: poses whose readings agree within REPEAT_TOLERANCE.

    In row order, a pose not yet grouped starts a group of itself and every
    ungrouped pose within the tolerance of it; the neighbours come from a k-d
    tree (max-norm ball), so the cost grows as P log P, not P^2."""
    neighbours = cKDTree(q).query_ball_point(q, REPEAT_TOLERANCE, p=np.inf)
    group = -np.ones(len(q), int)
    n_groups = 0
    for p in range(len(q)):
        if group[p] < 0:
            near = np.asarray(neighbours[p], int)
            group[near[group[near] < 0]] = n_groups
            n_groups += 1
    return group


def pure_error(samples: Readings, res: Residuals, noise: NoiseModel) -> tuple[float, int, float]:
    """Scatter of repeated poses about their group means: (sum of squares of the
    whitened residuals, its degrees of freedom, the pooled RMS per coordinate in
    m). Poses with the same readings share their whitener, so the whitened
    differences are pure noise whatever the model. Groups whose members saw
    different spots are left out."""
    n_poses = res.r.shape[0]
    white = np.einsum("pij,pj->pi", noise.whitener(res), res.r.reshape(n_poses, -1))
    raw = res.r.reshape(n_poses, -1)
    mask = np.repeat(res.valid, res.r.shape[2], axis=1)
    group = repeat_groups(samples.q)
    squares = raw_squares = 0.0
    dof = 0
    for g in np.unique(group):
        members = np.flatnonzero(group == g)
        if len(members) < 2 or not (mask[members] == mask[members[0]]).all():
            continue
        seen = mask[members[0]]
        squares += float(((white[members] - white[members].mean(axis=0)) ** 2)[:, seen].sum())
        raw_squares += float(((raw[members] - raw[members].mean(axis=0)) ** 2)[:, seen].sum())
        dof += (len(members) - 1) * int(seen.sum())
    return squares, dof, math.sqrt(raw_squares / dof) if dof else 0.0


def deviance(res: Residuals, scale: float) -> Callable[[float, float], float]:
    """-2 log-likelihood (up to a constant) of a fit's residuals, scaled by
    ``scale`` (sqrt(M/dof): the fit took dof away), as a function of the spot
    (m) and joint-reading (rad) sigma: the pose covariance spot^2 I + joint^2
    G G^T (G = jac_q, as in measurement.NoiseModel)."""
    n_poses = res.r.shape[0]
    m = res.r.shape[1] * res.r.shape[2]
    r = res.r.reshape(n_poses, m) * scale
    mask = np.repeat(res.valid, res.r.shape[2], axis=1)
    g = res.jac_q.reshape(n_poses, m, -1) * mask[..., None]
    outer = np.einsum("pin,pjn->pij", g, g)
    idx = np.nonzero(~mask)

    def value(s: float, j: float) -> float:
        cov = s ** 2 * np.eye(m) + j ** 2 * outer
        cov[~mask] = 0.0
        cov.transpose(0, 2, 1)[~mask] = 0.0
        cov[idx[0], idx[1], idx[1]] = 1.0
        _, logdet = np.linalg.slogdet(cov)
        return float(logdet.sum() + np.einsum("pi,pi->", r, np.linalg.solve(cov, r[..., None])[..., 0]))

    return value


def noise_components(res: Residuals, scale: float, spot: float | None, joint: float | None) -> tuple[float, float]:
    """Maximum-likelihood spot (m) and joint-reading (rad) noise of a fit's
    residuals (deviance); the given ones are held, the None ones estimated.
    Residuals are scaled by ``scale`` (sqrt(M/dof): the fit took dof away)."""
    free = [spot is None, joint is None]
    value = deviance(res, scale)

    def unpack(theta: np.ndarray) -> tuple[float, float]:
        values = iter(np.exp(theta))
        return (next(values) if free[0] else spot), (next(values) if free[1] else joint)

    def negative_log_likelihood(theta: np.ndarray) -> float:
        return value(*unpack(np.atleast_1d(theta)))

    mask = np.repeat(res.valid, res.r.shape[2], axis=1)
    rms = float(np.sqrt(np.mean((res.r.reshape(len(mask), -1) * scale)[mask] ** 2))) if mask.any() else 1e-3
    if free == [False, False]:
        return spot, joint
    if sum(free) == 1:
        bounds = (math.log(1e-7), math.log(0.05)) if free[1] else (math.log(rms * 1e-3), math.log(rms * 10))
        found = optimize.minimize_scalar(negative_log_likelihood, bounds=bounds, method="bounded")
        return unpack(np.array([found.x]))
    # Start with everything in the spot noise and a small joint noise; Nelder-Mead in log space.
    found = optimize.minimize(negative_log_likelihood, np.log([rms, 1e-4]), method="Nelder-Mead",
                              options={"xatol": 1e-3, "fatol": 1e-6})
    return unpack(found.x)
