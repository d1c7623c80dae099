"""The scatter of repeated poses: the noise without any model (pure error).
The two noise components of a fit's residual are measurement.noise_components'."""

from __future__ import annotations

import math

import numpy as np
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
