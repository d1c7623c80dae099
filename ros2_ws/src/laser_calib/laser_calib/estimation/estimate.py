"""Geometric calibration from samples: the entry point every front end calls
(command line, ROS estimator service and online node, replay).

estimate(robot, samples, options) runs, in order:
0. impossible spots (impossible.py): a spot outside the screen, or one given
   where the nominal beam misses the screen by far, is flagged per pose and
   left out (a warning line lists them); if the minimum reached meets the
   screen with such a beam, all steps run again with its spot (a gross
   nominal error, not a wrong spot);
1. identifiability at the nominal model: parameters the spots cannot separate
   are fixed at nominal and reported as merged (never as numbers); one pass
   of the model gives the residuals at the start (step 0 finds the impossible
   spots in them) and the whitened factor of every spot measured there;
2. robust (the default, robust.py): IRLS with the Cauchy loss and a MAD scale
   on the same Jacobians, then gross outliers rejected and listed where the
   rest leave residual values to judge them by (never too few: TooFewValues);
3. if no spot sigma is given, a fit estimates it from the residual
   (sigma^2 = chi^2 / dof at a trial sigma of 1 mm), and that value is used; a joint sigma not given
   (None) is estimated by maximum likelihood (with the spot one, or at the one given), kept where the
   residual shows it (noise_components.joint_noise_evidence): it moves a pose's spots by its levers'
   length, and taken as 0 the stds were too small; the robust rule runs again with it (outliers.py)
   (when the robust rule rejected spots, the fits after it start from its
   final least-squares minimum (by LM), which without a prior is that trial;
   with LM and no joint noise it is also the fit, rescaled to the sigma);
   from few residual values it is uncertain, said (redundancy.sigma_warnings);
4. identifiability again with the noise in use: a direction whose standard deviation exceeds
   STD_FACTOR times its tolerance scale is held too (not with the prior, which bounds every
   direction by its tolerance); without joint noise from step 1's factor, rescaled to the noise and
   without the rejected spots (a downdate: the model evaluated on their poses only); holding more
   than step 2 or 3's fit, step 5 starts from x0 (that fit's kept values carry the held ones' moves);
5. the fit (LM or the paper's EKF), with the optional prior (a manufacturing
   tolerance per parameter type, mean zero);
6. with a known sigma, a chi^2 test: if chi^2 exceeds dof by more than
   6 sqrt(2 dof), the minimum is suspect (a wrong local minimum, an outlier or
   an unmodelled effect); LM restarts from seeded random starts within twice
   the parameter scales and keeps the lowest cost; if still suspect, it says so.
Rank deficiency, an unconverged fit, dropped spots and a noise level far from the given one are
one warning line each (Estimate.warnings); what a failed fit kept but does not determine at its
values is named (Estimate.undetermined), for its files to write at nominal.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Callable

import numpy as np

from laser_calib.estimation import joint_noise_bound
from laser_calib.estimation.ekf import EkfOptions, extended_kalman
from laser_calib.estimation.failures import (NOT_CONVERGED, NoSpotToFit, beyond_data, first_failure, fit_failures,
                                             implausible, residual_level)
from laser_calib.estimation.folds import still_joint_warnings
from laser_calib.estimation.identifiability import (AMPLIFY, STD_FACTOR, Identifiability, TooFewValues, analyse,
                                                   check_fixed, weak_warnings)
from laser_calib.estimation.impossible import impossible_spots, judged_again
from laser_calib.estimation.lm import LmOptions, levenberg_marquardt, restarted, suspect
from laser_calib.estimation.problem import (Fit, Problem, downdated, factor_and_residuals, n_poses, rescaled,
                                            residuals_at, whitened_factor)
from laser_calib.estimation.redundancy import NOISE_RATIO, joint_noise, sigma_warnings
from laser_calib.estimation.outliers import LISTED, listing, model_samples, rejection
from laser_calib.measurement.base import ANGLE_SCALE, LENGTH_SCALE, MeasurementModel, NoiseModel, Residuals
from laser_calib.measurement.frames import is_frame_param
from laser_calib.measurement.noise_components import MIN_SIGMA
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.io.revisits import copied
from laser_calib.io.samples import Samples

# Finds the units to refuse, (pose index, channel, reason), in a model's residuals at the start.
Refusal = Callable[[Residuals], list[tuple[int, int, str]]]
METHODS = ("lm", "ekf")
TRIAL_SIGMA = 0.001
JOINT_NOISE_ALPHA = 0.05   # the joint-reading noise a residual must show before it weighs the fit


def spot_sigma_at_zero(sigma: float, sigma_estimated: bool) -> bool:
    """The estimated spot sigma is at 0 (below MIN_SIGMA): with no joint-reading noise the data
    are fitted exactly; beside one it is the likelihood's boundary, the joint noise carrying the
    residual (the spot component is below what the data resolve, not an exact fit)."""
    return sigma_estimated and sigma < MIN_SIGMA


@dataclass(frozen=True)
class EstimateOptions:
    """method 'lm' or 'ekf'; spot_sigma (m) per spot coordinate, None to estimate it;
    joint_sigma (rad) of the joint readings, None: estimated (step 3); prior: tolerance prior_length (m) /
    prior_angle (rad) per error; robust outlier rejection (robust.py); fixed:
    parameter names held at nominal; restarts of LM when the minimum is suspect;
    std_factor: the identifiability threshold (identifiability.py), None for
    the numerical rank only; amplify: a combination's carrier moved by more than
    this is held instead (identifiability.AMPLIFY), None to hold in the model's order;
    noise_checks: the residual's judgement of the joint-reading noise (joint_noise_bound),
    warnings only, which the diagnosis's hundreds of fold and candidate fits skip."""

    method: str = "lm"
    spot_sigma: float | None = None
    spot_sigma_source: str = "given"  # where spot_sigma came from, as the warnings name it (a caller may estimate it)
    joint_sigma: float | None = 0.0
    prior: bool = False
    prior_length: float = LENGTH_SCALE
    prior_angle: float = ANGLE_SCALE
    robust: bool = True
    fixed: tuple[str, ...] = ()
    restarts: int = 6
    seed: int = 0
    std_factor: float | None = STD_FACTOR
    amplify: float | None = AMPLIFY
    noise_checks: bool = True
    lm: LmOptions = LmOptions()
    ekf: EkfOptions = EkfOptions()

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; expected one of {', '.join(METHODS)}")
        if self.spot_sigma is not None and not (np.isfinite(self.spot_sigma) and self.spot_sigma > 0):
            raise ValueError(f"spot sigma must be a positive number of metres, got {self.spot_sigma}")


@dataclass(frozen=True)
class Estimate:
    """The result: fit holds x, the covariance and the history; sigma is the spot sigma used (estimated
    when sigma_estimated), joint_sigma the joint-reading sigma (rad; estimated when
    joint_sigma_estimated); rejected: (pose index, channel) of the spots the robust rule dropped; impossible:
    (pose index, channel, reason) of the spots refused before the fit; robust: the rule and its figures,
    None when off; predicted_at_start (P,C,D): what the model predicts at the start x0 (the nominal model),
    as fit.predicted at the result; undetermined: what a failed fit kept whose std at its values is beyond
    the identifiability threshold (failures.beyond_data; a calibration's minimum determines what it kept)."""

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
    predicted_at_start: np.ndarray | None = field(default=None, repr=False)
    undetermined: tuple[str, ...] = ()
    joint_sigma: float = 0.0
    joint_sigma_estimated: bool = False

    @property
    def values(self) -> np.ndarray:
        """(n,) the fitted x, nominal (0) where fixed: what the corrected model uses."""
        return self.fit.x

    @property
    def errors(self) -> np.ndarray:
        """(n,) the estimated errors, NaN where not identifiable or not determined (never reported as known)."""
        return np.where(self.determined, self.fit.x, np.nan)

    @property
    def std(self) -> np.ndarray:
        """(n,) standard deviations from the covariance, NaN where not identifiable."""
        return np.where(self.identifiable, self.fit.std, np.nan)

    @property
    def determined(self) -> np.ndarray:
        """(n,) the parameters a calibrated robot file writes a value of: those kept, but the undetermined."""
        return self.identifiable & ~np.isin(self.names, self.undetermined)

    def written(self, nominal: np.ndarray) -> np.ndarray:
        """(n,) the values a calibrated robot file writes: the fitted ones, the undetermined at ``nominal`` (n,)."""
        return np.where(np.isin(self.names, self.undetermined), nominal, self.values)


def prior_sigmas(model: MeasurementModel, n_geometric: int, options: EstimateOptions) -> np.ndarray | None:
    if not options.prior:
        return None
    sigma = np.full(len(model.names), np.inf)   # a length or an angle tolerance, of D-H or joint placements alike
    sigma[:n_geometric] = np.where(model.scales[:n_geometric] == LENGTH_SCALE, options.prior_length,
                                   options.prior_angle)
    return sigma


def estimate(robot: Robot, samples: Samples, options: EstimateOptions = EstimateOptions(),
             model: MeasurementModel | None = None, x0: np.ndarray | None = None) -> Estimate:
    """Geometric errors (4N+5) of ``robot`` from spot samples; with ``model`` (the spot
    model of these samples with effects, report.calibration.spot_model) its parameters
    too, from x0 (default 0)."""
    model = SpotModel(robot, samples) if model is None else model
    fit = partial(estimate_model, model, options, prior_sigmas(model, robot.n_params, options), x0)
    first = fit(impossible=lambda start: impossible_spots(robot, samples, start))
    again = (judged_again(robot, samples, first.impossible, residuals_at(model, first.values))
             if first.impossible else [])
    if len(again) == len(first.impossible):
        return first
    second = fit(impossible=again)
    readmitted = sorted({(p, c) for p, c, _ in first.impossible} - {(p, c) for p, c, _ in again})
    return replace(second, wall_time=first.wall_time + second.wall_time,
                   warnings=(f"{len(readmitted)} measurements whose nominal beam missed the screen by far were "
                             f"fitted: the calibrated beams meet the screen there: {listing(model, readmitted)}",)
                   + second.warnings)


def _factor_without(model: MeasurementModel, factor: np.ndarray, then: NoiseModel, noise: NoiseModel,
                    x0: np.ndarray, excluded: np.ndarray | None, removed: np.ndarray | None) -> np.ndarray:
    """The whitened factor at x0 (whitened_factor) under ``noise`` without the units
    ``excluded`` (P,C), from ``factor`` whitened under the noise ``then`` and
    without all of them but ``removed`` (P,C). Without joint noise the whitened
    Jacobian only scales with sigma and a unit's rows are its own, so the removed
    units' rows leave by a downdate (the model evaluated on their poses only);
    else, or where the downdate would not be exact, a new pass."""
    nothing_removed = removed is None or not removed.any()
    if nothing_removed and then is noise:
        return factor
    joint = then.joint_noise or noise.joint_noise
    if not joint and n_poses(model) is not None:
        factor = factor * (then.sigma / noise.sigma)
        if not nothing_removed:
            poses = np.flatnonzero(removed.any(axis=1))
            rows, _ = whitened_factor(model.subset(poses), noise, x0, ~removed[poses])
            factor = downdated(factor, rows)
        if factor is not None:
            return factor
    return whitened_factor(model, noise, x0, excluded)[0]


def estimate_model(model: MeasurementModel, options: EstimateOptions, prior_sigma: np.ndarray | None = None,
                   x0: np.ndarray | None = None, impossible: list[tuple[int, int, str]] | Refusal = ()) -> Estimate:
    """The same steps on any measurement model (geometric + effects, other sensors).
    prior_sigma: None takes the model's own (an EffectModel's penalised effects), if any;
    impossible: (pose index, channel, reason) of units refused before the fit,
    or the function that finds them in the model's residuals at x0."""
    start = time.perf_counter()
    if prior_sigma is None:
        prior_sigma = getattr(model, "prior_sigma", None)
    names = tuple(model.names)
    n = len(names)
    x0 = np.zeros(n) if x0 is None else np.asarray(x0, float)
    check_fixed(options.fixed, names)
    user_fixed = np.array([name in options.fixed for name in names])
    warnings: list[str] = []

    sigma = options.spot_sigma or TRIAL_SIGMA
    noise = NoiseModel(sigma, options.joint_sigma or 0.0)
    # one pass at the start: its residuals and the whitened factor of every unit measured there
    start_factor, _, at_start = factor_and_residuals(model, noise, x0)
    seen, dims = at_start.valid, at_start.r.shape[2]   # (P,C) the units measured at the start, D values each
    if callable(impossible):
        impossible = impossible(at_start)
    excluded = None
    if impossible:
        excluded = np.zeros(seen.shape, bool)
        for p, c, _ in impossible:
            excluded[p, c] = True
        warnings.append(f"{len(impossible)} physically impossible measurements refused, not fitted: "
                        + "; ".join(f"pose {model_samples(model).pose[p]} laser {c + 1}: {why}"
                                    for p, c, why in impossible[:LISTED])
                        + (f" and {len(impossible) - LISTED} more" if len(impossible) > LISTED else ""))
    # With a prior every direction is bounded by its tolerance: the prior, not
    # the threshold, decides what the data add.
    factor = options.std_factor if prior_sigma is None else None
    given_factor = None if options.spot_sigma is None else factor
    kept = seen if excluded is None else seen & ~excluded   # (P,C) the spots the fit is given
    n_values = int(kept.sum()) * dims
    if n_values == 0:
        raise NoSpotToFit()
    start_factor = _factor_without(model, start_factor, noise, noise, x0, excluded, excluded)
    start_noise = noise
    ident = analyse(start_factor, model.scales, names, user_fixed, std_factor=given_factor, amplify=options.amplify)
    free = ident.free
    # as many values as parameters fit exactly: nothing tests the fit or estimates the noise; nor do
    # rows that copy another exactly (one pose logged 50 times was '27 mm -> 0.000 mm', exit 0)
    copies = copied(model_samples(model))
    distinct = int(kept[~copies].sum()) * dims
    if distinct <= free.sum() and prior_sigma is None:
        refused = len(impossible) if impossible else 0   # beams that miss the start's screen among them
        raise TooFewValues(distinct, int(free.sum()), refused=(refused, refused * dims), n_params=n,
                           copies=int(copies.sum()))

    def fit(problem: Problem, start_x: np.ndarray) -> Fit:
        if options.method == "lm":
            return levenberg_marquardt(problem, start_x, options.lm)
        return extended_kalman(problem, start_x, options.ekf)

    rejected: list[tuple[int, int]] = []
    removed = None  # (P,C) the units the robust rule rejected
    robust = None
    start_x = x0
    least_squares = None  # the robust rule's final least-squares fit, when the fits below can start from it
    robust_sigma = sigma  # the spot sigma it ran with (the given one or the trial)
    refused = excluded    # the impossible units, left out before the rule
    robust_at, robust_said = len(warnings), 0   # where its warnings are, and how many
    if options.robust:
        # With spots rejected, the fits below start from the rule's minimum, and without a prior it is the
        # sigma trial itself. Without, they start from x0 as without the rule: on clean data the result is
        # least squares bit for bit whichever front end ran it, robust or not.
        outcome = rejection(model, noise, free, prior_sigma, x0, refused, at_start, options.lm)
        rejected, removed, robust, excluded = outcome.rejected, outcome.removed, outcome.summary, outcome.left_out
        if rejected:
            start_x = outcome.fit.x
            least_squares = outcome.fit if prior_sigma is None else None
        warnings.extend(outcome.warnings)
        robust_said = len(outcome.warnings)

    sigma_estimated = options.spot_sigma is None
    joint_sigma, joint_estimated, unseen_joint = noise.joint_sigma, False, None   # unseen: its ML sigma, not shown
    spot_held = None if sigma_estimated else sigma   # a given spot sigma is held while the joint one is estimated
    if sigma_estimated or (options.joint_sigma is None and sigma >= MIN_SIGMA):
        trial = least_squares or levenberg_marquardt(Problem(model, noise, free, excluded=excluded), start_x,
                                                     options.lm)
        if sigma_estimated:
            sigma = TRIAL_SIGMA * float(np.sqrt(trial.chi2 / trial.dof))
            sigma_dof = trial.n_values - int(trial.free.sum())   # the residual values it rests on
        if options.joint_sigma is None and sigma >= MIN_SIGMA:
            spot, joint, p = joint_noise(model, trial, excluded, spot_held)
            if p < JOINT_NOISE_ALPHA:
                if options.robust:  # the rule again, with the noise it did not know (outliers.py)
                    shown = NoiseModel(spot, joint)
                    outcome = rejection(model, shown, free, prior_sigma, x0, refused, at_start, options.lm)
                    warnings[robust_at:robust_at + robust_said] = outcome.warnings
                    rejected, removed, robust = outcome.rejected, outcome.removed, outcome.summary
                    excluded = outcome.left_out
                    least_squares = outcome.fit if prior_sigma is None else None
                    trial = least_squares or levenberg_marquardt(Problem(model, shown, free, excluded=excluded),
                                                                 trial.x, options.lm)
                    sigma_dof = trial.n_values - int(trial.free.sum())
                    spot, joint, _ = joint_noise(model, trial, excluded, spot_held)   # of the units it kept
                sigma, joint_sigma, joint_estimated = spot, joint, True
            else:
                unseen_joint = joint
        noise = NoiseModel(max(sigma, 1e-9), joint_sigma)
        start_x = trial.x
    if sigma_estimated or rejected or joint_estimated:
        ident = analyse(_factor_without(model, start_factor, start_noise, noise, x0, excluded, removed),
                        model.scales, names, user_fixed, std_factor=factor, amplify=options.amplify)
        start_x = start_x if np.array_equal(ident.free, free) else x0   # holding more: no start (step 4)
        free = ident.free
    held = [name for name, keep, user in zip(names, free, user_fixed) if not keep and not user]
    if held:  # a wrong sigma, not the data, holds those by_noise
        given = (f" at the spot sigma {options.spot_sigma_source} ({sigma * 1e3:.3g} mm; {ident.by_noise} held "
                 "for it)" if ident.by_noise and not sigma_estimated else "")
        warnings.append(f"rank deficient: the data determine {ident.rank} of {n - int(user_fixed.sum())} "
                        f"parameters{given}; held at nominal, reported as combinations: {', '.join(held)}")

    problem = Problem(model, noise, free, prior_sigma, excluded)
    if (options.method == "lm" and least_squares is not None and not noise.joint_noise
            and np.array_equal(free, least_squares.free)):
        # the same weighted least squares at another sigma: its minimum does not move
        result = rescaled(least_squares, noise.sigma / robust_sigma)
    else:
        result = fit(problem, start_x)
    if joint_estimated and sigma_estimated and prior_sigma is None and result.chi2 > 0:
        # the variance factor a posteriori: the likelihood set the components' ratio, chi^2 / dof their level
        # (none when the fit moved every beam off the screen: no residual to set it, the loss is said below)
        ratio = float(np.sqrt(result.chi2 / result.dof))
        result, sigma, joint_sigma = rescaled(result, ratio), sigma * ratio, joint_sigma * ratio
    restarts = 0
    if not sigma_estimated and suspect(result):
        result, restarts = restarted(problem, result, x0, model.scales, options.restarts, options.seed, options.lm)
        if suspect(result):
            warnings.append(f"chi^2/dof = {result.chi2 / result.dof:.2f} with spot sigma {sigma * 1e3:.3g} mm "
                            f"(the residual says {sigma * np.sqrt(result.chi2 / result.dof) * 1e3:.3g} mm): the "
                            "residual exceeds the noise model (outliers, an unmodelled effect, or a wrong noise "
                            "level); restarts found no better minimum")
        else:
            warnings.append(f"the first minimum was suspect; restart {restarts} found a lower one")
    elif not sigma_estimated and result.chi2 / result.dof < NOISE_RATIO ** -2:
        warnings.append(f"noise: the residual says {sigma * np.sqrt(result.chi2 / result.dof) * 1e3:.3g} mm per "
                        f"value, far below the spot sigma {options.spot_sigma_source}, {sigma * 1e3:.3g} mm (standard "
                        "deviations are overstated)")
    lost = int((seen if excluded is None else seen & ~excluded).sum()) - result.n_values // dims
    warnings.extend(fit_failures(lost, residual_level(model, result, excluded, sigma, bool(joint_sigma))))
    at_zero = spot_sigma_at_zero(sigma, sigma_estimated)
    exact = at_zero and not joint_sigma
    noise_doubts = sigma_warnings(sigma, sigma_dof) if sigma_estimated and not at_zero else []
    if exact:
        warnings.append(f"noise: the residual is {sigma * 1e3:.3g} mm per value: the data are fitted exactly "
                        "(repeated poses?), so they test nothing and the standard deviations mean nothing")
    warnings.extend(noise_doubts)
    if unseen_joint is not None and options.noise_checks and prior_sigma is None and not exact and not noise_doubts:
        warnings.extend(joint_noise_bound.hidden_warnings(joint_noise_bound.hidden(model, result, excluded, unseen_joint),
                                                          names))
    if options.joint_sigma and options.noise_checks:   # given
        warnings.extend(joint_noise_bound.given_warnings(model, result, excluded, options.joint_sigma))
    # frames are guesses, not drawings: only the robot's own errors have a tolerance
    own = free & np.array([not is_frame_param(name) for name in names])
    # std and carried held errors excuse a value beyond FAR_SCALES only on a sound sigma (not from 1-7 dof)
    sound = not sigma_estimated or (not exact and not noise_doubts)
    warnings.extend(implausible(names, result.x, model.scales, own, getattr(getattr(model, "robot", None),
                                "param_names", ()), *((result.std, ident.carry) if sound else (None, None))))
    warnings.extend(weak_warnings(names, result.std, model.scales, own, result.x)
                    if sound and prior_sigma is None else [])
    if getattr(model, "robot", None) is not None and getattr(model, "samples", None) is not None:
        warnings.extend(still_joint_warnings(model.samples.q, model.robot.joint_names))
    if not result.converged:
        warnings.append(f"{NOT_CONVERGED}: {options.method} stopped after {result.iterations} iterations; the "
                        "values are not a minimum")
    undetermined = beyond_data(names, free, result.std, model.scales, factor) if first_failure(warnings) else ()
    return Estimate(names, free.copy(), ident, result, sigma, sigma_estimated, tuple(rejected), tuple(warnings),
                    time.perf_counter() - start, restarts, tuple(impossible), robust, at_start.predicted, undetermined,
                    joint_sigma, joint_estimated)
