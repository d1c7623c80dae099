"""Geometric calibration from samples: the entry point every front end calls
(command line, ROS estimator service and online node, replay).

estimate(robot, samples, options) runs, in order:
0. impossible spots (impossible_spots): a spot outside the screen, or one given
   where the nominal beam misses the screen by far, is flagged per pose and
   left out (a warning line lists them);
1. identifiability at the nominal model: parameters the spots cannot separate
   are fixed at nominal and reported as merged (never as numbers);
2. robust (the default, robust.py): IRLS with the Cauchy loss and a MAD scale
   on the same Jacobians, then gross outliers rejected and listed;
3. if no spot sigma is given, a fit estimates it from the residual
   (sigma^2 = chi^2 / dof at a trial sigma of 1 mm), and that value is used
   (when the robust rule rejected spots, the fits after it start from its
   final least-squares minimum (by LM), which without a prior is that trial;
   with LM and no joint noise it is also the fit, rescaled to the sigma);
4. identifiability again with the noise in use: a direction whose standard
   deviation exceeds STD_FACTOR times its tolerance scale is held too (not
   with the prior, which bounds every direction by its tolerance);
5. the fit (LM or the paper's EKF), with the optional prior (a manufacturing
   tolerance per parameter type, mean zero);
6. with a known sigma, a chi^2 test: if chi^2 exceeds dof by more than
   6 sqrt(2 dof), the minimum is suspect (a wrong local minimum, an outlier or
   an unmodelled effect); LM restarts from seeded random starts within twice
   the parameter scales and keeps the lowest cost; if still suspect, it says so.
Rank deficiency, an unconverged fit, dropped spots and a noise level far from
the given one are one warning line each (Estimate.warnings).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from laser_calib.estimation.ekf import EkfOptions, extended_kalman
from laser_calib.estimation.identifiability import STD_FACTOR, Identifiability, analyse
from laser_calib.estimation.lm import LmOptions, levenberg_marquardt
from laser_calib.estimation.problem import Fit, Problem, residuals_at, whitened_factor
from laser_calib.estimation.robust import ROBUST_RULE, robust_fit
from laser_calib.measurement.base import ANGLE_SCALE, LENGTH_SCALE, MeasurementModel, NoiseModel, Residuals
from laser_calib.measurement.frames import FRAMES
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.io.samples import Samples

METHODS = ("lm", "ekf")
TRIAL_SIGMA = 0.001
# A spot given where the nominal beam lands beyond the screen edge by more than
# this fraction of the half size cannot be that laser's: nominal errors move a
# spot by centimetres, not by a fifth of the screen.
MISS_MARGIN = 0.2
NOISE_RATIO = 2.0  # the residual's noise beyond 2x or below 1/2 the given sigma: a warning
LISTED = 8         # poses named in one warning line
MIN_SIGMA = 1e-7   # m: an estimated noise below 0.1 um is an exact fit, not a measurement
FAR_SCALES = 10.0  # a fitted error beyond 10 tolerance scales (100 mm, 10 deg) is not a manufacturing error
NOT_CONVERGED = "NOT CONVERGED"  # how an unconverged fit's warning starts (the console makes it an error line)


@dataclass(frozen=True)
class EstimateOptions:
    """method 'lm' or 'ekf'; spot_sigma (m) per spot coordinate, None to estimate it;
    joint_sigma (rad) of the joint readings; prior: tolerance prior_length (m) /
    prior_angle (rad) per error; robust outlier rejection (robust.py); fixed:
    parameter names held at nominal; restarts of LM when the minimum is suspect;
    std_factor: the identifiability threshold (identifiability.py), None for
    the numerical rank only."""

    method: str = "lm"
    spot_sigma: float | None = None
    joint_sigma: float = 0.0
    prior: bool = False
    prior_length: float = LENGTH_SCALE
    prior_angle: float = ANGLE_SCALE
    robust: bool = True
    fixed: tuple[str, ...] = ()
    restarts: int = 6
    seed: int = 0
    std_factor: float | None = STD_FACTOR
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
    sigma used (estimated when sigma_estimated); rejected: (pose index, channel)
    of the spots the robust rule dropped; impossible: (pose index, channel,
    reason) of the spots refused before the fit; robust: the rule and its
    figures, None when off."""

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
    impossible: tuple[tuple[int, int, str], ...] = ()
    robust: dict | None = None

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


def impossible_spots(robot: Robot, samples: Samples, nominal: Residuals) -> list[tuple[int, int, str]]:
    """(pose index, laser index, reason) of every given spot that cannot be:
    outside the screen, or where the nominal beam misses the screen by far;
    nominal: the spot model's residuals at zero errors (valid: the beam meets
    the screen plane ahead)."""
    half = np.array([robot.screen.half_y, robot.screen.half_z])
    seen = samples.seen
    out = []
    outside = seen & (np.abs(np.nan_to_num(samples.spots)) > half).any(axis=2)
    beyond = np.abs(nominal.predicted) - half * (1 + MISS_MARGIN)
    misses = seen & ~outside & ~(nominal.valid & (beyond <= 0).all(axis=2))
    for p, j in zip(*np.nonzero(outside)):
        y, z = samples.spots[p, j]
        out.append((int(p), int(j), f"outside the screen (y, z = {y:.4g}, {z:.4g} m; half sizes "
                                    f"{half[0]:.4g}, {half[1]:.4g} m)"))
    for p, j in zip(*np.nonzero(misses)):
        out.append((int(p), int(j), "the nominal beam misses the screen by far"))
    return sorted(out)


def estimate(robot: Robot, samples: Samples, options: EstimateOptions = EstimateOptions()) -> Estimate:
    """Geometric errors (4N+5) of ``robot`` from spot samples."""
    model = SpotModel(robot, samples)
    nominal = residuals_at(model, np.zeros(len(model.names)))
    impossible = impossible_spots(robot, samples, nominal)
    outside = sum(why.startswith("outside") for *_, why in impossible)
    if outside and outside == samples.seen.sum():
        raise ValueError(f"every spot lies outside the screen (half sizes {robot.screen.half_y:g}, "
                         f"{robot.screen.half_z:g} m): spot coordinates are in metres (these look like millimetres)")
    return estimate_model(model, options, prior_sigmas(model, robot.n_params, options), impossible=impossible,
                          at_start=nominal)


def pose_ids(model: MeasurementModel) -> np.ndarray:
    """(P,) the pose ids of the model's samples (effects wrap a base model)."""
    while not hasattr(model, "samples") and hasattr(model, "base"):
        model = model.base
    return np.asarray(model.samples.pose)


def listing(model: MeasurementModel, units: list[tuple[int, int]]) -> str:
    ids = pose_ids(model)
    many = len(units) > 1 and len({c for _, c in units}) > 1
    names = [f"pose {ids[p]}" + (f" laser {c + 1}" if many else "") for p, c in units[:LISTED]]
    return ", ".join(names) + (f" and {len(units) - LISTED} more" if len(units) > LISTED else "")


def _analysis(model: MeasurementModel, noise: NoiseModel, x0: np.ndarray, fixed: np.ndarray,
              excluded: np.ndarray | None, std_factor: float | None) -> tuple[Identifiability, int]:
    factor, n_values = whitened_factor(model, noise, x0, excluded)
    if n_values == 0:
        raise ValueError("no measured spot to fit (every spot missing, refused, or its beam misses the screen)")
    return analyse(factor, model.scales, tuple(model.names), fixed, std_factor=std_factor), n_values


def estimate_model(model: MeasurementModel, options: EstimateOptions, prior_sigma: np.ndarray | None = None,
                   x0: np.ndarray | None = None, impossible: list[tuple[int, int, str]] = (),
                   at_start: Residuals | None = None) -> Estimate:
    """The same steps on any measurement model (geometric + effects, other sensors).
    prior_sigma: None takes the model's own (an EffectModel's penalised effects), if any;
    impossible: (pose index, channel, reason) of units refused before the fit;
    at_start: the model's residuals at x0 (residuals_at), when the caller has them."""
    start = time.perf_counter()
    if prior_sigma is None:
        prior_sigma = getattr(model, "prior_sigma", None)
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
    at_start = residuals_at(model, x0) if at_start is None else at_start
    seen, dims = at_start.valid, at_start.r.shape[2]   # (P,C) the units measured at the start, D values each
    excluded = None
    if impossible:
        excluded = np.zeros(seen.shape, bool)
        for p, c, _ in impossible:
            excluded[p, c] = True
        warnings.append(f"{len(impossible)} physically impossible measurements refused, not fitted: "
                        + "; ".join(f"pose {pose_ids(model)[p]} laser {c + 1}: {why}"
                                    for p, c, why in impossible[:LISTED])
                        + (f" and {len(impossible) - LISTED} more" if len(impossible) > LISTED else ""))
    # With a prior every direction is bounded by its tolerance: the prior, not
    # the threshold, decides what the data add.
    factor = options.std_factor if prior_sigma is None else None
    given_factor = None if options.spot_sigma is None else factor
    ident, n_values = _analysis(model, noise, x0, user_fixed, excluded, given_factor)
    free = ident.free
    # as many values as parameters fit exactly: nothing tests the fit or estimates the noise
    if n_values <= free.sum() and prior_sigma is None:
        raise ValueError(f"{n_values} measured values cannot determine and check {int(free.sum())} parameters; "
                         "measure more poses or use the prior")

    def fit(problem: Problem, start_x: np.ndarray) -> Fit:
        if options.method == "lm":
            return levenberg_marquardt(problem, start_x, options.lm)
        return extended_kalman(problem, start_x, options.ekf)

    rejected: list[tuple[int, int]] = []
    robust = None
    start_x = x0
    least_squares = None  # the robust rule's final least-squares fit, when the fits below can start from it
    robust_sigma = sigma  # the spot sigma it ran with (the given one or the trial)
    if options.robust:
        outcome = robust_fit(model, noise, free, prior_sigma, x0,
                             lambda problem, start: levenberg_marquardt(problem, start, options.lm), excluded,
                             at_start, options.lm)
        rejected = [(int(p), int(c)) for p, c in zip(*np.nonzero(outcome.rejected))]
        if rejected:
            excluded = outcome.rejected if excluded is None else excluded | outcome.rejected
        # Its final fit is least squares on the kept spots, by LM whatever the method (the
        # EKF's fixed point is the same, in hundreds of iterations). With spots rejected,
        # the fits below start from its minimum, and without a prior it is the sigma trial
        # itself. Without, they start from x0 as without the robust rule: on clean data the
        # result is least squares bit for bit whichever front end ran it, robust or not.
        if rejected:
            start_x = outcome.fit.x
            if prior_sigma is None:
                least_squares = outcome.fit
        kept = int((seen if excluded is None else seen & ~excluded).sum())
        robust = {"rule": ROBUST_RULE, "scale": outcome.scale, "rounds": outcome.rounds,
                  "weights_converged": outcome.converged, "rejected": len(rejected), "kept": kept}
        if rejected:
            warnings.append(f"robust: {len(rejected)} of {kept + len(rejected)} measurements rejected as outliers "
                            f"and not fitted: {listing(model, rejected)}")
        if outcome.overflow:
            warnings.append(f"robust: {outcome.overflow} of {kept} measurements lie beyond the outlier limit: "
                            "the model does not fit the data (an unmodelled effect or wrong nominal model); "
                            "none rejected")
        if not outcome.converged:
            warnings.append(f"robust: the weights did not settle in {outcome.rounds} rounds")

    sigma_estimated = options.spot_sigma is None
    if sigma_estimated:
        trial = least_squares or levenberg_marquardt(Problem(model, noise, free, excluded=excluded), start_x,
                                                     options.lm)
        sigma = TRIAL_SIGMA * float(np.sqrt(trial.chi2 / trial.dof))
        noise = NoiseModel(max(sigma, 1e-9), options.joint_sigma)
        start_x = trial.x
    if sigma_estimated or rejected:
        ident, _ = _analysis(model, noise, x0, user_fixed, excluded, factor)
        free = ident.free
    held = [name for name, keep, user in zip(names, free, user_fixed) if not keep and not user]
    if held:
        warnings.append(f"rank deficient: the data determine {ident.rank} of {n - int(user_fixed.sum())} "
                        f"parameters; held at nominal, reported as combinations: {', '.join(held)}")
    start_x = np.where(free, start_x, x0)

    problem = Problem(model, noise, free, prior_sigma, excluded)
    if (options.method == "lm" and least_squares is not None and not np.any(np.asarray(noise.joint_sigma) > 0)
            and np.array_equal(free, least_squares.free)):
        # the same weighted least squares at another sigma: its minimum does not move
        result = rescaled(least_squares, noise.sigma / robust_sigma)
    else:
        result = fit(problem, start_x)
    restarts = 0
    if not sigma_estimated and _suspect(result):
        result, restarts = _restart(problem, result, x0, free, model.scales, options)
        if _suspect(result):
            warnings.append(f"chi^2/dof = {result.chi2 / result.dof:.2f} with spot sigma {sigma * 1e3:.3g} mm "
                            f"(the residual says {sigma * np.sqrt(result.chi2 / result.dof) * 1e3:.3g} mm): the "
                            "residual exceeds the noise model (outliers, an unmodelled effect, or a wrong noise "
                            "level); restarts found no better minimum")
        else:
            warnings.append(f"the first minimum was suspect; restart {restarts} found a lower one")
    elif not sigma_estimated and result.chi2 / result.dof < NOISE_RATIO ** -2:
        warnings.append(f"noise: the residual says {sigma * np.sqrt(result.chi2 / result.dof) * 1e3:.3g} mm per "
                        f"value, far below the given spot sigma {sigma * 1e3:.3g} mm (standard deviations are "
                        "overstated)")
    lost = int((seen if excluded is None else seen & ~excluded).sum()) - result.n_values // dims
    if lost > 0:
        warnings.append(f"the fit lost {lost} measurements: at the fitted errors their beams no longer reach the "
                        "screen, so the cost fell by dropping them; this minimum is not a calibration")
    if sigma_estimated and sigma < MIN_SIGMA:
        warnings.append(f"noise: the residual is {sigma * 1e3:.3g} mm per value: the data are fitted exactly "
                        "(repeated poses?), so they test nothing and the standard deviations mean nothing")
    # frames are guesses, not drawings: only the robot's own errors have a tolerance
    own = free & np.array([name.split("_", 1)[0] not in FRAMES for name in names])
    size = np.abs(result.x) / model.scales
    if np.any(own & (size > FAR_SCALES)):
        worst = int(np.argmax(np.where(own, size, 0.0)))
        warnings.append(f"implausible: {names[worst]} is fitted at {size[worst]:.0f} times its tolerance scale; a "
                        "wrong minimum, a wrong nominal model or data the model cannot explain")
    if not result.converged:
        warnings.append(f"{NOT_CONVERGED}: {options.method} stopped after {result.iterations} iterations; the "
                        "values are not a minimum")
    return Estimate(names, free.copy(), ident, result, sigma, sigma_estimated, tuple(rejected), tuple(warnings),
                    time.perf_counter() - start, restarts, tuple(impossible), robust)


def rescaled(fit: Fit, ratio: float) -> Fit:
    """A least-squares fit without joint noise or prior under a noise sigma
    ``ratio`` times its own: x stays, chi^2 and the costs scale by 1 / ratio^2,
    the covariance by ratio^2."""
    return replace(fit, covariance=fit.covariance * ratio ** 2, cost=fit.cost / ratio ** 2,
                   chi2=fit.chi2 / ratio ** 2, cost_history=fit.cost_history / ratio ** 2)


def _suspect(result: Fit) -> bool:
    dof = result.dof
    return result.chi2 > dof + 6.0 * np.sqrt(2.0 * dof)


def _restart(problem: Problem, result: Fit, x0: np.ndarray, free: np.ndarray, scales: np.ndarray,
             options: EstimateOptions) -> tuple[Fit, int]:
    """Seeded random LM starts within twice the scales; the lowest cost wins."""
    rng = np.random.default_rng(options.seed)
    restarts = 0
    for _ in range(options.restarts):
        restarts += 1
        start_x = x0.copy()
        start_x[free] += rng.uniform(-2, 2, int(free.sum())) * scales[free]
        candidate = levenberg_marquardt(problem, start_x, options.lm)
        if candidate.cost < result.cost - 1e-9 * max(result.cost, 1.0):
            result = candidate
        if not _suspect(result):
            break
    return result, restarts
