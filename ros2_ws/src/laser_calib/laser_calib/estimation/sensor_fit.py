"""Calibration from point or pose samples: D-H errors and unknown frames together.

calibrate(robot, samples, options) runs, on estimation.estimate_model:
1. identifiability with the frames first: a frame error and a D-H error that
   move the target alike (d_1 and theta_1 against the sensor frame, the last
   link's a, alpha against the target frame, every SLM error) are carried by
   the frame; the D-H error is held at nominal and listed in ``absorbed``;
2. the nominal fit: frames only, everything else held (the reference
   "nominal D-H" figure: the frames fitted, the arm as designed);
3. step 1 again at the fitted frames, and the full fit from there, with the
   user's masks (``fixed``) and priors; what it kept but its own minimum does
   not determine (undetermined_at) is held too and the fit repeated, with a
   warning when holding it costs more chi^2 than undetermined parameters can;
   a failed fit (a wrong model) is not refitted so, but what it kept and does
   not determine at its values (Estimate.undetermined) is written at nominal;
4. for pose samples, the weight of rotation against translation
   (rotation_length, m/rad) from the residuals of the fit: the ratio of the RMS
   translation to the RMS rotation residual (a variance-component step,
   done twice), and both fits repeated with it.

An ``extend`` hook wraps the sensor model (e.g. effects.model.EffectModel with
joint effects); it gets the model and the indices of its poses in the caller's
sample set, so bases that depend on the whole sequence can be sliced.
kfold() repeats the calibration on k-1 folds and predicts the held-out fold.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from laser_calib.estimation.failures import FAR_SCALES, MAX_RESIDUAL, within_data
from laser_calib.estimation.folds import kfold_labels
from laser_calib.estimation.estimate import Estimate, EstimateOptions, estimate_model, prior_sigmas
from laser_calib.estimation.identifiability import analyse, carried_by_kept, check_fixed
from laser_calib.measurement.base import MeasurementModel, NoiseModel, whiten
from laser_calib.model.robot import Robot
from laser_calib.measurement.frames import FRAME_PARAMS, frame_list, is_frame_param, robot_frames, with_frames
from laser_calib.measurement.sensor import PointModel, PoseModel
from laser_calib.io.sensor_samples import SensorSamples

VARIANCE_STEPS = 2
SensorModel = PointModel | PoseModel
Extend = Callable[[SensorModel, np.ndarray], MeasurementModel]


@dataclass(frozen=True)
class SensorFitOptions:
    """estimate: the estimator's options (fixed names are the user's masks;
    prior applies to the D-H errors); frame_prior_length (m) / frame_prior_angle
    (rad): a zero-mean prior on the frame errors, None for none; rotation_length
    (m/rad) of pose residuals, None to estimate it; scale: estimate the
    sensor's scale per axis (models.py)."""

    estimate: EstimateOptions = field(default_factory=EstimateOptions)
    frame_prior_length: float | None = None
    frame_prior_angle: float | None = None
    rotation_length: float | None = None
    scale: bool = False


@dataclass(frozen=True)
class SensorFit:
    """model: the final model; nominal: the frames-only fit; estimate: the full
    fit; absorbed: name -> why it was held (Absorbed); rotation_length (m/rad)
    the pose residuals were weighted with."""

    model: MeasurementModel
    nominal: Estimate
    estimate: Estimate
    absorbed: dict[str, Absorbed]
    rotation_length: float

    @property
    def undetermined(self) -> tuple[str, ...]:
        """What a failed full fit kept but does not determine at its values (Estimate.undetermined),
        written at nominal."""
        return self.estimate.undetermined

    @property
    def determined(self) -> np.ndarray:
        """(n,) the parameters whose values the calibrated robot file writes: those the fit kept,
        but for a failed fit's undetermined ones."""
        return self.estimate.determined

    def corrected(self, robot: Robot) -> Robot:
        """The robot with the estimated D-H errors and frames (guess · error), a failed fit's
        undetermined ones at nominal (zero error)."""
        errors = self.estimate.written(np.zeros(len(self.model.names)))
        values = dict(zip(self.model.names, errors))
        guesses = robot_frames(robot)
        frames = {frame: guesses[frame].perturbed(np.array([values.get(f"{frame}_{p}", 0.0) for p in FRAME_PARAMS]))
                  for frame in frame_list(robot)}
        return with_frames(robot.with_errors(errors[:robot.n_params]), frames)

    @property
    def held(self) -> tuple[str, ...]:
        """The robot's parameters this fit held or wrote at nominal as undetermined, in the model's
        order: the robot file's ``held`` key (robot_file.with_held), as estimate writes it. Not those a
        frame of this set-up carries: a set-up without that frame (the laser screen) may determine them."""
        by_fit = self.estimate.identifiability.merged
        return tuple(name for name in self.model.names if not is_frame_param(name) and (
            name in by_fit or name in self.undetermined
            or (name in self.absorbed and not self.absorbed[name].by_frames)))

    @property
    def carried(self) -> dict[str, tuple[str, ...]]:
        """Kept parameter name -> the held ones whose combination it carries, held
        before the fit (absorbed) or by it: its value is that combination's."""
        carriers = {name: held.carriers for name, held in self.absorbed.items()}
        carriers.update(self.estimate.identifiability.carriers)
        # the held names in the model's order, as the spot estimate's identifiability lists them
        carried = carried_by_kept({name: carriers[name] for name in self.model.names if name in carriers})
        kept = {name for name, free in zip(self.model.names, self.estimate.identifiable) if free}
        # a carrier found before the fit may have been held since: only a kept value is a combination's
        return {name: held for name, held in carried.items() if name in kept}


def make_model(robot: Robot, samples: SensorSamples, rotation_length: float = 1.0,
               scale: bool = False) -> SensorModel:
    if samples.kind == "pose":
        return PoseModel(robot, samples, rotation_length, scale)
    return PointModel(robot, samples, scale)


@dataclass(frozen=True)
class Absorbed:
    """A parameter held before the fit: why, and the names of the parameters that
    carry its combination (none: the data do not determine it)."""

    why: str
    carriers: tuple[str, ...] = ()

    @property
    def by_frames(self) -> bool:
        return any(is_frame_param(name) for name in self.carriers)


def frames_first(model: MeasurementModel, noise: NoiseModel, fixed: np.ndarray,
                 x: np.ndarray | None = None, std_factor: float | None = None,
                 excluded: tuple[tuple[int, int], ...] = (), why: str = "") -> dict[str, Absorbed]:
    """Parameters the frames carry: identifiability with the frame columns first,
    linearised at ``x`` (default zero: the frame guesses); std_factor: the noise
    threshold (identifiability.analyse), with ``noise`` the real one; excluded:
    (pose index, channel) of units a fit left out; why: put before each held
    parameter's text."""
    res = model.residuals(np.zeros(len(model.names)) if x is None else x, True)
    if excluded:
        keep = res.valid.copy()
        keep[tuple(np.array(excluded).T)] = False
        res = replace(res, valid=keep, jac=np.where(keep[..., None, None], res.jac, 0.0))
    _, jac = whiten(res, noise.whitener(res))
    frame = np.array([is_frame_param(n) for n in model.names])
    order = np.r_[np.flatnonzero(frame), np.flatnonzero(~frame)]
    names = tuple(model.names[i] for i in order)
    ident = analyse(jac[:, order], model.scales[order], names, fixed[order], std_factor=std_factor)
    free = np.empty(len(order), bool)
    free[order] = ident.free
    return {name: Absorbed(why + ident.merged.get(name, "not seen by the data"), ident.carriers.get(name, ()))
            for name, keep, held in zip(model.names, free, fixed) if not keep and not held}


def undetermined_at(model: MeasurementModel, fit: Estimate, options: SensorFitOptions) -> dict[str, Absorbed]:
    """What ``fit`` kept but its own minimum does not determine (at the noise it
    found, over the units it fitted). The first decision is linearised at the
    frames-only fit, whose marker lies off a joint axis by its noise when the
    true one is on it: a point on the last axis showed that axis's tilt and the
    next placement as 3 tolerances there; the fit then moved the marker and
    both came out with 60 tolerances, written as numbers."""
    factor = _std_factor(model, options)
    if _wrong_model(model, fit, factor):
        return {}
    left_out = (*fit.rejected, *((p, c) for p, c, _ in fit.impossible))
    return frames_first(model, NoiseModel(fit.sigma, options.estimate.joint_sigma), ~fit.identifiable,
                        fit.values, factor, left_out, "not identifiable at the calibrated values: ")


def _std_factor(model: MeasurementModel, options: SensorFitOptions) -> float | None:
    """The noise threshold of identifiability (tolerance scales); None with a prior, which bounds every value."""
    return options.estimate.std_factor if _prior(model, options) is None else None


def _determined(model: MeasurementModel, fit: Estimate, factor: float | None) -> np.ndarray:
    """(n,) the parameters ``fit`` kept whose std at its values is within ``factor`` tolerance scales."""
    return fit.identifiable & within_data(fit.fit.std, model.scales, factor)


def _wrong_model(model: MeasurementModel, fit: Estimate, factor: float | None) -> bool:
    """A minimum that is no calibration whatever it holds: it misses the data
    beyond any sensor, or fits a robot error it determines (std within the
    noise threshold) beyond any manufacturing one. Its noise is no sensor's and
    its weak directions a wrong model's: holding them only moves the failure
    (the UR10e's shoulder and elbow columns swapped: elbow_joint.x at 62
    tolerances, std 0.2)."""
    level = fit.sigma * np.sqrt(fit.fit.chi2 / max(fit.fit.dof, 1))
    size = np.abs(fit.values) / model.scales
    own = np.isin(model.names, model.robot.param_names)
    return level > MAX_RESIDUAL or bool(np.any(own & _determined(model, fit, factor) & (size > FAR_SCALES)))


def _costly_hold(fit: Estimate, held: Estimate, names: tuple[str, ...]) -> str | None:
    """The warning when holding the k parameters ``names`` at nominal raised chi^2 (at
    ``fit``'s noise, per value) beyond k + 6 sqrt(2k), the spread of what k
    undetermined ones could cost, else None. They are held all the same, as the
    spot estimate holds what it cannot determine whatever the fit then misses:
    a value the minimum does not determine is no calibration (the paper's 4-DOF
    arm with its frames held 3 mm wrong: slm_x kept with a std of 4600
    tolerances, theta4 of 53000, written as numbers; held, chi^2 rose by 83)."""
    chi2 = held.fit.chi2 * (held.sigma / fit.sigma) ** 2 * fit.fit.n_values / held.fit.n_values
    k = len(names)
    cost, limit = chi2 - fit.fit.chi2, k + 6.0 * np.sqrt(2.0 * k)
    if cost <= limit:
        return None
    them = "it" if k == 1 else "them"
    return (f"not identifiable at the calibrated values, held at nominal: {', '.join(names)}; holding {them} "
            f"raised chi^2 by {cost:.3g}, beyond the {limit:.3g} that {k} undetermined parameter{'s' * (k > 1)} "
            f"can cost: the model is wrong (a frame held wrong, an unmodelled effect) or the data are insufficient "
            f"to determine {them}")


def _prior(model: MeasurementModel, options: SensorFitOptions) -> np.ndarray | None:
    sigma = prior_sigmas(model, model.robot.n_params, options.estimate)
    if options.frame_prior_length is None and options.frame_prior_angle is None:
        return sigma
    sigma = np.full(len(model.names), np.inf) if sigma is None else sigma
    for i, name in enumerate(model.names):
        if is_frame_param(name):
            value = options.frame_prior_angle if name.rsplit("_", 1)[1].startswith("r") else options.frame_prior_length
            sigma[i] = np.inf if value is None else value
    return sigma


def _rotation_length(model: MeasurementModel, fit: Estimate, current: float) -> float:
    """RMS translation / RMS rotation residual, m/rad (rotation values unscaled),
    over the poses the fit kept (a rejected outlier would set the ratio)."""
    res = model.residuals(fit.values, False)
    keep = res.valid.copy()
    for p, c in fit.rejected:
        keep[p, c] = False
    values = res.r[keep]
    translation = np.sqrt(np.mean(values[:, :3] ** 2))
    rotation = np.sqrt(np.mean(values[:, 3:] ** 2)) / current
    return float(translation / max(rotation, 1e-12))


def calibrate(robot: Robot, samples: SensorSamples, options: SensorFitOptions = SensorFitOptions(),
              extend: Extend | None = None, index: np.ndarray | None = None) -> SensorFit:
    """Nominal (frames-only) and full fits; see the module docstring. index (P,):
    the samples' positions in the caller's set, passed to ``extend``."""
    index = np.arange(len(samples)) if index is None else np.asarray(index)

    def build(length: float) -> MeasurementModel:
        base = make_model(robot, samples, length, options.scale)
        return base if extend is None else extend(base, index)

    length = options.rotation_length or 1.0
    model = build(length)
    user = options.estimate.fixed
    check_fixed(user, model.names)
    sigma = options.estimate.spot_sigma or 1e-3
    held = np.array([name in user for name in model.names])
    noise = NoiseModel(sigma, options.estimate.joint_sigma)
    not_frames = tuple(n for n in model.names if not is_frame_param(n))

    def fit(m: MeasurementModel, names: tuple[str, ...], x0: np.ndarray | None) -> Estimate:
        # what the frames carry is decided by frames_first's order, not re-chosen by amplification
        est_options = replace(options.estimate, fixed=tuple(dict.fromkeys(names)), amplify=None)
        return estimate_model(m, est_options, _prior(m, options), x0)

    nominal = fit(model, tuple(user) + tuple(frames_first(model, noise, held)) + not_frames, None)
    # What the frames carry, again at the fitted frames: at the guesses a marker
    # guessed at the tip's origin sits on the last axis, where a joint's offset
    # and the next placement move it alike; at the fitted marker they do not.
    absorbed = frames_first(model, noise, held, nominal.values)

    costly: list[str] = []  # the warnings of holds that cost chi^2: said on the final fit, before what they cause

    def full_fit(m: MeasurementModel, start: np.ndarray) -> Estimate:
        # Each refit holds at least one parameter more, so this ends; a fit holds its parameters at their start.
        est = fit(m, tuple(user) + tuple(absorbed), start)
        while more := undetermined_at(m, est, options):
            refit_start = np.where([name in more for name in m.names], nominal.values, start)
            refit = fit(m, tuple(user) + tuple(absorbed) + tuple(more), refit_start)
            if warning := _costly_hold(est, refit, tuple(more)):
                costly.append(warning)
            absorbed.update(more)
            start, est = refit_start, refit
        return est

    full = full_fit(model, nominal.values)
    if samples.kind == "pose" and options.rotation_length is None:
        for _ in range(VARIANCE_STEPS):
            length = _rotation_length(model, full, length)
            model = build(length)
            nominal = fit(model, tuple(user) + tuple(absorbed) + not_frames, nominal.values)
            full = full_fit(model, full.values)
    # a calibration's minimum determines what it kept (undetermined_at); a failed one's names what it
    # does not (Estimate.undetermined, by the same threshold: _std_factor is estimate_model's)
    return SensorFit(model, nominal, replace(full, warnings=tuple(costly) + full.warnings), absorbed, length)


@dataclass(frozen=True)
class HeldOut:
    """Per pose (P,), predicted from the fit on the other folds: position
    errors (m), rotation errors (rad, NaN for points), for the full and the
    nominal (frames-only) models; fold (P,) index of each pose's fold."""

    position: np.ndarray
    rotation: np.ndarray
    nominal_position: np.ndarray
    nominal_rotation: np.ndarray
    fold: np.ndarray


def sensor_of(model: MeasurementModel) -> SensorModel:
    """The point or pose model itself, or the one an extension (EffectModel) wraps."""
    return model if isinstance(model, (PointModel, PoseModel)) else model.base


def pose_errors(model: MeasurementModel, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P,) position error (m) and rotation error (rad; NaN for points) per pose:
    the norm of the translation and the angle of inv(predicted) · measured."""
    res = model.residuals(x, False)
    values = res.r[:, 0]
    position = np.where(res.valid[:, 0], np.linalg.norm(values[:, :3], axis=1), np.nan)
    if values.shape[1] == 3:
        return position, np.full(len(position), np.nan)
    length = sensor_of(model).rotation_length
    return position, np.where(res.valid[:, 0], np.linalg.norm(values[:, 3:], axis=1) / length, np.nan)


def kfold(robot: Robot, samples: SensorSamples, options: SensorFitOptions, k: int = 5, seed: int = 0,
          extend: Extend | None = None) -> HeldOut:
    """k-fold cross-validation: each fold predicted by the fit on the others."""
    fold = kfold_labels(len(samples), k, seed)
    out = np.full((4, len(samples)), np.nan)
    for f in range(k):
        train, test = np.flatnonzero(fold != f), np.flatnonzero(fold == f)
        result = calibrate(robot, samples.subset(train), options, extend, train)
        base = make_model(robot, samples.subset(test), result.rotation_length, options.scale)
        test_model = base if extend is None else extend(base, test)
        out[0, test], out[1, test] = pose_errors(test_model, result.estimate.values)
        out[2, test], out[3, test] = pose_errors(test_model, result.nominal.values)
    return HeldOut(*out, fold)
