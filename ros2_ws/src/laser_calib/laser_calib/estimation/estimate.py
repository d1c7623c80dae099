"""Geometric calibration from samples: the entry point every front end calls
(command line, ROS estimator service and online node, replay).

estimate(robot, samples, options) runs, in order:
1. identifiability at the nominal model: parameters the spots cannot separate
   are fixed at nominal and reported as merged (never as numbers);
2. if no spot sigma is given, a first fit estimates it from the residual
   (sigma^2 = chi^2 / dof at a trial sigma of 1 mm), and that value is used;
3. the fit (LM or the paper's EKF), with the optional prior (a manufacturing
   tolerance per parameter type, mean zero);
4. with a known sigma, a chi^2 test: if chi^2 exceeds dof by more than
   6 sqrt(2 dof), the minimum is suspect (a wrong local minimum, an outlier or
   an unmodelled effect); LM restarts from seeded random starts within twice
   the parameter scales and keeps the lowest cost; if still suspect, it says so;
5. robust (optional), the stated rule: after a fit, the seen spot with the
   largest whitened residual is dropped if its squared norm exceeds
   chi^2_2(0.999) = 13.82 (with the sigma in use), and the fit is repeated;
   at most 10 % of the spots are dropped; dropped spots are listed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from laser_calib.estimation.ekf import EkfOptions, extended_kalman
from laser_calib.estimation.identifiability import Identifiability, analyse
from laser_calib.estimation.lm import LmOptions, levenberg_marquardt
from laser_calib.estimation.problem import Fit, Problem, whitened_factor
from laser_calib.measurement.base import ANGLE_SCALE, LENGTH_SCALE, MeasurementModel, NoiseModel
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.io.samples import Samples

METHODS = ("lm", "ekf")
TRIAL_SIGMA = 0.001
CHI2_2_999 = 13.815510557964274  # 99.9 % quantile of chi^2 with 2 degrees of freedom


@dataclass(frozen=True)
class EstimateOptions:
    """method 'lm' or 'ekf'; spot_sigma (m) per spot coordinate, None to estimate it;
    joint_sigma (rad) of the joint readings; prior: tolerance prior_length (m) /
    prior_angle (rad) per error; robust outlier rejection; fixed: parameter names
    held at nominal; restarts of LM when the minimum is suspect."""

    method: str = "lm"
    spot_sigma: float | None = None
    joint_sigma: float = 0.0
    prior: bool = False
    prior_length: float = LENGTH_SCALE
    prior_angle: float = ANGLE_SCALE
    robust: bool = False
    fixed: tuple[str, ...] = ()
    restarts: int = 6
    seed: int = 0
    lm: LmOptions = LmOptions()
    ekf: EkfOptions = EkfOptions()

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; expected one of {', '.join(METHODS)}")
        if self.spot_sigma is not None and not (np.isfinite(self.spot_sigma) and self.spot_sigma > 0):
            raise ValueError(f"spot sigma must be a positive number of metres, got {self.spot_sigma}")


@dataclass(frozen=True)
class Estimate:
    """The result: fit holds x, the covariance and the history; sigma is the spot
    sigma used (estimated when sigma_estimated)."""

    names: tuple[str, ...]
    identifiable: np.ndarray
    identifiability: Identifiability
    fit: Fit
    sigma: float
    sigma_estimated: bool
    rejected: tuple[tuple[int, int], ...]
    warnings: tuple[str, ...]
    wall_time: float
    restarts: int = 0

    @property
    def values(self) -> np.ndarray:
        """(n,) the fitted x, nominal (0) where fixed: what the corrected model uses."""
        return self.fit.x

    @property
    def errors(self) -> np.ndarray:
        """(n,) the estimated errors, NaN where not identifiable (never reported as known)."""
        return np.where(self.identifiable, self.fit.x, np.nan)

    @property
    def std(self) -> np.ndarray:
        """(n,) standard deviations from the covariance, NaN where not identifiable."""
        return np.where(self.identifiable, self.fit.std, np.nan)

    def corrected(self, robot: Robot) -> Robot:
        return robot.with_errors(self.values[:robot.n_params])


def prior_sigmas(model: MeasurementModel, n_geometric: int, options: EstimateOptions) -> np.ndarray | None:
    if not options.prior:
        return None
    sigma = np.full(len(model.names), np.inf)
    lengths = model.scales[:n_geometric] == LENGTH_SCALE  # D-H or joint placements alike
    sigma[:n_geometric] = np.where(lengths, options.prior_length, options.prior_angle)
    return sigma


def estimate(robot: Robot, samples: Samples, options: EstimateOptions = EstimateOptions()) -> Estimate:
    """Geometric errors (4N+5) of ``robot`` from spot samples."""
    model = SpotModel(robot, samples)
    return estimate_model(model, options, prior_sigmas(model, robot.n_params, options))


def estimate_model(model: MeasurementModel, options: EstimateOptions, prior_sigma: np.ndarray | None = None,
                   x0: np.ndarray | None = None) -> Estimate:
    """The same steps on any measurement model (geometric + effects, other sensors)."""
    start = time.perf_counter()
    names = tuple(model.names)
    n = len(names)
    x0 = np.zeros(n) if x0 is None else np.asarray(x0, float)
    unknown = [name for name in options.fixed if name not in names]
    if unknown:
        raise ValueError(f"cannot fix unknown parameter {unknown[0]!r}")
    user_fixed = np.array([name in options.fixed for name in names])
    warnings: list[str] = []

    sigma = options.spot_sigma or TRIAL_SIGMA
    noise = NoiseModel(sigma, options.joint_sigma)
    factor, n_values = whitened_factor(model, noise, x0)
    if n_values == 0:
        raise ValueError("no measured spot to fit (every spot missing or its beam misses the screen)")
    ident = analyse(factor, model.scales, names, user_fixed)
    free = ident.free
    if n_values < free.sum() and prior_sigma is None:
        raise ValueError(f"{n_values} measured values cannot determine {int(free.sum())} parameters; "
                         "measure more poses or use the prior")

    def fit(problem: Problem, start_x: np.ndarray) -> Fit:
        if options.method == "lm":
            return levenberg_marquardt(problem, start_x, options.lm)
        return extended_kalman(problem, start_x, options.ekf)

    sigma_estimated = options.spot_sigma is None
    if sigma_estimated:
        trial = levenberg_marquardt(Problem(model, noise, free), x0, options.lm)
        sigma = TRIAL_SIGMA * float(np.sqrt(trial.chi2 / trial.dof))
        noise = NoiseModel(max(sigma, 1e-9), options.joint_sigma)

    problem = Problem(model, noise, free, prior_sigma)
    result = fit(problem, x0)
    restarts = 0
    if not sigma_estimated and _suspect(result):
        rng = np.random.default_rng(options.seed)
        for _ in range(options.restarts):
            restarts += 1
            start_x = x0.copy()
            start_x[free] += rng.uniform(-2, 2, int(free.sum())) * model.scales[free]
            candidate = levenberg_marquardt(problem, start_x, options.lm)
            if candidate.cost < result.cost - 1e-9 * max(result.cost, 1.0):
                result = candidate
            if not _suspect(result):
                break
        if _suspect(result):
            warnings.append(f"chi^2/dof = {result.chi2 / result.dof:.2f} with spot sigma {sigma * 1e3:.3g} mm: "
                            "the residual exceeds the noise model (outliers, an unmodelled effect, or a wrong "
                            "noise level); restarts found no better minimum")
        else:
            warnings.append(f"the first minimum was suspect; restart {restarts} found a lower one")

    rejected: list[tuple[int, int]] = []
    if options.robust:
        result, rejected = _reject_outliers(model, noise, free, prior_sigma, result, fit)
    if not result.converged:
        warnings.append(f"{options.method} stopped after {result.iterations} iterations without converging")

    return Estimate(names, free.copy(), ident, result, sigma, sigma_estimated, tuple(rejected), tuple(warnings),
                    time.perf_counter() - start, restarts)


def _suspect(result: Fit) -> bool:
    dof = result.dof
    return result.chi2 > dof + 6.0 * np.sqrt(2.0 * dof)


def _reject_outliers(model, noise, free, prior_sigma, result: Fit, fit) -> tuple[Fit, list[tuple[int, int]]]:
    res = model.residuals(result.x, True)
    n_spots = int(res.valid.sum())
    excluded = np.zeros(res.valid.shape, bool)
    rejected: list[tuple[int, int]] = []
    while len(rejected) < max(1, n_spots // 10):
        problem = Problem(model, noise, free, prior_sigma, excluded)
        res = problem.residuals(result.x, True)
        white = np.einsum("pij,pj->pi", noise.whitener(res), res.r.reshape(len(res.r), -1))
        d2 = (white.reshape(res.r.shape) ** 2).sum(axis=2)
        d2[~res.valid] = 0.0
        worst = np.unravel_index(np.argmax(d2), d2.shape)
        if d2[worst] <= CHI2_2_999:
            break
        excluded[worst] = True
        rejected.append((int(worst[0]), int(worst[1])))
        result = fit(Problem(model, noise, free, prior_sigma, excluded), result.x)
    return result, rejected
