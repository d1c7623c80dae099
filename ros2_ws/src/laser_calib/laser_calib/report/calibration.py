"""The result of one geometric calibration: what every output is made from.

calibrate() runs the estimate and evaluates it once: the spots the nominal and
the calibrated model predict on each set (calibration, test). The distances,
the tables, result.json, the plots and the Estimate service's response are all
derived from this one object; writing files is a separate step
(report.files.write_outputs).

A robot file with an ``effects:`` key (a diagnosis's robot_calibrated.yaml,
docs/effects.md) is the model with those effects: their parameters are
estimated with the geometric errors, from the file's values, and written back.
A learned compensator (diagnosis.compensator, the file a diagnosis keeps) adds
its offsets, fixed, to every pose of every set; it must be the one made for
this model (the same parameter names).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from laser_calib import __version__
from laser_calib.effects.base import Effect
from laser_calib.effects.catalog import effects_from_robot, effects_to_yaml
from laser_calib.effects.effect_model import EffectModel
from laser_calib.effects.screen import Surface, extrapolation_note
from laser_calib.estimation.estimate import Estimate, EstimateOptions, estimate
from laser_calib.estimation.failures import UNDETERMINED, first_failure
from laser_calib.estimation.folds import test_range_warnings
from laser_calib.estimation.identifiability import FIXED_NOTE, at_values, carried_note, weak_and_large
from laser_calib.estimation.problem import residuals_at, whitened_factor
from laser_calib.io.revisits import repeat_warnings
from laser_calib.io.samples import Samples, reading_warnings
from laser_calib.measurement.base import NoiseModel, RobotModel
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.model.robot_file import held, held_warnings, with_held
from laser_calib.report.noise import noise_warnings
from laser_calib.report.plots import display_units
from laser_calib.report.pose_table import NOT_FITTED, fit_status
from laser_calib.report.test_outliers import test_outlier_warnings, test_status
from laser_calib.report.statistics import iso9283, laser_stats, worse_on_test_warning

if TYPE_CHECKING:  # scikit-learn (1 s to import): only where a compensator is loaded
    from laser_calib.diagnosis.compensator import Compensator


def finite_or_none(value: float):
    return float(value) if math.isfinite(value) else None


def shown_mm(value: float | None) -> str:
    """A figure of laser_stats as printed: None (no spot's distance is finite) as 'n/a'."""
    return "n/a" if value is None else f"{value:.3f}"


MODELS = ("nominal", "calibrated")


@dataclass(frozen=True)
class SetEvaluation:
    """One set of samples and the spots both models predict for it: nominal and
    calibrated (P,2,2) in m, NaN where the beam misses the screen; status (P,2) per
    spot: the calibration set's fit_status, the test set's test_status; counts: the
    status of the spots the set's figures are over."""

    samples: Samples
    nominal: np.ndarray
    calibrated: np.ndarray
    status: np.ndarray | None = None
    counts: str | tuple[str, ...] = "fitted"

    @property
    def counted(self) -> str | tuple[str, ...] | None:
        """The status of the spots the set's figures are over: 'fitted' on a calibration set (those the
        fit refused or rejected would report what it did not do), 'tested' and 'beyond' on a test set
        (its outliers apart, test_status), None (every seen spot) without a status."""
        return None if self.status is None else self.counts

    def spots(self, status: str | tuple[str, ...] | None = None) -> np.ndarray:
        """(P,2,2) measured spots in m; NaN where unseen and, given statuses, where the spot's is another."""
        if status is None:
            return self.samples.spots
        return np.where(np.isin(self.status, status)[..., None], self.samples.spots, np.nan)

    def distances(self, model: str, status: str | tuple[str, ...] | None = None) -> np.ndarray:
        """(P,2) distance in m between measured and predicted spot; NaN where spots(status) is."""
        return np.linalg.norm(self.spots(status) - getattr(self, model), axis=2)


@dataclass(frozen=True)
class Calibration:
    """robot: the nominal model; sets: 'calibration' and optionally 'test'; start:
    the robot file's values (no geometric error, its effects' values) the fit
    started from; sources: where the inputs came from (file names), for
    result.json; effects: those of the robot file (estimated after the geometric
    errors), compensator: the learned compensator applied, if any."""

    robot: Robot
    options: EstimateOptions
    estimate: Estimate
    sets: dict[str, SetEvaluation]
    start: np.ndarray
    sources: dict = field(default_factory=dict)
    effects: tuple[Effect, ...] = ()
    compensator: Compensator | None = None

    @property
    def samples(self) -> Samples:
        return self.sets["calibration"].samples

    @property
    def calibrated(self) -> Robot:
        """The robot file's model with the estimate: D-H values corrected, effect values refitted; what a
        failed fit does not determine (Estimate.undetermined) at the file's values, held as what it could
        not separate (the spots out of step with the joint readings: d1 and d2 were written over 0.7 m off,
        with stds of 130 tolerance scales)."""
        est = self.estimate
        written = est.written(self.start)
        corrected = with_held(self.robot.with_errors(written[:self.robot.n_params]),
                              (*est.identifiability.merged, *est.undetermined, *held_for(self.compensator, self.robot)))
        if not self.effects:
            return corrected
        values = np.split(written[self.robot.n_params:], np.cumsum([len(e.params) for e in self.effects])[:-1])
        return replace(corrected, extra={**corrected.extra, "effects": effects_to_yaml(self.effects, values)})

    def units(self) -> list[tuple[float, str]]:
        """(factor from SI, unit shown) of every estimated parameter: mm or deg for the
        geometric errors, each effect parameter in its own unit."""
        factors = display_units(self.robot.param_kinds())
        out = [(float(f), "mm" if f == 1e3 else "deg") for f in factors]
        return out + [(1.0, unit) for e in self.effects for unit in e.units]

    @cached_property
    def spot_error(self) -> dict:
        """{set: {"before": per-laser stats, "after": ...}} against the measured spots (mm), over
        each set's counted spots: the calibration's fitted ones (the others: spot_error_not_fitted)."""
        return {name: _before_after(s, s.counted) for name, s in self.sets.items()}

    @cached_property
    def spot_error_not_fitted(self) -> dict:
        """{status: {"before": ..., "after": ...}} (mm) of the calibration spots the fit did not use, per
        status some spot has ('rejected', 'refused'): measured, so reported, apart from what the fit achieved."""
        s = self.sets["calibration"]
        return {status: _before_after(s, status) for status in NOT_FITTED if (s.status == status).any()}

    @cached_property
    def spot_error_test_outliers(self) -> dict | None:
        """{"before": ..., "after": ...} (mm) of the test spots beyond the outlier limit (test_status), None
        without: measured, so reported, apart from the test figures."""
        s = self.sets.get("test")
        return _before_after(s, "outlier") if s is not None and (s.status == "outlier").any() else None

    @cached_property
    def repeatability(self) -> dict:
        """ISO 9283 AP / RP (mm) of each laser's spot over the poses visited more than
        once, per set, the calibrated model's spot standing for the command."""
        out = {}
        for name, s in self.sets.items():
            spots = s.spots(s.counted)
            by_laser = {f"laser{j + 1}": iso9283(s.samples.pose, spots[:, j], s.calibrated[:, j], 1e3)
                        for j in range(spots.shape[1])}
            if any(v is not None for v in by_laser.values()):
                out[name] = by_laser
        return out

    def to_json(self) -> dict:
        """The content of result.json."""
        est, options = self.estimate, self.options
        units = self.units()
        errors = []
        robot_held, compensator_held = held(self.robot), held_for(self.compensator, self.robot)
        for i, name in enumerate(est.names):
            unit = {"mm": "m", "deg": "rad"}.get(units[i][1], units[i][1])
            entry = {"name": name, "value": finite_or_none(est.errors[i]), "std": finite_or_none(est.std[i]),
                     "identifiable": bool(est.identifiable[i]), "unit": unit}
            if name in est.undetermined:  # a failed fit's: where it went is no value (errors), the file has nominal
                entry["note"] = UNDETERMINED
            elif name in compensator_held:
                entry["note"] = "held at nominal: the compensator's fit could not determine it"
            elif name in options.fixed and name not in robot_held:  # the user's, not the data's
                entry["note"] = FIXED_NOTE
            elif name in est.identifiability.merged:
                entry["note"] = est.identifiability.merged[name]
            elif name in est.identifiability.carried:
                entry["note"] = carried_note(name, est.identifiability.carried[name])
            elif name in robot_held:
                entry["note"] = "held at nominal: the calibration that wrote the robot file could not determine it"
            errors.append(entry)
        ident = est.identifiability
        options_dict = {k: v for k, v in asdict(options).items() if k not in ("lm", "ekf")}
        if options.spot_sigma is None:  # no --spot-sigma: the fit estimated it (spot_sigma_estimated)
            options_dict["spot_sigma_source"] = "estimated"
        solver = asdict(options.ekf if options.method == "ekf" else options.lm)
        solver.pop("progress", None)
        options_dict[options.method] = solver
        return {
            "robot": self.robot.name,
            "software": f"laser_calib {__version__}",
            # said at the top, as urdf_corrections.json and diagnosis.json say them: a reader of the values
            # below finds no other mark of a fit that is no calibration than a line among the warnings
            "failure": self.failure,
            "caution": self.caution,
            "method": options.method,
            "options": options_dict,
            "errors": errors,
            "identifiability": {"rank": ident.rank, "parameters": len(ident.names),
                                "condition_number": finite_or_none(ident.condition),
                                "unseen_combinations": list(ident.null_combinations), "merged": ident.merged,
                                "shares": ident.shares},
            "spot_sigma_m": est.sigma,
            "spot_sigma_estimated": est.sigma_estimated,
            "joint_sigma_rad": est.joint_sigma,
            "joint_sigma_estimated": est.joint_sigma_estimated,
            "chi2": est.fit.chi2,
            "dof": est.fit.dof,
            "spot_error": self.spot_error,
            "spot_error_not_fitted": self.spot_error_not_fitted,
            "spot_error_test_outliers": self.spot_error_test_outliers,
            "iso9283_spot": self.repeatability,
            "iterations": est.fit.iterations,
            "converged": bool(est.fit.converged),
            "restarts": est.restarts,
            "wall_time_s": est.wall_time,
            "rejected_spots": [{"pose": int(self.samples.pose[p]), "laser": j + 1} for p, j in est.rejected],
            "impossible_spots": [{"pose": int(self.samples.pose[p]), "laser": j + 1, "reason": why}
                                 for p, j, why in est.impossible],
            "robust": est.robust,
            "warnings": list(est.warnings),
            "inputs": self.sources,
            "effects": [e.label for e in self.effects],
            "compensator": None if self.compensator is None else {
                "targets": [t for t, u in zip(self.compensator.targets, self.compensator.used) if u],
                "heldout_gain": self.compensator.heldout_gain, "file": self.sources.get("compensator")},
        }

    @property
    def failure(self) -> str | None:
        """The warning that says this estimate is no calibration (NOT CONVERGED, NOT A
        CALIBRATION: estimation/failures.py), None when it is one."""
        return first_failure(self.estimate.warnings)

    @cached_property
    def caution(self) -> str | None:
        """The warning that the test poses, never fitted, are missed by more than the nominal
        model (worse_on_test), or else that large corrections are written that the data barely
        determine (identifiability.WEAK_AND_LARGE), said in the calibrated files too (read once per
        file); None without."""
        return next(iter(worse_on_test(self.sets)), weak_and_large(self.estimate.warnings))

    def summary(self) -> str:
        """One line: the spot error before and after over the spots fitted, as the nodes log it."""
        before, after = self.spot_error["calibration"]["before"]["all"], self.spot_error["calibration"]["after"]["all"]
        return (f"{self.options.method} on {len(self.samples)} poses: mean spot error {shown_mm(before['mean_mm'])} mm "
                f"-> {shown_mm(after['mean_mm'])} mm (max {shown_mm(before['max_mm'])} -> {shown_mm(after['max_mm'])}; "
                f"{after['n']} spots fitted{self.not_fitted_count()})"
                + ("; " + "; ".join(self.estimate.warnings) if self.estimate.warnings else ""))

    def not_fitted_count(self) -> str:
        """', 1 rejected, 2 refused': the calibration spots not fitted, per status; '' when none."""
        status = self.sets["calibration"].status
        return "".join(f", {n} {word}" for word in NOT_FITTED if (n := int((status == word).sum())))


def _before_after(evaluation: SetEvaluation, status: str | None) -> dict:
    """{"before": ..., "after": ...}: laser_stats of the nominal and calibrated models' distances to spots(status)."""
    return {label: laser_stats(evaluation.distances(model, status))
            for label, model in zip(("before", "after"), MODELS)}


def spot_model(robot: Robot, samples: Samples, effects: tuple[Effect, ...] = (),
               compensator: Compensator | None = None) -> RobotModel:
    """The model a calibration fits and predicts with: the spot model, with the robot
    file's effects and the compensator's fixed offsets when there are any."""
    if not effects and compensator is None:
        return SpotModel(robot, samples)
    model = EffectModel(SpotModel(robot, samples), effects)
    return model if compensator is None else compensator.apply(model)


def evaluate(robot: Robot, samples: Samples, est: Estimate, test: Samples | None = None, effects: tuple = (),
             compensator: Compensator | None = None, start: np.ndarray | None = None) -> dict[str, SetEvaluation]:
    """Predict every set once with the nominal (the robot file's model as given, start) and the
    calibrated model; on the calibration set these are the estimate's own predictions at its
    start and its result (est fitted this model there, calibrate)."""
    start = np.zeros(len(est.values)) if start is None else start

    def predicted(s: Samples, known: np.ndarray | None, values: np.ndarray) -> np.ndarray:
        return known if known is not None else residuals_at(spot_model(robot, s, effects, compensator), values).predicted

    out = {"calibration": SetEvaluation(samples, predicted(samples, est.predicted_at_start, start),
                                        predicted(samples, est.fit.predicted, est.values),
                                        fit_status(samples.seen, est.rejected, est.impossible))}
    if test is not None:
        model = spot_model(robot, test, effects, compensator)
        out["test"] = SetEvaluation(test, residuals_at(model, start).predicted,
                                    residuals_at(model, est.values).predicted,
                                    test_status(model, test.seen, est, test.spots.shape[2]), ("tested", "beyond"))
    return out


def held_for(compensator: Compensator | None, robot: Robot) -> tuple[str, ...]:
    """The errors the compensator's fit held at nominal that the robot file does not hold already."""
    return tuple(name for name in (compensator.held if compensator else ()) if name not in held(robot))


def calibrate(robot: Robot, samples: Samples, options: EstimateOptions, test: Samples | None = None,
              sources: dict | None = None, compensator: Compensator | None = None) -> Calibration:
    """Estimate the errors from samples and evaluate the result (no files written): the
    geometric errors, and the robot file's effects and compensator when it has any (module docstring)."""
    sources = dict(sources or {})
    # what the calibration that wrote the robot file, or the compensator's fit, could not determine, this one holds too
    compensator_held = held_for(compensator, robot)
    options = replace(options, fixed=tuple(dict.fromkeys((*options.fixed, *held(robot), *compensator_held))))
    effects, values = effects_from_robot(robot, str(sources.get("robot", "robot")))
    effects = tuple(effects)
    model = spot_model(robot, samples, effects, compensator)
    start = np.concatenate([np.zeros(robot.n_params), *values])
    est = estimate(robot, samples, options, model, start)
    if est.identifiability.carriers:  # what each kept value stands for, where it was fitted (identifiability.at_values)
        factor, _ = whitened_factor(model, NoiseModel(max(est.sigma, 1e-9), est.joint_sigma), est.values,
                                    est.fit.excluded)
        est = replace(est, identifiability=at_values(est.identifiability, factor, model.scales))
    said = reading_warnings(samples, test) + repeat_warnings(samples, test, robot.joint_names, sources)
    if test is not None:  # a test pose beyond the joint ranges calibrated on is an extrapolation: said with the fit's
        said += test_range_warnings(samples.q, test.q, "test", robot.joint_names)
        beyond = extrapolation_note([e.label for e in effects if isinstance(e, Surface)], samples.spots, test.spots)
        said += [f"test: {beyond}"] if beyond else []
    said += held_warnings(robot, sources.get("robot", "the robot file")) + noise_warnings(robot, est)
    said += [f"held at nominal, as the fit of the compensator {compensator.source} held them (not determined by its "
             f"data; its key model.held): {', '.join(compensator_held)}"] if compensator_held else []
    sets = evaluate(robot, samples, est, test, effects, compensator, start)
    said += test_outliers(sets) + worse_on_test(sets)
    if compensator is not None:  # the check refits without it: only when one is applied
        from laser_calib.report.compensator_check import compensator_warnings
        said += compensator_warnings(robot, samples, options, effects, start, sets, compensator.source)
    est = replace(est, warnings=est.warnings + tuple(said))
    return Calibration(robot, options, est, sets, start, sources, effects, compensator)


def test_outliers(sets: dict[str, SetEvaluation]) -> list[str]:
    """The warning naming the test spots beyond the outlier limit (test_status), none without."""
    s = sets.get("test")
    return [] if s is None else test_outlier_warnings(s.status, s.samples, "residuals.csv l1_fit, l2_fit")


def worse_on_test(sets: dict[str, SetEvaluation]) -> list[str]:
    """The warning when the calibrated model misses the test set's spots by more than the nominal
    one (RMS over the spots both predict): the one figure the fit never saw says the calibration
    made things worse (it printed '92.488 mm -> 326.610 mm' under nothing but an 'implausible')."""
    if "test" not in sets:
        return []
    nominal, calibrated = (sets["test"].distances(model, sets["test"].counted) for model in MODELS)
    return worse_on_test_warning(
        nominal, calibrated, sets["test"].samples.pose,
        "test: the calibrated model misses the held-out spots by more than the nominal one (RMS {before:.3g} mm -> "
        "{after:.3g} mm, over the {count} spots both predict)",
        "the calibration does not carry over to them (a wrong minimum, samples out of step with the joint readings, "
        "or sets measured under other conditions)")
