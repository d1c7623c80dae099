"""The paper's EKF (eq. 13-15), batch over a Problem and one update shared
with the online filter.

The measurement is in whitened units: z = 0, h(x) = -r(x), R = I, so
H = d h / d x is the whitened Jacobian. The update is written in information
form, P+ = (P^-1 + H^T H)^-1 and x+ = x + P+ H^T (z - h(x)), which by the
Woodbury identity is the Kalman gain form P H^T (H P H^T + R)^-1 without its
(M,M) innovation matrix: H^T H and H^T r are what Problem accumulates block by
block, so the batch form costs what one LM iteration costs at any number of
poses.

Batch: the whole calibration set is one measurement per iteration,
x_{k+1|k} = x_k, P_{k+1|k} = P_k + Q, then the update. Its fixed point
satisfies J^T R^-1 r = 0 whatever Q and P0 are, so at convergence it is the
same weighted least-squares solution as LM; Q and P0 set how fast it gets there.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from laser_calib.estimation.lm import ProgressCallback
from laser_calib.estimation.problem import Fit, Problem, make_fit


@dataclass(frozen=True)
class EkfOptions:
    """The paper's settings (section IV-A): Q = R = 1e-4 I, at most 5000
    iterations, stop when the state changes by less than 1e-7 in norm.
    r is the variance of a spot coordinate the filter runs with (see
    filter_noise); None takes the noise model's own. p0 = 1 as filterpy's
    default (the paper does not state it)."""

    q: float = 1e-4
    r: float | None = 1e-4
    p0: float = 1.0
    max_iter: int = 5000
    tol: float = 1e-7
    # progress(done, total, note), called every 100 iterations; not an option of the math
    progress: ProgressCallback | None = field(default=None, compare=False, repr=False)


def information_update(x: np.ndarray, covariance: np.ndarray, information: np.ndarray,
                       gradient: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The EKF update (eq. 14-15) of state x (k,) with predicted covariance
    (k,k), from information H^T R^-1 H (k,k) and gradient H^T R^-1 (z - h(x))
    (k,): returns x+ (k,) and P+ (k,k)."""
    posterior = np.linalg.inv(np.linalg.inv(covariance) + information)
    posterior = 0.5 * (posterior + posterior.T)
    return x + posterior @ gradient, posterior


def filter_noise(problem: Problem, r: float | None) -> Problem:
    """The problem the filter runs on: its whole noise model (spot and joint sigma) scaled by one
    factor so that a spot coordinate's variance is the paper's R = r I. Scaling every variance
    alike leaves the weighted least-squares minimum where it is and sets the step. Not with a
    prior (a tolerance prior, an effect's penalty): its rows are not noise, so R would weigh the
    data against it and move the minimum; nor r=None. Replacing the spot sigma alone moved it
    too, with joint noise (the spot and joint variances' ratio changed): chi^2 94.7 where LM's
    minimum is 90.0, and 232.7 for 123.4 with the prior, 'converged' both times."""
    if r is None or np.isfinite(problem.prior_sigma).any():
        return problem
    factor = float(np.sqrt(r)) / problem.noise.sigma
    return problem.with_noise(replace(problem.noise, sigma=problem.noise.sigma * factor,
                                      joint_sigma=problem.noise.joint_sigma * factor))


def extended_kalman(problem: Problem, x0: np.ndarray, options: EkfOptions = EkfOptions()) -> Fit:
    """Paper eq. 13-15. The state is the free errors in their own units (the
    paper's Q and P0 are per unit of metre or radian)."""
    free = problem.free
    k = int(free.sum())
    x = np.array(x0, dtype=float)
    ekf_problem = filter_noise(problem, options.r)
    scales = problem.scales
    covariance = np.eye(k) * options.p0
    q = np.eye(k) * options.q
    history, costs = [x.copy()], []
    converged = False
    iterations = 0
    for iterations in range(1, options.max_iter + 1):
        covariance = covariance + q                                   # eq. 13
        normal = ekf_problem.normal_equations(x)
        costs.append(normal.cost)
        # Problem's Jacobian is in scaled parameters: H = J / scales in the state's units.
        state, covariance = information_update(x[free], covariance, normal.information / np.outer(scales, scales),
                                               normal.gradient / scales)
        change = np.linalg.norm(state - x[free])
        x[free] = state
        history.append(x.copy())
        if change < options.tol:
            converged = True
            break
        if options.progress is not None and iterations % 100 == 0:
            options.progress(iterations, options.max_iter,
                             f"state change {change:.2e} (stops below {options.tol:.0e}), cost {costs[-1]:.4g}")
    if options.progress is not None:
        options.progress(iterations, iterations, "converged" if converged else "stopped")
    # Report cost, covariance and chi^2 with the problem's own noise model.
    normal = problem.normal_equations(x)
    costs.append(normal.cost)
    return make_fit(problem, x, normal, iterations, converged, history, costs)
