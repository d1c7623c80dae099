"""Robust estimation: a single wrong detection, whatever its size, cannot move the fit.

Iteratively reweighted least squares outside the solvers: each measured unit
(a spot, a point, a pose: one channel of one pose, D values) gets a weight w,
applied as sqrt(w) on its columns of the whitener (its covariance inflated by
1/w, cross-terms included), so LM, the EKF and every model (spots, sensors,
effects) run unchanged on the reweighted residuals and Jacobian.

The rule (ROBUST_RULE, stated in result.json):
- d_u^2 = r_u^T C_u^-1 r_u per unit u (C_u its block of the noise covariance,
  so it is chi^2_D under the noise model);
- scale s^2 = median(d_u^2) / median(chi^2_D) over the kept units: for D = 1
  the MAD about zero (1.4826 median |z|; a fit's residual is centred on
  zero), for D > 1 the same on the unit's distance, so a unit whose
  components differ in size (position, rotation) is not judged per value;
- Cauchy weight w_u = 1 / (1 + t_u^2 / (D c^2)) with t_u^2 = d_u^2 / s^2 and
  c = 2.385 (95 % efficiency at the normal distribution). Its influence
  redescends to zero, so a 1e6 m spot weighs nothing;
- the first weights are those of the start (the nominal model: its residual
  is centimetres, a gross outlier metres), then fit and reweight until no
  weight changes by more than 1e-3 (at most MAX_ROUNDS rounds);
- at the end the units with t_u^2 > chi^2_D(1 - 0.01 / N) (N units) are
  candidates; the scale becomes the larger of s and the RMS of the other
  units' standardised values (real residuals have heavier tails than the
  normal law the MAD assumes), and a unit beyond the limit at that scale is
  rejected (listed): a clean set loses any unit with probability 1 %, while a
  gross outlier is hundreds of sigma out. The final fit is plain least squares
  on the others, so its covariance and chi^2 keep their meaning. If more
  than MAX_REJECTED of the units lie beyond the limit, the model, not the
  data, is wrong: nothing is rejected and RobustFit.overflow says so.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
# chi^2 quantiles as scipy.stats.chi2 computes them (ppf, isf), without importing scipy.stats (seconds)
from scipy.special import chdtri, gammaincinv

from laser_calib.estimation.problem import Fit, Problem, pose_blocks
from laser_calib.measurement.base import MeasurementModel, NoiseModel, Residuals

CAUCHY_C = 2.385
FAMILY_FALSE_REJECTION = 0.01  # probability that a clean set loses a unit
MAX_ROUNDS = 30
WEIGHT_TOL = 1e-3
# A residual below a thousandth of the noise model's sigma (noise-free data)
# has no outliers: the scale is not taken below this, in whitened units.
MIN_SCALE = 1e-3
MAX_REJECTED = 1 / 3  # beyond this fraction of outliers the residual is a model error
ROBUST_RULE = ("IRLS with the Cauchy loss (c = 2.385) on each spot's (point's, pose's) whitened residual, "
               "scale s^2 = median(d^2) / median(chi^2_D) (the MAD about zero for D = 1), weights from the "
               "nominal model first; at convergence a spot with d^2 / s'^2 > chi^2_D(1 - 0.01 / N) of N spots "
               "is rejected (s' the larger of s and the RMS scale of the spots within the limit), and the final "
               "fit is least squares on the rest")

Solver = Callable[[Problem, np.ndarray], Fit]  # (problem, start x) -> fit: LM, the EKF, ...


@dataclass(frozen=True)
class WeightedNoise(NoiseModel):
    """A noise model with a weight per unit (P,C) in [0, 1]: unit u's own
    covariance block is inflated by 1/w_u (its cross-covariances with the
    pose's other units kept), so w_u = 0 is exactly leaving it out. Without
    joint noise this is sqrt(w_u) on its whitener columns. dataclasses.replace
    keeps the weights (the EKF replaces sigma)."""

    weights: np.ndarray | None = None

    def for_poses(self, index: slice) -> "WeightedNoise":
        return self if self.weights is None else replace(self, weights=self.weights[index])

    def whitener(self, residuals: Residuals) -> np.ndarray:
        if self.weights is None:
            return super().whitener(residuals)
        kept = self.weights > 0
        base = super().whitener(replace(residuals, valid=residuals.valid & kept))
        dims = residuals.r.shape[2]
        weight = np.repeat(np.where(kept, self.weights, 1.0), dims, axis=1)        # (P, CD)
        left_out = np.repeat(kept, dims, axis=1)[:, None, :]                        # zero columns: no residual
        if not (np.any(np.asarray(self.joint_sigma) > 0) and residuals.jac_q is not None):
            return base * np.sqrt(weight)[:, None, :] * left_out
        factor = np.linalg.inv(base)
        covariance = factor @ factor.transpose(0, 2, 1)                             # (P, CD, CD)
        own = np.kron(np.eye(residuals.r.shape[1]), np.ones((dims, dims)))          # the units' blocks
        covariance = covariance + covariance * own * (1.0 / weight - 1.0)[:, :, None]
        return np.linalg.inv(np.linalg.cholesky(covariance)) * left_out


@dataclass(frozen=True)
class RobustFit:
    """fit: the final least-squares fit without the rejected units; rejected
    (P,C) bool; weights (P,C) of the last round; scale s (whitened units);
    rounds of reweighting; converged: the weights settled; overflow: the
    number of units beyond the limit when it exceeded MAX_REJECTED (none
    rejected), else 0."""

    fit: Fit
    rejected: np.ndarray
    weights: np.ndarray
    scale: float
    rounds: int
    converged: bool
    overflow: int = 0


def unit_distances(res: Residuals, noise: NoiseModel) -> np.ndarray:
    """Squared Mahalanobis distance d^2 (P,C) of each unit against its own block of the noise covariance (so one
    outlier does not colour its pose's other unit). Invalid units: 0."""
    n_poses, channels, dims = res.r.shape
    inverse_factor = noise.whitener(res)                       # (P, CD, CD), W^T W = C^-1
    covariance = np.linalg.inv(np.einsum("pki,pkj->pij", inverse_factor, inverse_factor))
    blocks = np.stack([covariance[:, c * dims:(c + 1) * dims, c * dims:(c + 1) * dims] for c in range(channels)],
                      axis=1)                                    # (P, C, D, D)
    chol = np.linalg.cholesky(blocks)
    z = np.linalg.solve(chol, res.r[..., None])[..., 0]
    return np.where(res.valid, (z ** 2).sum(axis=2), 0.0)


def distances_at(model: MeasurementModel, noise: NoiseModel, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """unit_distances (P,C) at x, the valid units (P,C) and the values per unit D, block by block of poses
    (problem.pose_blocks): memory does not grow with the poses beyond these (P,C) arrays. Only joint noise
    needs the Jacobian (its whitener); without it the model runs without."""
    joint = bool(np.any(np.asarray(noise.joint_sigma) > 0))
    d2, valid = [], []
    for index, block in pose_blocks(model):
        res = block.residuals(x, joint)
        d2.append(unit_distances(res, noise.for_poses(index)))
        valid.append(res.valid)
    return np.concatenate(d2), np.concatenate(valid), res.r.shape[2]


def cauchy_weights(d2: np.ndarray, scale: float, dims: int) -> np.ndarray:
    return 1.0 / (1.0 + d2 / (scale ** 2 * dims * CAUCHY_C ** 2))


def mad_scale(d2: np.ndarray, use: np.ndarray, dims: int) -> float:
    """sqrt(median d^2 / median chi^2_D) over the units in ``use`` (P,C), at least MIN_SCALE."""
    values = d2[use]
    scale = float(np.sqrt(np.median(values) / (2 * gammaincinv(dims / 2, 0.5)))) if values.size else 1.0
    return max(scale, MIN_SCALE)


def robust_fit(model: MeasurementModel, noise: NoiseModel, free: np.ndarray, prior_sigma: np.ndarray | None,
               x0: np.ndarray, solve: Solver,
               excluded: np.ndarray | None = None) -> RobustFit:
    """IRLS (module docstring) with any solver solve(problem, x_start) -> Fit.
    excluded (P,C): units already refused (impossible measurements)."""
    x = np.asarray(x0, float)
    d2, valid, dims = distances_at(model, noise, x)
    excluded = np.zeros(valid.shape, bool) if excluded is None else excluded
    use = valid & ~excluded
    scale = mad_scale(d2, use, dims)
    weights = np.where(use, cauchy_weights(d2, scale, dims), 0.0)
    converged = False
    rounds = 0
    fit = None
    while rounds < MAX_ROUNDS and not converged:
        rounds += 1
        weighted = WeightedNoise(noise.sigma, noise.joint_sigma, weights)
        fit = solve(Problem(model, weighted, free, prior_sigma, excluded), x)
        x = fit.x
        d2 = distances_at(model, noise, x)[0]
        scale = mad_scale(d2, use, dims)
        new = np.where(use, cauchy_weights(d2, scale, dims), 0.0)
        converged = float(np.abs(new - weights).max(initial=0.0)) < WEIGHT_TOL
        weights = new
    limit = chdtri(dims, FAMILY_FALSE_REJECTION / max(int(use.sum()), 1))
    candidates = use & (d2 / scale ** 2 > limit)
    inliers = use & ~candidates
    if inliers.any():  # judged by the inliers' own standard deviation (heavier tails than the MAD assumes)
        scale = max(scale, float(np.sqrt(d2[inliers].mean() / dims)))
    rejected = use & (d2 / scale ** 2 > limit)
    overflow = int(rejected.sum()) if rejected.sum() > MAX_REJECTED * use.sum() else 0
    if overflow:
        rejected[:] = False
    final = solve(Problem(model, noise, free, prior_sigma, excluded | rejected), x)
    return RobustFit(final, rejected, weights, scale, rounds, converged, overflow)
