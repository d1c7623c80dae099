"""Command line for data from other sensors and for pose planning:

    laser-calib import-positioner --data DIR --out DIR
    laser-calib calibrate-poses --robot R.yaml --samples S.csv --out DIR [--folds K] [--scale] [--diagnose]
    laser-calib plan --robot R.yaml --n N --out poses.csv

cli.py calls register(); bad input raises InputError / ValueError, which cli.main
turns into one line on stderr and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from laser_calib.cli.arguments import add_robot_arguments, positive
from laser_calib.estimation.estimate import METHODS, EstimateOptions
from laser_calib.model.robot import Robot
from laser_calib.io.positioner import read_positioner
from laser_calib.planning import PlanOptions, plan
from laser_calib.session.poses import format_poses
from laser_calib.model.robot_file import load_robot, save_robot
from laser_calib.model.urdf import load_robot_description
from laser_calib.report.urdf_export import save_calibrated_urdf
from laser_calib.diagnosis.sensor_data import diagnose, diagnose_options, heldout_effects
from laser_calib.estimation.sensor_fit import SensorFit, SensorFitOptions, calibrate, kfold, pose_errors
from laser_calib.io.sensor_samples import SensorSamples, load_sensor_samples, save_sensor_samples


def cmd_import_positioner(args: argparse.Namespace) -> int:
    robot, samples = read_positioner(args.data)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_robot(robot, out / "robot.yaml", header=f"Two-axis positioner imported from {args.data} "
               "(laser-calib import-positioner): nominal standard D-H and the source's frame guesses.")
    save_sensor_samples(samples, out / "samples.csv")
    print(f"wrote {out}/robot.yaml and samples.csv ({len(samples)} pose measurements)")
    return 0


def _stats(values: np.ndarray, factor: float) -> dict:
    seen = values[np.isfinite(values)] * factor
    return {"n": int(seen.size), "mean": float(seen.mean()), "std": float(seen.std(ddof=1)),
            "max": float(seen.max())}


def _unit(name: str) -> str:
    """'m', 'rad' or '1' from a parameter name (a1, alpha1, slm_rx, sensor_y, scale_z)."""
    if name.startswith("scale_"):
        return "1"
    tail = name.rsplit("_", 1)[-1] if "_" in name else name.rstrip("0123456789")
    return "rad" if tail in ("alpha", "theta", "rx", "ry", "rz") else "m"


def _parameters(fit: SensorFit, robot: Robot) -> list[dict]:
    est = fit.estimate
    # The robot's own kinds: a joint placement's offset is m or rad by its joint type.
    units = {n: "m" if kind == "length" else "rad" for n, kind in zip(robot.param_names, robot.param_kinds())}
    out = []
    for i, name in enumerate(est.names):
        entry = {"name": name, "unit": units.get(name) or _unit(name),
                 "value": float(est.errors[i]) if math.isfinite(est.errors[i]) else None,
                 "std": float(est.std[i]) if math.isfinite(est.std[i]) else None}
        if name in fit.absorbed:
            entry["note"] = "carried by the frames: " + fit.absorbed[name]
        elif not est.identifiable[i]:
            entry["note"] = est.identifiability.merged.get(name, "held")
        out.append(entry)
    return out


def _options(args: argparse.Namespace) -> SensorFitOptions:
    estimate = EstimateOptions(method=args.method, spot_sigma=args.sigma, fixed=tuple(args.fix),
                               prior=args.prior, robust=args.robust)
    return SensorFitOptions(estimate=estimate, frame_prior_length=args.frame_prior_length,
                            frame_prior_angle=None if args.frame_prior_angle_deg is None
                            else math.radians(args.frame_prior_angle_deg),
                            rotation_length=args.rotation_length, scale=args.scale)


def _diagnosis(robot: Robot, samples: SensorSamples, options: SensorFitOptions, folds: int, seed: int) -> dict:
    """The diagnosis engine on the samples (sensors.analysis.diagnose): its
    selection rounds, verdict and evidence, and per stage the k-fold held-out
    and in-sample mean position error (mm) of the calibration with its effects."""
    diagnosis = diagnose(robot, samples, options, diagnose_options(options, folds, seed))
    full = diagnosis.to_json()
    stages = []
    for stage in diagnosis.stages:
        held = heldout_effects(robot, samples, options, stage.fitted.effects, folds, seed)
        stages.append({"model": stage.label, "heldout_mean_mm": float(np.nanmean(held.position)) * 1e3,
                       "bic": stage.fitted.bic})
    return {"stages": stages, "selection": full["selection"], "effects": full["effects"],
            "verdict": diagnosis.verdict, "evidence": diagnosis.evidence, "noise": full["noise"],
            "notes": full["notes"]}


def cmd_calibrate_poses(args: argparse.Namespace) -> int:
    robot = load_robot_description(args.robot, args.base, args.tip)
    samples = load_sensor_samples(args.samples, robot)
    options = _options(args)
    fit = calibrate(robot, samples, options)
    after_p, after_r = pose_errors(fit.model, fit.estimate.values)
    before_p, before_r = pose_errors(fit.model, fit.nominal.values)
    result = {"robot": robot.name, "samples": str(args.samples), "kind": samples.kind, "poses": len(samples),
              "rotation_length_m_per_rad": fit.rotation_length, "sigma_m": fit.estimate.sigma,
              "chi2": fit.estimate.fit.chi2, "dof": fit.estimate.fit.dof,
              "parameters": _parameters(fit, robot),
              "insample": {"nominal_position_mm": _stats(before_p, 1e3), "position_mm": _stats(after_p, 1e3)},
              "warnings": list(fit.nominal.warnings + fit.estimate.warnings)}
    if samples.kind == "pose":
        result["insample"]["nominal_rotation_deg"] = _stats(before_r, 180 / math.pi)
        result["insample"]["rotation_deg"] = _stats(after_r, 180 / math.pi)
    fitted = [n for n, free in zip(robot.param_names, fit.estimate.identifiable) if free]
    lines = [f"{robot.name}: {len(samples)} {samples.kind} samples; "
             f"{'joint placements' if robot.chain else 'D-H errors'} fitted: {', '.join(fitted) or 'none'}",
             f"in-sample mean position error {result['insample']['nominal_position_mm']['mean']:.3f} mm "
             f"(nominal D-H, frames fitted) -> {result['insample']['position_mm']['mean']:.3f} mm"]
    if args.folds:
        held = kfold(robot, samples, options, args.folds, args.seed)
        result["heldout"] = {"folds": args.folds, "seed": args.seed,
                             "nominal_position_mm": _stats(held.nominal_position, 1e3),
                             "position_mm": _stats(held.position, 1e3)}
        lines.append(f"{args.folds}-fold held-out mean position error "
                     f"{result['heldout']['nominal_position_mm']['mean']:.3f} mm (nominal) -> "
                     f"{result['heldout']['position_mm']['mean']:.3f} mm")
    if args.diagnose:
        result["diagnosis"] = _diagnosis(robot, samples, options, args.folds or 5, args.seed)
        chosen = result["diagnosis"]["stages"][-1]
        lines.append(f"diagnosis: {chosen['model']} (held-out mean {chosen['heldout_mean_mm']:.3f} mm); "
                     f"verdict: {result['diagnosis']['verdict']}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if robot.chain is not None:
        written = save_calibrated_urdf(fit.corrected(robot), robot, fit.estimate.identifiable, out, str(args.robot))
    else:
        save_robot(fit.corrected(robot), out / "robot_calibrated.yaml",
                   header=f"Calibrated from {args.samples} (laser-calib calibrate-poses).")
        written = ("robot_calibrated.yaml",)
    (out / "result.json").write_text(json.dumps(result, indent=2))
    print("\n".join(lines + [f"wrote {out}/{', '.join(written)} and result.json"]))
    return 0


def cmd_plan(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    options = PlanOptions(n=args.n, spot_sigma=args.spot_sigma, joint_sigma=args.joint_sigma,
                          candidates=args.candidates, margin=args.margin, seed=args.seed)
    result = plan(robot, options)
    Path(args.out).write_text(format_poses(result.q))
    print(f"wrote {args.out}: {args.n} poses of {robot.name} (D-optimal, log det {result.log_det:.2f} over "
          f"{int(result.free.sum())} identifiable errors)")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add import-positioner, calibrate-poses and plan to cli.py's subcommands."""
    p = sub.add_parser("import-positioner", help="import the real two-axis positioner data set")
    p.add_argument("--data", required=True, help="folder with measurements.yaml and pose_initial_guesses.yaml")
    p.add_argument("--out", required=True, help="folder for robot.yaml and samples.csv")
    p.set_defaults(func=cmd_import_positioner)

    p = sub.add_parser("calibrate-poses", help="D-H errors and frames from point or pose samples")
    add_robot_arguments(p)
    p.add_argument("--samples", required=True, help="CSV pose,stamp,q1..qN,x,y,z[,qw,qx,qy,qz]")
    p.add_argument("--out", required=True)
    p.add_argument("--method", choices=METHODS, default="lm")
    p.add_argument("--sigma", type=positive, default=None,
                   help="noise std per position value, m (default: estimated from the residual)")
    p.add_argument("--rotation-length", type=positive, default=None,
                   help="m/rad weighing rotation residuals (default: estimated from the residuals)")
    p.add_argument("--fix", nargs="*", default=[], help="parameter names to hold (D-H, frame or scale)")
    p.add_argument("--prior", action="store_true", help="tolerance prior on the D-H errors: 10 mm and 1 deg")
    p.add_argument("--frame-prior-length", type=positive, default=None, help="prior std of frame offsets, m")
    p.add_argument("--frame-prior-angle-deg", type=positive, default=None, help="prior std of frame angles, deg")
    p.add_argument("--scale", action="store_true", help="estimate the sensor's scale per axis")
    p.add_argument("--robust", action="store_true", help="reject outlying samples and refit")
    p.add_argument("--folds", type=int, default=5, help="k of the k-fold held-out error (0: none)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fold split")
    p.add_argument("--diagnose", action="store_true",
                   help="select effects and test the residual (the diagnosis engine)")
    p.set_defaults(func=cmd_calibrate_poses)

    p = sub.add_parser("plan", help="D-optimal calibration poses (spot and joint noise)")
    p.add_argument("--robot", required=True)
    p.add_argument("--n", type=int, required=True, help="number of poses")
    p.add_argument("--out", required=True, help="CSV pose,q1..qN (rad)")
    p.add_argument("--spot-sigma", type=positive, default=PlanOptions(1).spot_sigma,
                   help="spot noise std per coordinate, m (default: the paper's +-2 mm uniform)")
    p.add_argument("--joint-sigma", type=float, default=PlanOptions(1).joint_sigma,
                   help="joint disturbance std, rad (default: the paper's +-0.1 deg uniform)")
    p.add_argument("--candidates", type=int, default=PlanOptions(1).candidates,
                   help="random poses to choose from (at least --n)")
    p.add_argument("--margin", type=float, default=PlanOptions(1).margin,
                   help="keep both nominal spots this far inside the screen edge, m")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_plan)
