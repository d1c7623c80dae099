"""The figures calibrate-poses reports, in mm and deg, each with its nominal counterpart (the
robot as designed, its frames fitted): in-sample, k-fold and chronological held-out, and on a
test file; their console lines and their warnings (a calibration worse than the design on poses
it never saw, held-out poses beyond the joint ranges calibrated, test poses missed grossly)."""

from __future__ import annotations

import argparse
import math

import numpy as np

from laser_calib.estimation.folds import chronological_labels, outside_range, range_warnings, test_outside_range
from laser_calib.estimation.identifiability import TooFewValues
from laser_calib.estimation.sensor_fit import (SensorFit, SensorFitOptions, calibrate, is_frame_param, kfold,
                                               make_model, pose_errors, sensor_of)
from laser_calib.io.errors import InputError
from laser_calib.io.samples import Samples
from laser_calib.measurement.base import MeasurementModel
from laser_calib.model.robot import Robot
from laser_calib.report.pose_table import NOT_FITTED
from laser_calib.report.statistics import STATISTICS, iso9283, summary, worse_on_test_warning
from laser_calib.report.test_outliers import test_outlier_warnings, test_status


def error_columns(model: MeasurementModel, fit: SensorFit, prefix: str = "",
              components: bool = False) -> dict[str, np.ndarray]:
    """Per-pose columns (P,) of the residual table for ``model``'s poses: the
    position error (m) and, for pose samples, the rotation error (rad) of the
    nominal D-H (with the fit's frames) and of the calibration; with
    ``components`` first the calibration's measured - predicted position
    dx, dy, dz in the sensor frame (m)."""
    samples = sensor_of(model).samples
    out = {}
    if components:
        predicted = model.residuals(fit.estimate.values, False).predicted[:, 0, :3]
        out.update(zip(("dx_m", "dy_m", "dz_m"), (samples.position - predicted).T))
    for name, values in (("nominal_", fit.nominal.values), ("", fit.estimate.values)):
        position, rotation = pose_errors(model, values)
        out[f"{prefix}{name}position_m"] = position
        if samples.kind == "pose":
            out[f"{prefix}{name}rotation_rad"] = rotation
    return out


WORSE_THAN_DESIGN = "the calibrated model misses these poses by more than the"  # worse_warnings'; the files say it too


def worse_warnings(label: str, columns: dict[str, np.ndarray], prefix: str, poses: np.ndarray, design: str) -> list[str]:
    """The warning when the calibration misses poses it never saw (``label``: the held-out or test
    set) by more in position than the frames-only fit of the robot as designed (report.statistics)."""
    return worse_on_test_warning(
        columns[f"{prefix}nominal_position_m"], columns[f"{prefix}position_m"], poses,
        f"{label}: {WORSE_THAN_DESIGN} {design} with its frames fitted "
        "(RMS position {before:.3g} mm -> {after:.3g} mm over the {count} poses both predict)",
        "the calibration does not carry over to them (errors too small for these poses to determine: keep the robot "
        "as designed; a wrong minimum; joint readings out of step with the measurements; orientations in another "
        "convention; or sets measured under other conditions)")


def summaries(columns: dict[str, np.ndarray], prefix: str = "", rows: np.ndarray | None = None) -> dict:
    """The error columns '<prefix>[nominal_]position_m' / 'rotation_rad' as summaries in mm / deg,
    over the poses ``rows`` (bool (P,); default all)."""
    out = {}
    for name in ("nominal_position", "position", "nominal_rotation", "rotation"):
        for unit, (shown, factor) in (("m", ("mm", 1e3)), ("rad", ("deg", 180 / math.pi))):
            values = columns.get(f"{prefix}{name}_{unit}")
            if values is not None:
                out[f"{name}_{shown}"] = summary(values if rows is None else values[rows], factor)
    return out


def repeat_accuracy(samples: Samples, model: MeasurementModel, fit: SensorFit, rows: np.ndarray) -> dict | None:
    """ISO 9283 AP / RP (mm, and deg for pose samples) of the poses visited more
    than once among ``rows`` (bool (P,)), nominal and calibrated; None without repeats."""
    out = {}
    position = np.where(rows[:, None], samples.position, np.nan)  # iso9283 leaves out a NaN row
    for name, x in (("nominal", fit.nominal.values), ("calibrated", fit.estimate.values)):
        res = model.residuals(x, False)
        rotation = None
        if samples.kind == "pose":
            rotation = np.where(res.valid, res.r[:, 0, 3:], np.nan) / sensor_of(model).rotation_length
        out[name] = iso9283(samples.pose, position, res.predicted[:, 0, :3], 1e3, rotation, 180 / math.pi)
    return out if out["nominal"] else None


def _figures(stats: dict) -> str:
    return " / ".join("-" if stats[k] is None else f"{stats[k]:.3f}" for k in STATISTICS if k != "std")


def design_label(robot: Robot) -> str:
    """What the nominal figures hold: the robot as designed."""
    return "nominal joint placements" if robot.chain is not None else "nominal D-H"


def figure_line(label: str, section: dict, nominal: str) -> str:
    return (f"{label} position error, mm (mean / RMS / P95 / max): {_figures(section['nominal_position_mm'])} "
            f"({nominal}) -> {_figures(section['position_mm'])}")


def nominal_label(fit: SensorFit, robot: Robot) -> str:
    """What the in-sample nominal figure holds: the robot as designed and the frames fitted in it (if any)."""
    frames = dict.fromkeys(n.split("_", 1)[0] for n, free in zip(fit.model.names, fit.nominal.identifiable)
                           if free and is_frame_param(n))
    return f"{design_label(robot)}, " + (f"frames fitted: {', '.join(frames)}" if frames else "no frame fitted")


def _split(robot: Robot, samples: Samples, options: SensorFitOptions, train: np.ndarray,
           prefix: str) -> dict[str, np.ndarray]:
    """Calibrate on the poses ``train`` (bool (P,)), predict the others: columns (P,), NaN on ``train``."""
    fit = calibrate(robot, samples.subset(train), options)
    test = np.flatnonzero(~train)
    model = make_model(robot, samples.subset(test), fit.rotation_length, options.scale)
    columns = {}
    for name, values in error_columns(model, fit, prefix).items():
        columns[name] = np.full(len(samples), np.nan)
        columns[name][test] = values
    return columns


def _held_out_summaries(table: dict[str, np.ndarray], prefix: str) -> dict:
    """A held-out error's summaries over the poses the calibration fitted, and apart
    (``not_fitted``) over those it rejected or refused: a gross outlier's own held-out error says
    nothing of the model (one 0.2 m reading made a 5-fold mean of 12.5 mm with a P95 of 6.6)."""
    status, held = table["fit"], np.isfinite(table[f"{prefix}position_m"])
    return {**summaries(table, prefix, status == "fitted"),
            "not_fitted": {word: summaries(table, prefix, status == word) for word in NOT_FITTED
                           if (held & (status == word)).any()}}


def _held_out_lines(label: str, section: dict, design: str) -> list[str]:
    return [figure_line(label, section, design)] + [figure_line(f"{label}, {word} poses not fitted", apart, design)
                                              for word, apart in section["not_fitted"].items()]


def _fitted_only(table: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The table's columns with NaN on the poses the calibration did not fit (rejected, refused)."""
    kept = table["fit"] == "fitted"
    return {name: np.where(kept, values, np.nan) if name.endswith(("_m", "_rad")) else values
            for name, values in table.items()}


def heldout_figures(args: argparse.Namespace, robot: Robot, samples: Samples, options: SensorFitOptions,
             table: dict, result: dict, lines: list[str]) -> None:
    """k-fold and chronological held-out errors into the result, the table and the console."""
    if args.folds:
        try:
            held = kfold(robot, samples, options, args.folds, args.seed)
        except TooFewValues as exc:  # a training part's counts: said as a part of the file given
            raise InputError(str(args.samples), f"{len(samples)} poses, too few for the {args.folds}-fold held-out "
                                                f"error: a training part holds {exc.n_values} measured values for "
                                                f"{exc.n_free} parameters; measure more poses, or give more --folds "
                                                "(each leaves out fewer) or --folds 0 (none)") from None
        table.update({"fold": held.fold, "kfold_nominal_position_m": held.nominal_position,
                      "kfold_position_m": held.position})
        if samples.kind == "pose":
            table.update({"kfold_nominal_rotation_rad": held.nominal_rotation, "kfold_rotation_rad": held.rotation})
        outside = outside_range(samples.q, held.fold, range(args.folds))
        result["heldout"] = {"folds": args.folds, "seed": args.seed, **_held_out_summaries(table, "kfold_"),
                             "outside_joint_range": outside.tolist()}
        result["warnings"] += range_warnings(outside, f"{args.folds}-fold held-out", robot.joint_names) + worse_warnings(
            f"{args.folds}-fold held-out", _fitted_only(table), "kfold_", samples.pose, design_label(robot))
        lines += _held_out_lines(f"{args.folds}-fold held-out", result["heldout"], design_label(robot))
    if args.chronological:
        train = chronological_labels(len(samples), args.chronological) == 0
        try:
            table.update(_split(robot, samples, options, train, "chronological_"))
        except TooFewValues as exc:
            raise InputError(str(args.samples), f"--chronological {args.chronological}: the first {train.sum()} of "
                                                f"the {len(samples)} poses hold {exc.n_values} measured values for "
                                                f"{exc.n_free} parameters; give a larger fraction or measure more "
                                                "poses") from None
        outside = outside_range(samples.q, (~train).astype(int), (1,))
        result["chronological"] = {"calibration_fraction": args.chronological,
                                   "calibration_poses": int(train.sum()), "test_poses": int((~train).sum()),
                                   **_held_out_summaries(table, "chronological_"),
                                   "outside_joint_range": outside.tolist()}
        result["warnings"] += range_warnings(outside, "chronological test", robot.joint_names) + worse_warnings(
            "chronological test", _fitted_only(table), "chronological_", samples.pose, design_label(robot))
        lines += _held_out_lines(f"chronological held-out (first {train.sum()} poses -> last {(~train).sum()})",
                                 result["chronological"], design_label(robot))


def test_figures(args: argparse.Namespace, robot: Robot, samples: Samples, test: Samples, fit: SensorFit,
          options: SensorFitOptions, result: dict, lines: list[str]) -> tuple:
    """--test FILE: the calibration (its fitted frames, fixed ones as given) predicts the test poses."""
    model = make_model(robot, test, fit.rotation_length, options.scale)
    columns = error_columns(model, fit, components=True)
    # a test pose the calibration misses grossly (a wrong reading) is listed and reported apart
    columns["fit"] = test_status(model, test.seen[:, None], fit.estimate, 6 if test.kind == "pose" else 3)[:, 0]
    counted, outlier = np.isin(columns["fit"], ("tested", "beyond")), columns["fit"] == "outlier"
    outside = test_outside_range(samples.q, test.q)
    result["test"] = {"samples": str(args.test), "poses": len(test), **summaries(columns, rows=counted),
                      "outliers": summaries(columns, rows=outlier) if outlier.any() else None,
                      "outside_joint_range": outside.tolist()}
    accuracy = repeat_accuracy(test, model, fit, counted)
    if accuracy:
        result["test"]["iso9283"] = accuracy
    result["warnings"] += (list(test.warnings) + range_warnings(outside, f"test {args.test}", robot.joint_names)
                           + test_outlier_warnings(columns["fit"][:, None], test, "residuals.csv fit")
                           + worse_warnings(f"test {args.test}", {k: np.where(counted, v, np.nan) for k, v in columns.items()
                                                          if k.endswith(("_m", "_rad"))}, "", test.pose, design_label(robot)))
    lines.append(figure_line(f"test ({counted.sum()} poses of {args.test})", result["test"], design_label(robot)))
    if outlier.any():
        lines.append(figure_line(f"test, {outlier.sum()} outlier poses not counted", result["test"]["outliers"],
                           design_label(robot)))
    return test.pose, test.stamp, columns
