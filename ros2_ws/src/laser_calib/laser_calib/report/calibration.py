"""The result of one geometric calibration: what every output is made from.

calibrate() runs the estimate and evaluates it once: the spots the nominal and
the calibrated model predict on each set (calibration, test). The distances,
the tables, result.json, the plots and the Estimate service's response are all
derived from this one object; writing files is a separate step
(report.files.write_outputs).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from functools import cached_property

import numpy as np

from laser_calib import __version__
from laser_calib.estimation.estimate import Estimate, EstimateOptions, estimate
from laser_calib.estimation.problem import residuals_at
from laser_calib.io.samples import Samples
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.report.plots import display_units
from laser_calib.report.statistics import iso9283, laser_stats


def finite_or_none(value: float):
    return float(value) if math.isfinite(value) else None


@dataclass(frozen=True)
class SetEvaluation:
    """One set of samples and the spots both models predict for it: nominal and
    calibrated (P,2,2) in m, NaN where the beam misses the screen."""

    samples: Samples
    nominal: np.ndarray
    calibrated: np.ndarray

    def distances(self, model: str) -> np.ndarray:
        """(P,2) distance in m between measured and predicted spot; NaN where unseen."""
        return np.linalg.norm(self.samples.spots - getattr(self, model), axis=2)


@dataclass(frozen=True)
class Calibration:
    """robot: the nominal model; sets: 'calibration' and optionally 'test';
    sources: where the inputs came from (file names), for result.json."""

    robot: Robot
    options: EstimateOptions
    estimate: Estimate
    sets: dict[str, SetEvaluation]
    sources: dict = field(default_factory=dict)

    @property
    def samples(self) -> Samples:
        return self.sets["calibration"].samples

    @property
    def calibrated(self) -> Robot:
        return self.estimate.corrected(self.robot)

    @cached_property
    def spot_error(self) -> dict:
        """{set: {"before": per-laser stats, "after": ...}} against the measured spots (mm)."""
        return {name: {"before": laser_stats(s.distances("nominal")), "after": laser_stats(s.distances("calibrated"))}
                for name, s in self.sets.items()}

    @cached_property
    def repeatability(self) -> dict:
        """ISO 9283 AP / RP (mm) of each laser's spot over the poses visited more than
        once, per set, the calibrated model's spot standing for the command."""
        out = {}
        for name, s in self.sets.items():
            by_laser = {f"laser{j + 1}": iso9283(s.samples.pose, s.samples.spots[:, j], s.calibrated[:, j], 1e3)
                        for j in range(s.samples.spots.shape[1])}
            if any(v is not None for v in by_laser.values()):
                out[name] = by_laser
        return out

    def to_json(self) -> dict:
        """The content of result.json."""
        est, options = self.estimate, self.options
        units = display_units(self.robot.param_kinds())
        errors = []
        for i, name in enumerate(est.names):
            entry = {"name": name, "value": finite_or_none(est.errors[i]), "std": finite_or_none(est.std[i]),
                     "identifiable": bool(est.identifiable[i]), "unit": "m" if units[i] == 1e3 else "rad"}
            if name in est.identifiability.merged:
                entry["note"] = est.identifiability.merged[name]
            errors.append(entry)
        ident = est.identifiability
        options_dict = {k: v for k, v in asdict(options).items() if k not in ("lm", "ekf")}
        solver = asdict(options.ekf if options.method == "ekf" else options.lm)
        solver.pop("progress", None)
        options_dict[options.method] = solver
        return {
            "robot": self.robot.name,
            "software": f"laser_calib {__version__}",
            "method": options.method,
            "options": options_dict,
            "errors": errors,
            "identifiability": {"rank": ident.rank, "parameters": len(ident.names),
                                "condition_number": finite_or_none(ident.condition),
                                "unseen_combinations": list(ident.null_combinations), "merged": ident.merged},
            "spot_sigma_m": est.sigma,
            "spot_sigma_estimated": est.sigma_estimated,
            "chi2": est.fit.chi2,
            "dof": est.fit.dof,
            "spot_error": self.spot_error,
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
        }

    def summary(self) -> str:
        """One line: the spot error before and after, as the nodes log it."""
        before, after = self.spot_error["calibration"]["before"]["all"], self.spot_error["calibration"]["after"]["all"]

        def mm(value):
            return "n/a" if value is None else f"{value:.3f}"

        return (f"{self.options.method} on {len(self.samples)} poses: mean spot error {mm(before['mean_mm'])} mm -> "
                f"{mm(after['mean_mm'])} mm (max {mm(before['max_mm'])} -> {mm(after['max_mm'])}; {after['n']} spots)"
                + ("; " + "; ".join(self.estimate.warnings) if self.estimate.warnings else ""))


def evaluate(robot: Robot, samples: Samples, est: Estimate, test: Samples | None = None) -> dict[str, SetEvaluation]:
    """Predict every set once with the nominal and the calibrated model (on the
    calibration set the estimate's own predictions at its start and its result)."""
    values = est.values[:robot.n_params]
    nominal = np.zeros_like(values)
    out = {"calibration": SetEvaluation(samples, _or_predicted(est.predicted_at_start, robot, samples, nominal),
                                        _or_predicted(est.fit.predicted, robot, samples, values))}
    if test is not None:
        out["test"] = SetEvaluation(test, predicted_spots(robot, test, nominal), predicted_spots(robot, test, values))
    return out


def _or_predicted(known: np.ndarray | None, robot: Robot, samples: Samples, errors: np.ndarray) -> np.ndarray:
    return known if known is not None else predicted_spots(robot, samples, errors)


def predicted_spots(robot: Robot, samples: Samples, errors: np.ndarray) -> np.ndarray:
    """(P,2,2) the spots the model with errors (n,) predicts at the readings of
    samples (kinematics.predict's, through the spot model block by block of poses)."""
    return residuals_at(SpotModel(robot, samples), errors).predicted


def calibrate(robot: Robot, samples: Samples, options: EstimateOptions, test: Samples | None = None,
              sources: dict | None = None) -> Calibration:
    """Estimate the errors from samples and evaluate the result (no files written)."""
    est = estimate(robot, samples, options)
    return Calibration(robot, options, est, evaluate(robot, samples, est, test), dict(sources or {}))
