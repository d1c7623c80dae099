"""The two components of the noise in a fit's residual, by maximum likelihood.

The measurement covariance of a pose is spot^2 I + joint^2 G G^T (G = jac_q,
measurement.NoiseModel): spot noise on each coordinate, and joint-reading noise
moving the pose's spots together, most where the beams are long levers. When
either is not given, it is estimated from a fit's residuals (the diagnosis's
verdict; `estimate` without any sigma).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
# the chi^2 tail without importing scipy.stats (seconds at every start of the command line)
from scipy.special import chdtrc

from laser_calib.measurement.base import Residuals


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
    from scipy import optimize  # a second at import: only the fits that estimate both components pay it

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


def boundary_p(ratio: float) -> float:
    """p of a likelihood-ratio statistic (deviance difference) ``ratio`` for one sigma held at a
    boundary value against it estimated on one side of it: chi^2(1) halved (the null on the boundary)."""
    return 0.5 * float(chdtrc(1, ratio)) if ratio > 0 else 1.0


def joint_noise_evidence(res: Residuals, scale: float) -> tuple[float, float, float]:
    """(spot sigma m, joint sigma rad, p) of a fit's residuals (scaled as in deviance) with
    both components estimated, and the p-value of "no joint-reading noise": the one-sided
    likelihood-ratio test against the spot noise alone (boundary_p)."""
    value = deviance(res, scale)
    spot, joint = noise_components(res, scale, None, None)
    alone = noise_components(res, scale, None, 0.0)
    ratio = value(*alone) - value(spot, joint)
    return spot, joint, boundary_p(ratio)
