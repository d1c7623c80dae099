"""The two components of the noise in a fit's residual, by maximum likelihood.

The measurement covariance of a pose is spot^2 I + joint^2 G G^T (G = jac_q,
measurement.NoiseModel): spot noise on each coordinate, and joint-reading noise
moving the pose's spots together, most where the beams are long levers. When
either is not given, it is estimated from a fit's residuals (the diagnosis's
verdict; `estimate` without any sigma).

A fit takes up part of the noise, and not evenly: a joint read wrong at one pose
moves its spots as that joint's own errors do, so the residual shows less joint
noise than there was. Given the fit's Jacobian, the likelihood is the restricted
one (REML, Patterson and Thompson 1971): that of the residual's part no parameter
can take up, -2 log L = log|C| + log|X^T C^-1 X| + r^T C^-1 r - b^T (X^T C^-1 X)^-1 b
with b = X^T C^-1 r, the same for every r = y - X beta (over the directions X spans: its
pseudo-determinant and pseudo-inverse where its columns are dependent). Without it, the residuals
are scaled by sqrt(M/dof) instead (evenly). On a UR10e with 0.058 deg joint noise
the plain likelihood found none in 6 of 7 sessions.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
# the chi^2 tail without importing scipy.stats (seconds at every start of the command line)
from scipy.special import chdtrc

from laser_calib.measurement.base import Residuals

JOINT_STARTS = (1e-4, 3e-3)   # rad: 0.006 and 0.17 deg, the joint-reading sigma's two starts
NO_JOINT_NOISE = 1e-6         # rad: a joint-reading sigma ending below this tries the second start
MIN_SIGMA = 1e-7              # m: an estimated noise below 0.1 um is an exact fit, not a measurement


def deviance(res: Residuals, scale: float, jac: np.ndarray | None = None) -> Callable[[float, float], float]:
    """-2 log-likelihood (up to a constant) of a fit's residuals, scaled by
    ``scale`` (sqrt(M/dof): the fit took dof away), as a function of the spot
    (m) and joint-reading (rad) sigma: the pose covariance spot^2 I + joint^2
    G G^T (G = jac_q, as in measurement.NoiseModel). With ``jac`` (P,C,D,k), the
    Jacobian of the k parameters the fit determined, the restricted likelihood
    (module docstring; ``scale`` 1 then)."""
    n_poses = res.r.shape[0]
    m = res.r.shape[1] * res.r.shape[2]
    mask = np.repeat(res.valid, res.r.shape[2], axis=1)
    g = res.jac_q.reshape(n_poses, m, -1) * mask[..., None]
    # In the eigenvectors U of each pose's G G^T (eigenvalues lam) the covariance is diagonal,
    # spot^2 + joint^2 lam: one decomposition here, none per evaluation (the solves it replaced
    # made a 2000-pose estimate 2.7 times slower with the restricted likelihood).
    lam, basis = np.linalg.eigh(np.einsum("pin,pjn->pij", g, g))
    lam = np.clip(lam, 0.0, None)
    r = np.einsum("pmi,pm->pi", basis, res.r.reshape(n_poses, m) * scale * mask)           # U^T r
    x = (None if jac is None or not jac.shape[-1] else   # no parameter determined: nothing taken up
         np.einsum("pmi,pmk->pik", basis, jac.reshape(n_poses, m, jac.shape[-1]) * mask[..., None]))
    # an entry without a measurement has covariance 1, not spot^2: its row of G G^T is 0 (lam 0)
    unmeasured = int(mask.size - mask.sum())

    def value(s: float, j: float) -> float:
        variance = s ** 2 + j ** 2 * lam                                                    # (P, m)
        total = float(np.log(variance).sum() - unmeasured * np.log(s ** 2) + np.sum(r ** 2 / variance))
        if x is None:
            return total
        weighted = (x / variance[..., None]).reshape(-1, x.shape[-1])                       # C^-1 X
        information = weighted.T @ x.reshape(-1, x.shape[-1])                               # X^T C^-1 X
        b = weighted.T @ r.reshape(-1)
        # Over the directions X spans: a fit gone wrong (the beams of most poses off the screen) leaves
        # fewer measured values than determined parameters, and solve() raised "Singular matrix" from
        # the middle of an estimate. The pseudo-determinant of A^T M A (X = B A, B a basis of X's
        # columns) is det(M) det(A A^T): the same likelihood up to a constant.
        eigenvalues, vectors = np.linalg.eigh(information)
        spanned = eigenvalues > eigenvalues[-1] * len(eigenvalues) * np.finfo(float).eps
        projected = vectors[:, spanned].T @ b
        return total + float(np.log(eigenvalues[spanned]).sum() - projected @ (projected / eigenvalues[spanned]))

    return value


def noise_components(res: Residuals, scale: float, spot: float | None, joint: float | None,
                     jac: np.ndarray | None = None) -> tuple[float, float]:
    """Maximum-likelihood spot (m) and joint-reading (rad) noise of a fit's
    residuals (deviance; restricted with ``jac``); the given ones are held, the
    None ones estimated. Residuals are scaled by ``scale`` (sqrt(M/dof): the fit
    took dof away; 1 with ``jac``)."""
    from scipy import optimize  # a second at import: only the fits that estimate both components pay it

    free = [spot is None, joint is None]
    value = deviance(res, scale, jac)

    def unpack(theta: np.ndarray) -> tuple[float, float]:
        values = iter(np.exp(theta))
        return (next(values) if free[0] else spot), (next(values) if free[1] else joint)

    def negative_log_likelihood(theta: np.ndarray) -> float:
        return value(*unpack(np.atleast_1d(theta)))

    mask = np.repeat(res.valid, res.r.shape[2], axis=1)
    rms = float(np.sqrt(np.mean((res.r.reshape(len(mask), -1) * scale)[mask] ** 2))) if mask.any() else 1e-3
    if free == [False, False]:
        return spot, joint
    if rms < MIN_SIGMA:
        # An exact fit (a correct model on noise-free data): the likelihood grows without bound as the
        # noise goes to 0, and its logarithm was -inf; the noise is the least this project calls one.
        return (MIN_SIGMA if free[0] else spot), (0.0 if free[1] else joint)
    if sum(free) == 1:
        bounds = (math.log(1e-7), math.log(0.05)) if free[1] else (math.log(rms * 1e-3), math.log(rms * 10))
        found = optimize.minimize_scalar(negative_log_likelihood, bounds=bounds, method="bounded")
        return unpack(np.array([found.x]))
    # Nelder-Mead in log space from everything in the spot noise with a small joint noise, and where
    # that ends at no joint noise, again from a large one: from the first alone it settled at a joint
    # noise of 0 in 3 of 20 sessions of 2 mrad (deviance 29, 3.5 and 15 above the minimum a grid found).
    found = None
    for start in JOINT_STARTS:
        trial = optimize.minimize(negative_log_likelihood, np.log([rms, start]), method="Nelder-Mead",
                                  options={"xatol": 1e-3, "fatol": 1e-6})
        found = trial if found is None or trial.fun < found.fun else found
        if np.exp(found.x[1]) > NO_JOINT_NOISE:
            break
    return unpack(found.x)


def boundary_p(ratio: float) -> float:
    """p of a likelihood-ratio statistic (deviance difference) ``ratio`` for one sigma held at a
    boundary value against it estimated on one side of it: chi^2(1) halved (the null on the boundary)."""
    return 0.5 * float(chdtrc(1, ratio)) if ratio > 0 else 1.0


def joint_noise_evidence(res: Residuals, scale: float, jac: np.ndarray | None = None,
                         spot: float | None = None) -> tuple[float, float, float]:
    """(spot sigma m, joint sigma rad, p) of a fit's residuals (scaled as in deviance; restricted
    with ``jac``) with both components estimated (the spot one held at ``spot`` when given), and
    the p-value of "no joint-reading noise": the one-sided likelihood-ratio test against the spot
    noise alone (boundary_p)."""
    value = deviance(res, scale, jac)
    alone = noise_components(res, scale, spot, 0.0, jac)
    spot, joint = noise_components(res, scale, spot, None, jac)
    ratio = value(*alone) - value(spot, joint)
    return spot, joint, boundary_p(ratio)
