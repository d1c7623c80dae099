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
from typing import Iterable, Iterator

import numpy as np

from laser_calib.estimation import cancel
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
    # sum over units u of g_u g_u^T (k,k), g_u = J_u^T r_u of the unit's whitened rows, when asked
    unit_outer: np.ndarray | None = None
    # (P,C,D) what the model predicts at x (the report's per-pose figures, computed once)
    predicted: np.ndarray | None = None
    # the normal equations of another problem at the same x, when asked
    also: "Normal | None" = None


def n_poses(model: MeasurementModel) -> int | None:
    """The poses of a model that can be cut in blocks (it has samples and subset), else None."""
    samples = getattr(model, "samples", None)
    return len(samples.q) if samples is not None and hasattr(model, "subset") else None


def pose_blocks(model: MeasurementModel, chunk: int = CHUNK_POSES) -> Iterator[tuple[slice, MeasurementModel]]:
    """(poses, model on them) per block; the model itself when it fits in one
    (it keeps its own cache of the last point). Every evaluation of a model passes here, so this
    is where a caller's cancel (cancel.py) stops a fit."""
    cancel.check()
    total = n_poses(model)
    if total is None or total <= chunk:
        yield slice(None), model
        return
    for start in range(0, total, chunk):
        index = slice(start, min(start + chunk, total))
        yield index, model.subset(index)


def residuals_at(model: MeasurementModel, x: np.ndarray, chunk: int = CHUNK_POSES,
                 jacobian: bool = False, parameters: bool = True) -> Residuals:
    """The residuals of all poses at x (with the Jacobians when asked), evaluated
    block by block (the model's transient arrays stay those of one block).
    parameters=False keeps of the Jacobians only the joints' jac_q: the
    parameters' jac (P,C,D,n) is the largest array of all, and a noise
    estimate needs only jac_q."""
    blocks = ((index, block.residuals(x, jacobian)) for index, block in pose_blocks(model, chunk))
    return _joined(blocks if parameters else ((index, replace(res, jac=None)) for index, res in blocks),
                   n_poses(model))


def whitened_factor(model: MeasurementModel, noise: NoiseModel, x: np.ndarray, excluded: np.ndarray | None = None,
                    chunk: int = CHUNK_POSES) -> tuple[np.ndarray, int]:
    """R (min(M,n),n) with R^T R = J^T J of the whitened Jacobian (M,n) of all
    parameters at x, without the units ``excluded`` (P,C), and the measured
    values counted. R comes from QR of each block stacked under the running R
    (tall-skinny QR), so it has the singular values and right singular vectors
    of J itself: identifiability.analyse(R) decides as on J, without forming
    J^T J (which would square its condition)."""
    factor, n_values, _ = factor_and_residuals(model, noise, x, excluded, chunk, keep=False)
    return factor, n_values


def factor_and_residuals(model: MeasurementModel, noise: NoiseModel, x: np.ndarray,
                         excluded: np.ndarray | None = None, chunk: int = CHUNK_POSES,
                         keep: bool = True) -> tuple[np.ndarray, int, Residuals | None]:
    """whitened_factor's R and count, and (keep) the residuals at x without their
    Jacobians (residuals_at's), from the same pass of the model."""
    problem = Problem(model, noise, np.ones(len(model.names), bool), excluded=excluded, chunk=chunk)
    factor = np.zeros((0, len(model.names)))
    n_values = 0
    parts = []
    for index, block in pose_blocks(model, chunk):
        res = block.residuals(x, True)
        if keep:
            parts.append((index, replace(res, jac=None, jac_q=None)))
        res = problem.excluding(res, index)
        _, jac = whiten(res, noise.for_poses(index).whitener(res))
        factor = np.linalg.qr(np.vstack([factor, jac]), mode="r")
        n_values += count_values(res)
    return factor, n_values, _joined(parts, n_poses(model)) if keep else None


_FIELDS = ("r", "valid", "jac", "jac_q", "predicted")


def _joined(parts: Iterable[tuple[slice, Residuals]], total: int | None) -> Residuals:
    """The residuals of all ``total`` poses from those of their blocks (index,
    Residuals), each copied into place as it comes (no second copy of the whole)."""
    out: dict[str, np.ndarray | None] = {}
    for index, res in parts:
        if index == slice(None):
            return res
        for f in _FIELDS:
            value = getattr(res, f)
            if f not in out:
                out[f] = None if value is None else np.empty((total,) + value.shape[1:], value.dtype)
            if value is not None:
                out[f][index] = value
    return Residuals(*(out[f] for f in _FIELDS))


# Rows leave a factor through R^-1 (downdated): as exact as a new QR where R is
# well conditioned and no direction loses more than 1 - DOWNDATE_LIMIT^2 of its
# information; elsewhere the caller factors the kept rows anew.
DOWNDATE_CONDITION = 1e8
DOWNDATE_LIMIT = 0.9


def downdated(factor: np.ndarray, removed: np.ndarray) -> np.ndarray | None:
    """R' (n,n) with R'^T R' = R^T R - E^T E: the factor R (n,n) of
    whitened_factor without the rows whose factor (or the rows themselves) is E
    (m,n), e.g. spots rejected after R was formed; None where it would not be
    exact (module constants). With Z = E R^-1 = U S V^T:
    R^T R - E^T E = R^T V (I - S^2) V^T R, so R' is the QR factor of
    sqrt(I - S^2) V^T R."""
    n = factor.shape[1]
    if factor.shape[0] < n:
        return None
    singular = np.linalg.svd(factor, compute_uv=False)
    if not singular[-1] > singular[0] / DOWNDATE_CONDITION:
        return None
    z = np.linalg.solve(factor.T, removed.T).T                                 # (m,n)
    _, s, vt = np.linalg.svd(z, full_matrices=True)
    if s.size and s[0] > DOWNDATE_LIMIT:
        return None
    keep = np.sqrt(1.0 - np.concatenate([s, np.zeros(n - s.size)]) ** 2)      # (n,)
    return np.linalg.qr(keep[:, None] * (vt @ factor), mode="r")


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
        if self.excluded is None or not self.excluded[index].any():  # invalid values are zero already
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
        jac = jac if self.free.all() else jac[:, self.free]   # whiten's own array, or a copy
        jac *= self.scales
        return r, jac

    def normal_equations(self, x: np.ndarray, weights: np.ndarray | None = None, unit_outer: bool = False,
                         also: "Problem | None" = None) -> Normal:
        """The normal equations at x under its own weights; with ``weights``
        (P,CD,CD) also x's cost under those (one model evaluation for both);
        with ``unit_outer`` also the sum of g_u g_u^T over the units (a unit: a
        channel's D values; g_u = J_u^T r_u of its whitened rows, meaningful
        when the whitener does not mix units: robust.py's Newton step); with
        ``also`` (a problem of the same model under other noise or exclusions)
        its normal equations at x too, as Normal.also, from the same evaluation."""
        sums = _Sums(self, weights, unit_outer)
        other = None if also is None else _Sums(also)
        for index, block in pose_blocks(self.model, self.chunk):
            res = block.residuals(x, True)
            sums.add(index, res)
            if other is not None:
                other.add(index, res)
        normal = sums.normal(x)
        return normal if other is None else replace(normal, also=other.normal(x))

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


class _Sums:
    """One problem's normal equations summed block by block of poses (Problem.normal_equations)."""

    def __init__(self, problem: Problem, weights: np.ndarray | None = None, unit_outer: bool = False):
        self.problem, self.weights = problem, weights
        k = int(problem.free.sum())
        self.information, self.gradient = np.zeros((k, k)), np.zeros(k)
        self.outer = np.zeros((k, k)) if unit_outer else None
        self.cost = self.cost_under = 0.0
        self.n_values = 0
        self.whitener = self.predicted = None

    def add(self, index: slice, res: Residuals) -> None:
        """The block of poses ``index`` with its residuals and Jacobians ``res``."""
        problem = self.problem
        res = problem.excluding(res, index)
        own = problem.noise.for_poses(index).whitener(res)
        if self.whitener is None:
            total = len(res.r) if index == slice(None) else n_poses(problem.model)
            self.whitener = np.empty((total,) + own.shape[1:])
            self.predicted = np.empty((total,) + res.predicted.shape[1:])
        self.whitener[index] = own
        self.predicted[index] = res.predicted
        r, jac = problem.whitened(index, res, own)
        self.information += jac.T @ jac
        self.gradient += jac.T @ r
        self.cost += 0.5 * r @ r
        if self.outer is not None:
            dims = res.r.shape[2]
            per_unit = np.einsum("udk,ud->uk", jac.reshape(-1, dims, jac.shape[1]), r.reshape(-1, dims))   # (PC,k)
            self.outer += per_unit.T @ per_unit
        if self.weights is not None:
            r_under, _ = problem.whitened(index, res, self.weights[index], jacobian=False)
            self.cost_under += 0.5 * r_under @ r_under
        self.n_values += count_values(res)

    def normal(self, x: np.ndarray) -> Normal:
        """The sums with the prior rows added: the normal equations at x."""
        problem = self.problem
        information, gradient = self.information, self.gradient
        prior = np.isfinite(problem.prior_sigma) & problem.free
        if prior.any():
            # prior rows: residual -x_i / s_i, Jacobian scale_i / s_i in the scaled parameter
            sigma = problem.prior_sigma[prior]
            rows = np.flatnonzero(prior[problem.free])
            slope = problem.scales[rows] / sigma
            information[rows, rows] += slope ** 2
            gradient[rows] += slope * (-x[prior] / sigma)
        prior_cost = problem.prior_cost(x)
        return Normal(information, gradient, float(self.cost + prior_cost), self.whitener, self.n_values,
                      float(self.cost_under + prior_cost) if self.weights is not None else np.nan, self.outer,
                      self.predicted)


@dataclass(frozen=True)
class Fit:
    """x (n,); covariance (n,n) with NaN rows/columns for parameters not free;
    cost = 1/2 chi^2 of the whitened residuals (prior rows included);
    history (iterations+1, n) and cost_history (iterations+1,); predicted (P,C,D)
    what the model predicts at x."""

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
    predicted: np.ndarray | None = field(default=None, repr=False)

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
               normal.n_values, iterations, converged, np.array(history), np.array(costs), problem.excluded,
               predicted=normal.predicted)


def rescaled(fit: Fit, ratio: float) -> Fit:
    """A least-squares fit without a prior under a noise model ``ratio`` times its own
    (both sigmas, or the spot sigma without joint noise): x stays, chi^2 and the
    costs scale by 1 / ratio^2, the covariance by ratio^2."""
    return replace(fit, covariance=fit.covariance * ratio ** 2, cost=fit.cost / ratio ** 2,
                   chi2=fit.chi2 / ratio ** 2, cost_history=fit.cost_history / ratio ** 2)
