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

from laser_calib.cli.pose_figures import (WORSE_THAN_DESIGN, error_columns, figure_line, heldout_figures,
                                         nominal_label, repeat_accuracy, summaries, test_figures)
from laser_calib.cli.arguments import (SIGMA_LENGTH, add_robot_arguments, fraction, non_negative_int, out_folder,
                                      positive, print_notes, print_warnings, require_measured, sigma_length,
                                      staged_folder, tolerance_angle_deg, tolerance_length)
from laser_calib.estimation.estimate import METHODS, EstimateOptions
from laser_calib.estimation.failures import UNDETERMINED, first_failure, is_failure, undetermined_note
from laser_calib.estimation.identifiability import FIXED_NOTE, TooFewValues, carried_note, weak_and_large
from laser_calib.model.fit_marks import fit_marks
from laser_calib.model.robot import Robot
from laser_calib.io.figaroh import ROW_ORDER_AS_TIME, is_figaroh
from laser_calib.io.positioner import read_positioner
from laser_calib.io.revisits import repeat_warnings
from laser_calib.model.robot_file import held, held_warnings, load_robot_description, save_robot, with_held
from laser_calib.report.urdf_export import save_calibrated_urdf
from laser_calib.estimation.sensor_fit import SensorFit, SensorFitOptions, calibrate
from laser_calib.io.errors import InputError
from laser_calib.report.pose_table import NOT_FITTED, fit_status, save_pose_table
from laser_calib.io.read import read_text
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
    table = error_columns(fit.model, fit, components=True) | {"fit": status}
    result = {"robot": robot.name, "samples": str(args.samples), "kind": samples.kind, "poses": len(samples),
              "rotation_length_m_per_rad": fit.rotation_length, "sigma_m": fit.estimate.sigma,
              "chi2": fit.estimate.fit.chi2, "dof": fit.estimate.fit.dof,
              "parameters": _parameters(fit, robot, args.fix), "insample": summaries(table, rows=used),
              "insample_not_fitted": {w: summaries(table, "", status == w) for w in NOT_FITTED if (status == w).any()},
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
    accuracy = repeat_accuracy(samples, fit.model, fit, used)
    if accuracy:
        result["insample"]["iso9283"] = accuracy
    fitted = [n for n, free in zip(robot.param_names, fit.estimate.identifiable) if free]
    lines = [f"{robot.name}: {len(samples)} {samples.kind} samples; "
             f"{'joint placements' if robot.chain else 'D-H errors'} fitted: {', '.join(fitted) or 'none'}",
             figure_line(f"in-sample ({used.sum()} poses fitted)", result["insample"], nominal_label(fit, robot))]
    lines += [figure_line(f"in-sample, {word} poses not fitted ({(status == word).sum()})", section,
                    nominal_label(fit, robot)) for word, section in result["insample_not_fitted"].items()]
    if accuracy:
        iso = accuracy["calibrated"]
        lines.append(f"ISO 9283 over {iso['poses']} repeated poses: AP mean {iso['AP']['mean']:.3f} mm "
                     f"(nominal {accuracy['nominal']['AP']['mean']:.3f}), RP mean {iso['RP']['mean']:.3f} mm")
    heldout_figures(args, robot, samples, options, table, result, lines)
    sets = {"calibration": (samples.pose, samples.stamp, table)}
    if test is not None:
        sets["test"] = test_figures(args, robot, samples, test, fit, options, result, lines)
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
    caution = next((w for w in result["warnings"] if WORSE_THAN_DESIGN in w), weak_and_large(fit.estimate.warnings))
    # at the top, as estimate's result.json: a failed fit was a line among the warnings, beside its figures
    result = {"failure": failure, "caution": caution, **result}
    with staged_folder(args.out) as out:
        if robot.chain is not None:
            written = save_calibrated_urdf(fit.corrected(robot), robot, fit.determined, out, str(args.robot), failure,
                                           caution)
        else:
            corrected = with_held(fit.corrected(robot), fit.held)
            save_robot(replace(corrected, extra={k: v for k, v in corrected.extra.items() if k != "effects"}),
                       out / "robot_calibrated.yaml",
                       header=f"Calibrated from {args.samples} (laser-calib calibrate-poses)."
                              + "".join(f"\n{line}" for line in fit_marks(failure, caution))
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
