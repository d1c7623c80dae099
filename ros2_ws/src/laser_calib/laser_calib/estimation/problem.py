"""What the estimators solve: a model, its noise, the prior and the free set,
reduced block by block of poses to the normal equations of the whitened problem.

Both estimators minimise  sum_p r_p^T C_p^-1 r_p  (+ the prior  sum_i (x_i / s_i)^2),
where C_p is pose p's measurement covariance (spot noise plus the joint
disturbance seen through the joint Jacobian, see measurement.NoiseModel). Per
block of at most ``chunk`` poses the model is evaluated, whitened, and folded
into J^T J (k,k) and J^T r (k,) in float64: the stacked Jacobian (M,k) of all
poses never exists, so memory does not grow with the poses beyond the per-pose
noise weights (P,CD,CD).

The seam for reweighting (robust IRLS and the like) is Problem.whitened, the
whitened residual and Jacobian rows of one block: the solvers only see the
normal equations built from them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Iterator

import numpy as np

from laser_calib.measurement.base import MeasurementModel, NoiseModel, Residuals, count_values, whiten

# Poses per block: the Jacobians of one block of the 7-DOF arm (33 errors) take
# ~2 MB, so a block's arrays stay in the caches, and numpy's per-call overhead
# is still small (one evaluation of 20,000 poses: 83 ms at 2048, 116 ms at 8192).
CHUNK_POSES = 2048


@dataclass(frozen=True)
class Normal:
    """The normal equations at one x under its own noise weights, in free scaled
    parameters: information J^T J (k,k), gradient J^T r (k,), cost r^T r / 2
    (prior rows included); whitener (P,CD,CD) the weights; n_values measured."""

    information: np.ndarray
    gradient: np.ndarray
    cost: float
    whitener: np.ndarray
    n_values: int
    # the cost of the same x under other weights (LmStep's test), when asked
    cost_under: float = field(default=np.nan)


def n_poses(model: MeasurementModel) -> int | None:
    """The poses of a model that can be cut in blocks (it has samples and subset), else None."""
    samples = getattr(model, "samples", None)
    return len(samples.q) if samples is not None and hasattr(model, "subset") else None


def pose_blocks(model: MeasurementModel, chunk: int = CHUNK_POSES) -> Iterator[tuple[slice, MeasurementModel]]:
    """(poses, model on them) per block; the model itself when it fits in one
    (it keeps its own cache of the last point)."""
    total = n_poses(model)
    if total is None or total <= chunk:
        yield slice(None), model
        return
    for start in range(0, total, chunk):
        index = slice(start, min(start + chunk, total))
        yield index, model.subset(index)


def residuals_at(model: MeasurementModel, x: np.ndarray, chunk: int = CHUNK_POSES,
                 jacobian: bool = False) -> Residuals:
    """The residuals of all poses at x (with the Jacobians when asked), evaluated
    block by block (the model's transient arrays stay those of one block)."""
    parts = [block.residuals(x, jacobian) for _, block in pose_blocks(model, chunk)]
    if len(parts) == 1:
        return parts[0]
    return Residuals(*(None if getattr(parts[0], f) is None else np.concatenate([getattr(r, f) for r in parts])
                       for f in ("r", "valid", "jac", "jac_q", "predicted")))


def whitened_factor(model: MeasurementModel, noise: NoiseModel, x: np.ndarray, excluded: np.ndarray | None = None,
                    chunk: int = CHUNK_POSES) -> tuple[np.ndarray, int]:
    """R (min(M,n),n) with R^T R = J^T J of the whitened Jacobian (M,n) of all
    parameters at x, without the units ``excluded`` (P,C), and the measured
    values counted. R comes from QR of each block stacked under the running R
    (tall-skinny QR), so it has the singular values and right singular vectors
    of J itself: identifiability.analyse(R) decides as on J, without forming
    J^T J (which would square its condition)."""
    problem = Problem(model, noise, np.ones(len(model.names), bool), excluded=excluded, chunk=chunk)
    factor = np.zeros((0, len(model.names)))
    n_values = 0
    for index, block in pose_blocks(model, chunk):
        res = problem.excluding(block.residuals(x, True), index)
        _, jac = whiten(res, noise.for_poses(index).whitener(res))
        factor = np.linalg.qr(np.vstack([factor, jac]), mode="r")
        n_values += count_values(res)
    return factor, n_values


class Problem:
    """A model, its noise, the prior and the free set.

    prior_sigma (n,) with inf where there is none; excluded (P,C) spots left out
    (robust rejection).
    """

    def __init__(self, model: MeasurementModel, noise: NoiseModel, free: np.ndarray,
                 prior_sigma: np.ndarray | None = None, excluded: np.ndarray | None = None,
                 chunk: int = CHUNK_POSES):
        self.model = model
        self.noise = noise
        self.free = np.asarray(free, bool)
        n = len(model.names)
        self.prior_sigma = np.full(n, np.inf) if prior_sigma is None else np.asarray(prior_sigma, float)
        self.excluded = excluded
        self.scales = model.scales[self.free]
        self.chunk = chunk

    def with_noise(self, noise: NoiseModel) -> "Problem":
        return Problem(self.model, noise, self.free, self.prior_sigma, self.excluded, self.chunk)

    def residuals(self, x: np.ndarray, jacobian: bool = True) -> Residuals:
        """All poses at once (small problems, benchmarks); the solvers go by blocks."""
        return self.excluding(self.model.residuals(x, jacobian), slice(None))

    def excluding(self, res: Residuals, index: slice) -> Residuals:
        if self.excluded is None:
            return res
        keep = res.valid & ~self.excluded[index]
        r = np.where(keep[..., None], res.r, 0.0)
        jac = None if res.jac is None else np.where(keep[..., None, None], res.jac, 0.0)
        return replace(res, r=r, valid=keep, jac=jac)

    def whitened(self, index: slice, res: Residuals, whitener: np.ndarray,
                 jacobian: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """Whitened residuals (m,) and Jacobian (m,k) in free scaled parameters of
        the block of poses ``index``. The seam for reweighting (robust IRLS): a
        subclass that scales these rows changes what every solver minimises."""
        r, jac = whiten(res if jacobian else replace(res, jac=None), whitener)
        if jac is None:
            return r, None
        return r, (jac if self.free.all() else jac[:, self.free]) * self.scales

    def normal_equations(self, x: np.ndarray, weights: np.ndarray | None = None) -> Normal:
        """The normal equations at x under its own weights; with ``weights``
        (P,CD,CD) also x's cost under those (one model evaluation for both)."""
        k = int(self.free.sum())
        information, gradient = np.zeros((k, k)), np.zeros(k)
        cost = cost_under = 0.0
        n_values = 0
        whitener = None
        for index, block in pose_blocks(self.model, self.chunk):
            res = self.excluding(block.residuals(x, True), index)
            own = self.noise.for_poses(index).whitener(res)
            if whitener is None:
                total = len(res.r) if index == slice(None) else n_poses(self.model)
                whitener = np.empty((total,) + own.shape[1:])
            whitener[index] = own
            r, jac = self.whitened(index, res, own)
            information += jac.T @ jac
            gradient += jac.T @ r
            cost += 0.5 * r @ r
            if weights is not None:
                r_under, _ = self.whitened(index, res, weights[index], jacobian=False)
                cost_under += 0.5 * r_under @ r_under
            n_values += count_values(res)
        prior = np.isfinite(self.prior_sigma) & self.free
        if prior.any():
            # prior rows: residual -x_i / s_i, Jacobian scale_i / s_i in the scaled parameter
            sigma = self.prior_sigma[prior]
            rows = np.flatnonzero(prior[self.free])
            slope = self.scales[rows] / sigma
            information[rows, rows] += slope ** 2
            gradient[rows] += slope * (-x[prior] / sigma)
        prior_cost = self.prior_cost(x)
        cost += prior_cost
        cost_under += prior_cost
        return Normal(information, gradient, float(cost), whitener, n_values,
                      float(cost_under) if weights is not None else np.nan)

    def prior_cost(self, x: np.ndarray) -> float:
        """The prior rows' part of the cost at x (0 without a prior)."""
        prior = np.isfinite(self.prior_sigma) & self.free
        return 0.5 * float(np.sum((x[prior] / self.prior_sigma[prior]) ** 2))

    def covariance(self, information: np.ndarray) -> np.ndarray:
        """(n,n) in the parameters' units from J^T J in free scaled ones; NaN where not free."""
        n = len(self.free)
        cov = np.full((n, n), np.nan)
        inner = np.linalg.pinv(information)
        cov[np.ix_(self.free, self.free)] = inner * np.outer(self.scales, self.scales)
        return cov


@dataclass(frozen=True)
class Fit:
    """x (n,); covariance (n,n) with NaN rows/columns for parameters not free;
    cost = 1/2 chi^2 of the whitened residuals (prior rows included);
    history (iterations+1, n) and cost_history (iterations+1,)."""

    x: np.ndarray
    covariance: np.ndarray
    free: np.ndarray
    cost: float
    chi2: float
    n_values: int
    iterations: int
    converged: bool
    history: np.ndarray
    cost_history: np.ndarray
    excluded: np.ndarray | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def dof(self) -> int:
        return max(self.n_values - int(self.free.sum()), 1)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))


def make_fit(problem: Problem, x: np.ndarray, normal: Normal, iterations: int, converged: bool,
             history: list, costs: list) -> Fit:
    """The Fit at x from its normal equations (the problem's own noise model)."""
    return Fit(x, problem.covariance(normal.information), problem.free, normal.cost, 2 * normal.cost,
               normal.n_values, iterations, converged, np.array(history), np.array(costs), problem.excluded)
