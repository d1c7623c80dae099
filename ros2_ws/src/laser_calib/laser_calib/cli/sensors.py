"""Command line for data from other sensors:

    laser-calib import-positioner --data DIR --out DIR
    laser-calib calibrate-poses --robot R.yaml --samples S.csv --out DIR [--folds K] [--chronological F]
                                [--test T.csv] [--scale] [--diagnose]

cli.py calls register(); bad input raises InputError / ValueError, which cli.main
turns into one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace

import numpy as np

from laser_calib.cli.arguments import (SIGMA_LENGTH, add_robot_arguments, fraction, non_negative_int, out_folder,
                                      positive, print_notes, print_warnings, require_measured, sigma_length,
                                      staged_folder, tolerance_angle_deg, tolerance_length)
from laser_calib.estimation.estimate import METHODS, EstimateOptions
from laser_calib.estimation.failures import UNDETERMINED, first_failure, is_failure, undetermined_note
from laser_calib.estimation.identifiability import FIXED_NOTE, TooFewValues, carried_note
from laser_calib.model.robot import Robot
from laser_calib.io.figaroh import ROW_ORDER_AS_TIME, is_figaroh
from laser_calib.io.positioner import read_positioner
from laser_calib.io.revisits import repeat_warnings
from laser_calib.model.robot_file import held, held_warnings, load_robot_description, save_robot, with_held
from laser_calib.report.urdf_export import save_calibrated_urdf
from laser_calib.estimation.folds import chronological_labels, outside_range, range_warnings, test_outside_range
from laser_calib.estimation.sensor_fit import (SensorFit, SensorFitOptions, calibrate, is_frame_param, kfold,
                                               make_model, pose_errors, sensor_of)
from laser_calib.io.errors import InputError
from laser_calib.measurement.base import MeasurementModel
from laser_calib.report.pose_table import NOT_FITTED, fit_status, save_pose_table
from laser_calib.report.statistics import STATISTICS, iso9283, summary, worse_on_test_warning
from laser_calib.io.read import read_text
from laser_calib.io.samples import Samples
from laser_calib.io.sensor_samples import load_sensor_samples, save_sensor_samples


def cmd_import_positioner(args: argparse.Namespace) -> int:
    robot, samples = read_positioner(args.data)
    with staged_folder(args.out) as out:
        save_robot(robot, out / "robot.yaml", header=f"Two-axis positioner imported from {args.data} "
                   "(laser-calib import-positioner): nominal standard D-H and the source's frame guesses.")
        save_sensor_samples(samples, out / "samples.csv")
    print(f"wrote {args.out}/robot.yaml and samples.csv ({len(samples)} pose measurements)")
    return 0


def _unit(name: str) -> str:
    """'m', 'rad' or '1' from a parameter name (a1, alpha1, slm_rx, sensor_y, scale_z)."""
    if name.startswith("scale_"):
        return "1"
    tail = name.rsplit("_", 1)[-1] if "_" in name else name.rstrip("0123456789")
    return "rad" if tail in ("alpha", "theta", "rx", "ry", "rz") else "m"


def _parameters(fit: SensorFit, robot: Robot, fixed: list[str]) -> list[dict]:
    est = fit.estimate
    # The robot's own kinds: a joint placement's offset is m or rad by its joint type.
    units = {n: "m" if kind == "length" else "rad" for n, kind in zip(robot.param_names, robot.param_kinds())}
    carried = fit.carried
    out = []
    for i, name in enumerate(est.names):
        entry = {"name": name, "unit": units.get(name) or _unit(name),
                 "value": float(est.errors[i]) if math.isfinite(est.errors[i]) else None,
                 "std": float(est.std[i]) if math.isfinite(est.std[i]) else None}
        if name in fit.absorbed:  # held before the fit: said to be the frames' only where a frame carries it
            held = fit.absorbed[name]
            entry["note"] = ("carried by the frames: " if held.by_frames else "") + held.why
        elif not est.identifiable[i]:  # --fix's, or the data's (merged), or the robot file's (held:)
            entry["note"] = FIXED_NOTE if name in fixed else est.identifiability.merged.get(name, "held")
        elif name in fit.undetermined:  # a failed fit's: where it went is no value (errors), the file has nominal
            entry["note"] = UNDETERMINED
        elif name in carried:  # as the spot estimate's result.json says it
            entry["note"] = carried_note(name, carried[name])
        out.append(entry)
    return out


def _options(args: argparse.Namespace, robot: Robot) -> SensorFitOptions:
    # what the calibration that wrote the robot file could not determine, this one holds too, as estimate does
    estimate = EstimateOptions(method=args.method, spot_sigma=args.sigma, fixed=tuple(dict.fromkeys(
                               (*args.fix, *held(robot)))), prior=args.prior, robust=args.robust)
    return SensorFitOptions(estimate=estimate, frame_prior_length=args.frame_prior_length,
                            frame_prior_angle=None if args.frame_prior_angle_deg is None
                            else math.radians(args.frame_prior_angle_deg),
                            rotation_length=args.rotation_length, scale=args.scale)


def _evaluate(model: MeasurementModel, fit: SensorFit, prefix: str = "",
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


WORSE_THAN_DESIGN = "the calibrated model misses these poses by more than the"  # _worse's; the files say it too


def _worse(label: str, columns: dict[str, np.ndarray], prefix: str, poses: np.ndarray, design: str) -> list[str]:
    """The warning when the calibration misses poses it never saw (``label``: the held-out or test
    set) by more in position than the frames-only fit of the robot as designed (report.statistics)."""
    return worse_on_test_warning(
        columns[f"{prefix}nominal_position_m"], columns[f"{prefix}position_m"], poses,
        f"{label}: {WORSE_THAN_DESIGN} {design} with its frames fitted "
        "(RMS position {before:.3g} mm -> {after:.3g} mm over the {count} poses both predict)",
        "the calibration does not carry over to them (errors too small for these poses to determine: keep the robot "
        "as designed; a wrong minimum; joint readings out of step with the measurements; orientations in another "
        "convention; or sets measured under other conditions)")


def _summaries(columns: dict[str, np.ndarray], prefix: str = "", rows: np.ndarray | None = None) -> dict:
    """The error columns '<prefix>[nominal_]position_m' / 'rotation_rad' as summaries in mm / deg,
    over the poses ``rows`` (bool (P,); default all)."""
    out = {}
    for name in ("nominal_position", "position", "nominal_rotation", "rotation"):
        for unit, (shown, factor) in (("m", ("mm", 1e3)), ("rad", ("deg", 180 / math.pi))):
            values = columns.get(f"{prefix}{name}_{unit}")
            if values is not None:
                out[f"{name}_{shown}"] = summary(values if rows is None else values[rows], factor)
    return out


def _accuracy(samples: Samples, model: MeasurementModel, fit: SensorFit, rows: np.ndarray) -> dict | None:
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


def _design(robot: Robot) -> str:
    """What the nominal figures hold: the robot as designed."""
    return "nominal joint placements" if robot.chain is not None else "nominal D-H"


def _line(label: str, section: dict, nominal: str) -> str:
    return (f"{label} position error, mm (mean / RMS / P95 / max): {_figures(section['nominal_position_mm'])} "
            f"({nominal}) -> {_figures(section['position_mm'])}")


def _nominal_label(fit: SensorFit, robot: Robot) -> str:
    """What the in-sample nominal figure holds: the robot as designed and the frames fitted in it (if any)."""
    frames = dict.fromkeys(n.split("_", 1)[0] for n, free in zip(fit.model.names, fit.nominal.identifiable)
                           if free and is_frame_param(n))
    return f"{_design(robot)}, " + (f"frames fitted: {', '.join(frames)}" if frames else "no frame fitted")


def _split(robot: Robot, samples: Samples, options: SensorFitOptions, train: np.ndarray,
           prefix: str) -> dict[str, np.ndarray]:
    """Calibrate on the poses ``train`` (bool (P,)), predict the others: columns (P,), NaN on ``train``."""
    fit = calibrate(robot, samples.subset(train), options)
    test = np.flatnonzero(~train)
    model = make_model(robot, samples.subset(test), fit.rotation_length, options.scale)
    columns = {}
    for name, values in _evaluate(model, fit, prefix).items():
        columns[name] = np.full(len(samples), np.nan)
        columns[name][test] = values
    return columns


def _held_out_summaries(table: dict[str, np.ndarray], prefix: str) -> dict:
    """A held-out error's summaries over the poses the calibration fitted, and apart
    (``not_fitted``) over those it rejected or refused: a gross outlier's own held-out error says
    nothing of the model (one 0.2 m reading made a 5-fold mean of 12.5 mm with a P95 of 6.6)."""
    status, held = table["fit"], np.isfinite(table[f"{prefix}position_m"])
    return {**_summaries(table, prefix, status == "fitted"),
            "not_fitted": {word: _summaries(table, prefix, status == word) for word in NOT_FITTED
                           if (held & (status == word)).any()}}


def _held_out_lines(label: str, section: dict, design: str) -> list[str]:
    return [_line(label, section, design)] + [_line(f"{label}, {word} poses not fitted", apart, design)
                                              for word, apart in section["not_fitted"].items()]


def _fitted_only(table: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The table's columns with NaN on the poses the calibration did not fit (rejected, refused)."""
    kept = table["fit"] == "fitted"
    return {name: np.where(kept, values, np.nan) if name.endswith(("_m", "_rad")) else values
            for name, values in table.items()}


def _heldout(args: argparse.Namespace, robot: Robot, samples: Samples, options: SensorFitOptions,
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
        result["warnings"] += range_warnings(outside, f"{args.folds}-fold held-out", robot.joint_names) + _worse(
            f"{args.folds}-fold held-out", _fitted_only(table), "kfold_", samples.pose, _design(robot))
        lines += _held_out_lines(f"{args.folds}-fold held-out", result["heldout"], _design(robot))
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
        result["warnings"] += range_warnings(outside, "chronological test", robot.joint_names) + _worse(
            "chronological test", _fitted_only(table), "chronological_", samples.pose, _design(robot))
        lines += _held_out_lines(f"chronological held-out (first {train.sum()} poses -> last {(~train).sum()})",
                                 result["chronological"], _design(robot))


def _test(args: argparse.Namespace, robot: Robot, samples: Samples, test: Samples, fit: SensorFit,
          options: SensorFitOptions, result: dict, lines: list[str]) -> tuple:
    """--test FILE: the calibration (its fitted frames, fixed ones as given) predicts the test poses."""
    model = make_model(robot, test, fit.rotation_length, options.scale)
    columns = _evaluate(model, fit, components=True)
    outside = test_outside_range(samples.q, test.q)
    result["test"] = {"samples": str(args.test), "poses": len(test), **_summaries(columns),
                      "outside_joint_range": outside.tolist()}
    accuracy = _accuracy(test, model, fit, test.seen)
    if accuracy:
        result["test"]["iso9283"] = accuracy
    result["warnings"] += (list(test.warnings) + range_warnings(outside, f"test {args.test}", robot.joint_names)
                           + _worse(f"test {args.test}", columns, "", test.pose, _design(robot)))
    lines.append(_line(f"test ({len(test)} poses of {args.test})", result["test"], _design(robot)))
    return test.pose, test.stamp, columns


def cmd_calibrate_poses(args: argparse.Namespace) -> int:
    robot = load_robot_description(args.robot, args.base, args.tip)
    samples = load_sensor_samples(args.samples, robot)
    require_measured(samples, str(args.samples))
    test = load_sensor_samples(args.test, robot) if args.test else None
    if test is not None and test.kind != samples.kind:
        raise InputError(str(args.test), f"{test.kind} samples, but the calibration's are {samples.kind} samples")
    if test is not None:
        require_measured(test, str(args.test), f"no {test.kind} is measured in the test set")
    options = _options(args, robot)
    try:
        fit = calibrate(robot, samples, options)
    except TooFewValues as exc:  # the estimator counts the values, the command knows their file
        raise InputError(str(args.samples), str(exc)) from None
    # the in-sample figures are over the poses the fit used: the rejected ones would report what it did not do
    status = fit_status(samples.seen[:, None], fit.estimate.rejected, fit.estimate.impossible)[:, 0]
    used = status == "fitted"
    table = _evaluate(fit.model, fit, components=True) | {"fit": status}
    result = {"robot": robot.name, "samples": str(args.samples), "kind": samples.kind, "poses": len(samples),
              "rotation_length_m_per_rad": fit.rotation_length, "sigma_m": fit.estimate.sigma,
              "chi2": fit.estimate.fit.chi2, "dof": fit.estimate.fit.dof,
              "parameters": _parameters(fit, robot, args.fix), "insample": _summaries(table, rows=used),
              "insample_not_fitted": {w: _summaries(table, "", status == w) for w in NOT_FITTED if (status == w).any()},
              "rejected_poses": [int(samples.pose[p]) for p, _ in fit.estimate.rejected],
              "robust": fit.estimate.robust,
              # a warning both fits give (a still joint's: the data's, not a fit's) is said once; the
              # nominal fit is the reference, whose missing the data by centimetres is what the
              # calibration corrects, not a failed calibration (its level is the in-sample line's)
              "warnings": list(samples.warnings) + [f"nominal (frames-only) fit: {w}" for w in fit.nominal.warnings
                                                    if w not in fit.estimate.warnings and not is_failure(w)]
                          + list(fit.estimate.warnings)
                          + repeat_warnings(samples, test, robot.joint_names,
                                            {"samples": args.samples, "test": args.test})
                          + held_warnings(robot, str(args.robot))}
    # their values belong to the geometry they were fitted with, not to this calibration's
    if stale := robot.extra.get("effects"):
        result["warnings"].append(f"{args.robot}: its effects ({len(stale)}) are not fitted by calibrate-poses (the "
                                  "geometric model and the frames only): the calibrated robot is written without "
                                  "them; --diagnose selects effects anew")
    if (args.chronological or args.diagnose) and is_figaroh(read_text(args.samples)):
        result["warnings"].append(f"{args.samples}: {ROW_ORDER_AS_TIME}")
    accuracy = _accuracy(samples, fit.model, fit, used)
    if accuracy:
        result["insample"]["iso9283"] = accuracy
    fitted = [n for n, free in zip(robot.param_names, fit.estimate.identifiable) if free]
    lines = [f"{robot.name}: {len(samples)} {samples.kind} samples; "
             f"{'joint placements' if robot.chain else 'D-H errors'} fitted: {', '.join(fitted) or 'none'}",
             _line(f"in-sample ({used.sum()} poses fitted)", result["insample"], _nominal_label(fit, robot))]
    lines += [_line(f"in-sample, {word} poses not fitted ({(status == word).sum()})", section,
                    _nominal_label(fit, robot)) for word, section in result["insample_not_fitted"].items()]
    if accuracy:
        iso = accuracy["calibrated"]
        lines.append(f"ISO 9283 over {iso['poses']} repeated poses: AP mean {iso['AP']['mean']:.3f} mm "
                     f"(nominal {accuracy['nominal']['AP']['mean']:.3f}), RP mean {iso['RP']['mean']:.3f} mm")
    _heldout(args, robot, samples, options, table, result, lines)
    sets = {"calibration": (samples.pose, samples.stamp, table)}
    if test is not None:
        sets["test"] = _test(args, robot, samples, test, fit, options, result, lines)
    if args.diagnose:
        # The engine pulls in scikit-learn and scipy.stats (0.8 s): only --diagnose pays for them.
        from laser_calib.diagnosis.sensor_data import diagnosis_summary

        result["diagnosis"] = diagnosis_summary(robot, samples, options, args.folds or 5, args.seed, str(args.samples))
        chosen = result["diagnosis"]["stages"][-1]
        lines.append(f"diagnosis: {chosen['model']} (held-out mean {result['diagnosis']['heldout_nested_mean_mm']:.3f}"
                     f" mm with the selection inside the folds, {chosen['heldout_mean_mm']:.3f} mm for this model "
                     f"chosen on all poses); verdict: {result['diagnosis']['verdict']}"
                     + ("; its effects are in result.json, not in the calibrated robot file (the geometric model)"
                        if len(result["diagnosis"]["stages"]) > 1 else ""))
    failure = first_failure(fit.estimate.warnings)
    caution = next((w for w in result["warnings"] if WORSE_THAN_DESIGN in w), None)
    with staged_folder(args.out) as out:
        if robot.chain is not None:
            written = save_calibrated_urdf(fit.corrected(robot), robot, fit.determined, out, str(args.robot), failure,
                                           caution)
        else:
            corrected = with_held(fit.corrected(robot), fit.held)
            save_robot(replace(corrected, extra={k: v for k, v in corrected.extra.items() if k != "effects"}),
                       out / "robot_calibrated.yaml",
                       header=f"Calibrated from {args.samples} (laser-calib calibrate-poses)."
                              + (f"\nNO CALIBRATION: {failure}" if failure else "")
                              + (f"\nCAUTION: {caution}" if caution else "")
                              + undetermined_note(fit.undetermined)
                              + (f"\nThe geometric model only: the effects --diagnose chose "
                                 f"({result['diagnosis']['stages'][-1]['model']}) are in result.json, not here."
                                 if args.diagnose and len(result["diagnosis"]["stages"]) > 1 else ""))
            written = ("robot_calibrated.yaml",)
        (out / "result.json").write_text(json.dumps(result, indent=2))
        save_pose_table(sets, out / "residuals.csv")
    print("\n".join(lines))
    print_notes(result.get("diagnosis", {}).get("notes", []), "diagnosis note")
    status = print_warnings(result["warnings"])
    print(f"wrote {args.out}/{', '.join(written)}, result.json and residuals.csv")
    return status


def register(sub: argparse._SubParsersAction) -> None:
    """Add import-positioner and calibrate-poses to cli.py's subcommands."""
    p = sub.add_parser("import-positioner", help="import the real two-axis positioner data set")
    p.add_argument("--data", required=True, help="folder with measurements.yaml and pose_initial_guesses.yaml")
    p.add_argument("--out", required=True, type=out_folder, help="folder for robot.yaml and samples.csv")
    p.set_defaults(func=cmd_import_positioner)

    p = sub.add_parser("calibrate-poses", help="D-H errors and frames from point or pose samples")
    add_robot_arguments(p)
    p.add_argument("--samples", required=True, help="CSV pose,stamp,q1..qN,x,y,z[,qw,qx,qy,qz]")
    p.add_argument("--out", required=True, type=out_folder)
    p.add_argument("--method", choices=METHODS, default="lm")
    p.add_argument("--sigma", type=sigma_length, default=None,
                   help="noise std per position value, m (default: estimated from the residual)")
    p.add_argument("--rotation-length", type=positive, default=None,
                   help="m/rad weighing rotation residuals (default: estimated from the residuals)")
    p.add_argument("--fix", nargs="+", default=[], help="parameter names to hold (D-H, frame or scale)")
    p.add_argument("--prior", action="store_true", help="tolerance prior on the D-H errors: 10 mm and 1 deg")
    p.add_argument("--frame-prior-length", type=tolerance_length, default=None,
                   help=f"prior std of frame offsets, m ({SIGMA_LENGTH[0]:g} .. {SIGMA_LENGTH[1]:g})")
    p.add_argument("--frame-prior-angle-deg", type=tolerance_angle_deg, default=None, help="prior std of frame angles, deg")
    p.add_argument("--scale", action="store_true", help="estimate the sensor's scale per axis")
    p.add_argument("--robust", action=argparse.BooleanOptionalAction, default=True,
                   help="robust fit: outlying samples rejected and listed (default; rule in result.json)")
    p.add_argument("--folds", type=non_negative_int, default=5, help="k of the k-fold held-out error (0: none)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of the fold split")
    p.add_argument("--chronological", type=fraction, default=None, metavar="FRACTION",
                   help="also calibrate on the first FRACTION of the poses in measurement order and test on the rest")
    p.add_argument("--test", default=None, metavar="FILE",
                   help="samples CSV the calibration predicts (its frames included; nothing is refitted on them)")
    p.add_argument("--diagnose", action="store_true",
                   help="select effects and test the residual (the diagnosis engine)")
    p.set_defaults(func=cmd_calibrate_poses)
