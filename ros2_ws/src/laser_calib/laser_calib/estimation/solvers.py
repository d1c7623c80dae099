"""The two estimators, on the same whitened residuals and Jacobian.

Both minimise  sum_p r_p^T C_p^-1 r_p  (+ the prior  sum_i (x_i / s_i)^2),
where C_p is pose p's measurement covariance (spot noise plus the joint
disturbance seen through the joint Jacobian, see measurement.NoiseModel):

- levenberg_marquardt: damped Gauss-Newton in parameters scaled by their
  characteristic size, so the damping treats 10 mm and 1 deg alike.
- extended_kalman: the paper's EKF (eq. 13-15) on filterpy's
  ExtendedKalmanFilter, the whole calibration set as one stacked measurement per
  iteration: x_{k+1|k} = x_k, P_{k+1|k} = P_k + Q, then the update. Its fixed
  point satisfies J^T R^-1 r = 0 whatever Q and P0 are (Woodbury), so at
  convergence it is the same weighted least-squares solution as LM; Q and P0
  set how fast it gets there.

Parameters outside ``free`` stay at their start value (the identifiability
analysis fixes what the data cannot see).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from laser_calib.measurement.base import MeasurementModel, NoiseModel, Residuals, count_values, whiten


@dataclass(frozen=True)
class LmOptions:
    max_iter: int = 100
    step_tol: float = 1e-4    # stop when the step is shorter than this many standard deviations
    cost_tol: float = 1e-12   # ... or the relative cost decrease falls below this
    damping: float = 1e-3     # initial lambda


@dataclass(frozen=True)
class EkfOptions:
    """The paper's settings (section IV-A): Q = R = 1e-4 I, at most 5000
    iterations, stop when the state changes by less than 1e-7 in norm.
    r=None takes R from the noise model (the spot sigma and joint noise);
    p0 is filterpy's default (the paper does not state it)."""

    q: float = 1e-4
    r: float | None = 1e-4
    p0: float = 1.0
    max_iter: int = 5000
    tol: float = 1e-7
    # Called with a progress line every 100 iterations (long runs); not an option of the math.
    progress: Callable[[str], None] | None = field(default=None, compare=False, repr=False)


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


class Problem:
    """A model, its noise, the prior and the free set, as whitened stacks.

    prior_sigma (n,) with inf where there is none; excluded (P,C) spots left out
    (robust rejection).
    """

    def __init__(self, model: MeasurementModel, noise: NoiseModel, free: np.ndarray,
                 prior_sigma: np.ndarray | None = None, excluded: np.ndarray | None = None):
        self.model = model
        self.noise = noise
        self.free = np.asarray(free, bool)
        n = len(model.names)
        self.prior_sigma = np.full(n, np.inf) if prior_sigma is None else np.asarray(prior_sigma, float)
        self.excluded = excluded
        self.scales = model.scales[self.free]

    def residuals(self, x: np.ndarray, jacobian: bool = True) -> Residuals:
        res = self.model.residuals(x, jacobian)
        if self.excluded is None:
            return res
        keep = res.valid & ~self.excluded
        r = np.where(keep[..., None], res.r, 0.0)
        jac = None if res.jac is None else np.where(keep[..., None, None], res.jac, 0.0)
        return replace(res, r=r, valid=keep, jac=jac)

    def stack(self, x: np.ndarray, whitener: np.ndarray | None = None):
        """Whitened residuals (M,) and Jacobian in free, scaled parameters (M,k),
        prior rows appended; also the whitener used and the residual object.
        Without a whitener, the one of x itself (its joint-noise covariance)."""
        res = self.residuals(x, True)
        if whitener is None:
            whitener = self.noise.whitener(res)
        r, jac = self.whitened(x, res, whitener)
        return r, jac, whitener, res

    def whitened(self, x: np.ndarray, res: Residuals, whitener: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, jac = whiten(res, whitener)
        jac = jac[:, self.free] * self.scales
        prior = np.isfinite(self.prior_sigma) & self.free
        if prior.any():
            sigma = self.prior_sigma[prior]
            r = np.concatenate([r, -x[prior] / sigma])
            rows = np.zeros((prior.sum(), self.free.sum()))
            rows[np.arange(prior.sum()), np.flatnonzero(prior[self.free])] = self.scales[prior[self.free]] / sigma
            jac = np.vstack([jac, rows])
        return r, jac

    def covariance(self, jac: np.ndarray) -> np.ndarray:
        n = len(self.free)
        cov = np.full((n, n), np.nan)
        inner = np.linalg.pinv(jac.T @ jac)
        cov[np.ix_(self.free, self.free)] = inner * np.outer(self.scales, self.scales)
        return cov


def levenberg_marquardt(problem: Problem, x0: np.ndarray, options: LmOptions = LmOptions()) -> Fit:
    """Iteratively reweighted LM: a trial is compared with the current point under
    the current point's noise weights (the joint-noise covariance depends on x);
    the weights are renewed at each accepted point."""
    x = np.array(x0, dtype=float)
    r, jac, whitener, res = problem.stack(x)
    cost = 0.5 * r @ r
    history, costs = [x.copy()], [cost]
    damping = options.damping
    converged = False
    iterations = 0
    eye = np.eye(jac.shape[1])
    while iterations < options.max_iter and not converged:
        iterations += 1
        gradient = jac.T @ r
        normal = jac.T @ jac
        while True:
            step = np.linalg.solve(normal + damping * eye, gradient)
            # The step's length in standard deviations of the estimate (the information
            # metric): below step_tol it changes nothing that the data can tell.
            if np.sqrt(max(step @ normal @ step, 0.0)) < options.step_tol:
                converged = True
                break
            trial = x.copy()
            trial[problem.free] += step * problem.scales
            res_trial = problem.residuals(trial, True)
            r_trial, _ = problem.whitened(trial, res_trial, whitener)
            cost_trial = 0.5 * r_trial @ r_trial
            if cost_trial <= cost:
                break
            damping *= 10.0
        if converged:
            break
        decrease = cost - cost_trial
        x, res = trial, res_trial
        whitener = problem.noise.whitener(res)
        r, jac = problem.whitened(x, res, whitener)
        cost = 0.5 * r @ r
        history.append(x.copy())
        costs.append(cost)
        damping = max(damping / 10.0, 1e-12)
        converged = decrease <= options.cost_tol * max(cost, 1e-300)
    return Fit(x, problem.covariance(jac), problem.free, cost, 2 * cost, count_values(res), iterations,
               converged, np.array(history), np.array(costs), problem.excluded)


def extended_kalman(problem: Problem, x0: np.ndarray, options: EkfOptions = EkfOptions()) -> Fit:
    """Paper eq. 13-15 with filterpy. The state is the free errors in their own
    units (the paper's Q and P0 are per unit of metre or radian)."""
    free = problem.free
    k = int(free.sum())
    x = np.array(x0, dtype=float)
    noise = problem.noise if options.r is None else replace(problem.noise, sigma=float(np.sqrt(options.r)))
    ekf_problem = Problem(problem.model, noise, free, problem.prior_sigma, problem.excluded)
    scales = problem.scales

    # filterpy evaluates H and h(x) separately at the same state: cache one stack.
    cache: dict[str, object] = {}

    def stacked(state: np.ndarray):
        key = state.tobytes()
        if cache.get("key") != key:
            full = x.copy()
            full[free] = state
            cache["key"], cache["value"] = key, ekf_problem.stack(full)
        return cache["value"]

    ekf = ExtendedKalmanFilter(dim_x=k, dim_z=1)
    ekf.x = x[free].copy()
    ekf.P = np.eye(k) * options.p0
    ekf.Q = np.eye(k) * options.q
    ekf.F = np.eye(k)
    history, costs = [x.copy()], []
    converged = False
    iterations = 0
    for iterations in range(1, options.max_iter + 1):
        ekf.predict()                                                # eq. 13
        r, jac, _, _ = stacked(ekf.x)
        costs.append(0.5 * r @ r)
        before = ekf.x.copy()
        # Measurement in whitened units: z = 0, h(x) = -r(x), H = d h / d x = J / scales (eq. 14-15).
        ekf.update(np.zeros(len(r)), lambda s: stacked(s)[1] / scales, lambda s: -stacked(s)[0],
                   R=np.eye(len(r)))
        x[free] = ekf.x
        history.append(x.copy())
        change = np.linalg.norm(ekf.x - before)
        if change < options.tol:
            converged = True
            break
        if options.progress is not None and iterations % 100 == 0:
            options.progress(f"ekf iteration {iterations}/{options.max_iter}: state change {change:.2e} "
                             f"(stops below {options.tol:.0e}), cost {costs[-1]:.4g}")
    # Report cost, covariance and chi^2 with the problem's own noise model.
    r, jac, _, res = problem.stack(x)
    costs.append(0.5 * r @ r)
    return Fit(x, problem.covariance(jac), free, costs[-1], 2 * costs[-1], count_values(res), iterations,
               converged, np.array(history), np.array(costs), problem.excluded)
