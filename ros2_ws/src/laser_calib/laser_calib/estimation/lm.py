"""Levenberg-Marquardt on the normal equations of a Problem.

Damped Gauss-Newton in parameters scaled by their characteristic size, so the
damping treats 10 mm and 1 deg alike. Iteratively reweighted: a trial is
compared with the current point under the current point's noise weights (the
joint-noise covariance depends on x); the weights are renewed at each accepted
point. A trial whose cost is not finite (a step into a region where the model
overflows) is a rejected step like any other rise of the cost. Normal equations
that are not finite themselves give no finite step at any damping: that is a
numerical breakdown (LinAlgError), not a loop without end.

Parameters outside ``free`` stay at their start value (the identifiability
analysis fixes what the data cannot see).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from laser_calib.estimation.problem import Fit, Normal, Problem, make_fit

# progress(done, total or None when unknown, note): called once per iteration; not part of the math
ProgressCallback = Callable[[int, int | None, str], None]

# Damping beyond this many times the largest information shortens any finite step below step_tol
# (cost below 1e30): a step that is still not finite there never will be.
MAX_DAMPING_RATIO = 1e20


@dataclass(frozen=True)
class LmOptions:
    max_iter: int = 100
    step_tol: float = 1e-4    # stop when the step is shorter than this many standard deviations
    cost_tol: float = 1e-12   # ... or the relative cost decrease falls below this
    damping: float = 1e-3     # initial lambda
    progress: ProgressCallback | None = field(default=None, compare=False, repr=False)


def levenberg_marquardt(problem: Problem, x0: np.ndarray, options: LmOptions = LmOptions(),
                        start: Normal | None = None) -> Fit:
    """start: the problem's normal equations at x0, when the caller has them."""
    x = np.array(x0, dtype=float)
    normal = problem.normal_equations(x) if start is None else start
    history, costs = [x.copy()], [normal.cost]
    damping = options.damping
    converged = False
    iterations = 0
    eye = np.eye(len(normal.gradient))
    while iterations < options.max_iter and not converged:
        iterations += 1
        while True:
            _check_damping(damping, normal)
            try:
                step = np.linalg.solve(normal.information + damping * eye, normal.gradient)
            except np.linalg.LinAlgError:
                # damping * I lost in rounding beside information of dependent rows (a wrong robot
                # file's restart, 4-DOF arm: 'Singular matrix' from the middle of an estimate)
                damping *= 10.0
                continue
            if not np.isfinite(step).all():
                damping *= 10.0
                continue
            # The step's length in standard deviations of the estimate (the information
            # metric): below step_tol it changes nothing that the data can tell.
            if np.sqrt(max(step @ normal.information @ step, 0.0)) < options.step_tol:
                converged = True
                break
            trial = x.copy()
            trial[problem.free] += step * problem.scales
            candidate = _trial(problem, trial, normal)
            if candidate is not None and candidate.cost_under <= normal.cost:
                break
            damping *= 10.0
        if converged:
            break
        decrease = normal.cost - candidate.cost_under
        x, normal = trial, candidate
        history.append(x.copy())
        costs.append(normal.cost)
        damping = max(damping / 10.0, 1e-12)
        converged = decrease <= options.cost_tol * max(normal.cost, 1e-300)
        if options.progress is not None:
            # no total: LM stops long before max_iter, a time left from it would mislead
            options.progress(iterations, None, f"cost {normal.cost:.6g}")
    if options.progress is not None:
        options.progress(iterations, iterations, "converged" if converged else "stopped")
    return make_fit(problem, x, normal, iterations, converged, history, costs)


def _check_damping(damping: float, normal: Normal) -> None:
    """Raise LinAlgError once the damping has passed any that a finite step could need."""
    largest = np.max(np.abs(np.diag(normal.information)), initial=1.0)
    # infinite information (an overflow) or a damping overflowed to inf: no step to find either
    if not (np.isfinite(largest) and np.isfinite(damping) and damping <= MAX_DAMPING_RATIO * largest):
        raise np.linalg.LinAlgError(f"no finite damped step: the normal equations are not finite "
                                    f"(cost {normal.cost:g}, damping {damping:.0e})")


def _trial(problem: Problem, trial: np.ndarray, current: Normal) -> Normal | None:
    """The trial's normal equations, None when its cost under the current
    weights is not finite or its own weights cannot be formed (it diverged)."""
    with np.errstate(over="ignore", invalid="ignore"):
        try:
            candidate = problem.normal_equations(trial, current.whitener)
        except np.linalg.LinAlgError:
            return None
    finite = np.isfinite(candidate.cost_under) and np.isfinite(candidate.information).all()
    return candidate if finite else None


def suspect(fit: Fit) -> bool:
    """A minimum whose chi^2 exceeds its dof by more than 6 sqrt(2 dof), the noise being known:
    a wrong local minimum, an outlier or an unmodelled effect."""
    return fit.chi2 > fit.dof + 6.0 * np.sqrt(2.0 * fit.dof)


def restarted(problem: Problem, fit: Fit, x0: np.ndarray, scales: np.ndarray, count: int, seed: int,
              options: LmOptions) -> tuple[Fit, int]:
    """LM from up to ``count`` seeded random starts within twice the scales about x0 while the
    minimum is suspect; the lowest cost wins. Returns it and the starts tried."""
    rng = np.random.default_rng(seed)
    free = problem.free
    restarts = 0
    for _ in range(count):
        restarts += 1
        start_x = x0.copy()
        start_x[free] += rng.uniform(-2, 2, int(free.sum())) * scales[free]
        candidate = levenberg_marquardt(problem, start_x, options)
        if candidate.cost < fit.cost - 1e-9 * max(fit.cost, 1.0):
            fit = candidate
        if not suspect(fit):
            break
    return fit, restarts
