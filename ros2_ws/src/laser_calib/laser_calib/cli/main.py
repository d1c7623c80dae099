"""Command line: laser-calib simulate | estimate | identify | slm-calibrate | replay | diagnose |
screen-calibrate | render-calibration-images | import-positioner | calibrate-poses | plan.

Bad input gives one line on stderr naming the file, field or pose, and exit status 2;
a fit that did not converge (NOT CONVERGED) or whose minimum dropped measurements
(NOT A CALIBRATION), an error line and exit status 3 (its files are written, but
they are not a calibration); a reader that stops early (| head), no line and 141.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.estimation.estimate import METHODS, EstimateOptions
from laser_calib.estimation.failures import NoSpotToFit
from laser_calib.estimation.ekf import EkfOptions
from laser_calib.estimation.lm import LmOptions
from laser_calib.estimation.problem import whitened_factor
from laser_calib.report.progress import Progress
from laser_calib.estimation.identifiability import (AMPLIFY, CHECK_UNITS, STD_FACTOR, TooFewValues, UnknownFixed,
                                                   analyse)
from laser_calib.measurement.base import NoiseModel
from laser_calib.measurement.spot import SpotModel
from laser_calib.report.calibration import shown_mm
from laser_calib.report.files import run_estimate
from laser_calib.model.robot_file import load_robot, save_robot
from laser_calib.io.ament import installed
from laser_calib.io.bag import bag_topics
from laser_calib.io.samples import load_samples, save_samples
from laser_calib.sim.simulation import CASE_POSES, CASES, NoiseSpec, paper_session, robot_session
from laser_calib.cli import diagnose as diagnose_cli
from laser_calib.cli import plan as plan_cli
from laser_calib.cli import sensors as real_cli
from laser_calib import slm as slm_calibration
from laser_calib.cli import vision as vision_cli
from laser_calib.cli.sample_sets import add_sample_arguments, read_sample_sets
from laser_calib.cli.arguments import (MAX_SIGMA_DEG, SIGMA_LENGTH, OneLineParser, add_replay_arguments,
                                      noise_angle_deg, noise_length, non_negative_int, no_spot_to_fit, out_file,
                                      out_folder, print_warnings, readable_file, replay_argv,
                                      require_measured, sigma_angle, span_poses, spot_sigma, staged_folder,
                                      tolerance_angle_deg, tolerance_length)

EXIT_BAD_INPUT = 2
# A breakdown of our own numerics (numpy's LinAlgError, which Python counts as a ValueError): not the input's fault.
EXIT_INTERNAL_ERROR = 1
# The reader of the output went away (| head): the status a shell gives a program SIGPIPE ends (128 + 13).
EXIT_BROKEN_PIPE = 141


def cmd_simulate(args: argparse.Namespace) -> int:
    noise = NoiseSpec(spot=args.spot_noise, joint=np.deg2rad(args.joint_noise_deg))
    if args.robot:
        robot = load_robot(args.robot)
        if not robot.lasers:
            raise InputError(args.robot, "has no lasers ('slm:' and 'lasers:'): spots cannot be simulated")
        try:
            session = robot_session(robot, args.seed, args.poses_per_span or CASE_POSES["paper-7dof"], noise,
                                    random_errors=args.random_errors)
        except RuntimeError as exc:  # the paper's pose spans keep no beam on this robot's screen
            raise InputError(args.robot, f"{exc}: the screen is the plane x = 0 of the robot's frame {{0}} (its "
                                         "base), 'screen:' its half sizes; the beams must reach it") from None
    else:
        session = paper_session(args.case, args.seed, args.poses_per_span, noise, random_errors=args.random_errors)
    with staged_folder(args.out) as out:
        cases = _write_simulation(args, session, noise, out)
    print(f"wrote {args.out}/: robot_nominal.yaml, robot_true.yaml, samples.csv (all {len(session.samples)} poses), "
          f"truth.csv (their spots without noise), {', '.join(cases)}, truth.json")
    return 0


def _write_simulation(args: argparse.Namespace, session, noise: NoiseSpec, out: Path) -> list[str]:
    """The files of a simulation into out; the names of the cases' sets written, in order."""
    label = args.case or args.robot
    save_robot(session.nominal, out / "robot_nominal.yaml", header=f"Nominal model ({label}).")
    save_robot(session.true, out / "robot_true.yaml", header=f"True model of the simulation ({label}, seed {args.seed}).")
    save_samples(session.samples, out / "samples.csv")
    save_samples(session.truth, out / "truth.csv")
    cases = []
    for case, (cal, test) in session.cases.items():
        save_samples(session.samples.subset(cal), out / f"{case}_cal.csv")
        cases.append(f"{case}_cal.csv")
        if len(test):
            save_samples(session.samples.subset(test), out / f"{case}_test.csv")
            save_samples(session.truth.subset(test), out / f"{case}_test_truth.csv")
            cases += [f"{case}_test.csv", f"{case}_test_truth.csv"]
    (out / "truth.json").write_text(json.dumps({
        "case": args.case, "robot": args.robot, "seed": args.seed, "spot_noise_halfwidth_m": noise.spot,
        "joint_noise_halfwidth_rad": noise.joint, "spot_sigma_m": noise.spot_sigma,
        "joint_sigma_rad": noise.joint_sigma,
        "errors": dict(zip(session.nominal.param_names, map(float, session.errors)))}, indent=2))
    return cases


def _options(args: argparse.Namespace, progress: Progress | None = None) -> EstimateOptions:
    lm, ekf = LmOptions(progress=progress), EkfOptions(progress=progress)
    return EstimateOptions(method=args.method, spot_sigma=args.spot_sigma, joint_sigma=args.joint_sigma,
                           prior=args.prior or args.prior_length is not None or args.prior_angle_deg is not None,
                           prior_length=args.prior_length if args.prior_length is not None else 0.010,
                           prior_angle=np.deg2rad(args.prior_angle_deg if args.prior_angle_deg is not None else 1.0),
                           robust=args.robust, fixed=tuple(args.fix), lm=lm, ekf=ekf)


def cmd_estimate(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    if set(robot.param_names) <= set(args.fix):  # a fit of nothing: NOT A CALIBRATION, blaming the robot file
        raise InputError("--fix", f"holds every one of the {robot.n_params} parameters of {args.robot}: nothing "
                                  "is left to estimate")
    sets = read_sample_sets(args, robot)
    samples, test = sets.samples, sets.test
    compensator = None
    if args.compensator:
        from laser_calib.diagnosis.compensator import load_compensator  # scikit-learn: only when asked for
        compensator = load_compensator(args.compensator)
    # said once the fit has begun: input refused before it (too few values) is its error line alone
    header = (f"estimating {robot.n_params} errors of {robot.name} from {len(samples)} poses ({args.method})"
              + (f", tested on {len(test)} poses of {sets.test_source}" if test is not None else ""))
    with staged_folder(args.out) as out, Progress(args.method, unit="iteration", header=header) as progress:
        try:
            calibration = run_estimate(robot, samples, _options(args, progress), out, test,
                                       sources={"robot": str(args.robot), "samples": sets.source,
                                                "test": sets.test_source,
                                                "compensator": args.compensator},
                                       compensator=compensator)
        except TooFewValues as exc:  # the estimator counts the values, the command knows their file
            raise InputError(sets.source, str(exc)) from None
        except UnknownFixed as exc:  # the estimator knows the parameters, the command the option
            raise InputError("--fix", f"{exc.name!r} is not a parameter of {args.robot} (its parameters: "
                                      f"{', '.join(exc.names)})") from None
        except NoSpotToFit:  # every measured spot refused at the nominal model: the robot file's doing
            raise no_spot_to_fit(str(args.robot), sets.source, args.compensator) from None
    status = _summary(calibration)
    urdf = ", robot_calibrated.urdf, urdf_corrections.json" if robot.chain is not None else ""
    print(f"wrote {args.out}/robot_calibrated.yaml{urdf}, result.json, report.md, residuals.csv")
    return status


def _summary(calibration) -> int:
    """The spot errors before and after (the calibration set's over the spots fitted, those it did not fit
    on lines of their own), the warnings; the exit status (print_warnings)."""
    errors = calibration.spot_error
    lines = [("calibration", "", errors["calibration"])]
    lines += [("calibration", f" {status}, not fitted:", by_model)
              for status, by_model in calibration.spot_error_not_fitted.items()]
    lines += [(name, "", by_model) for name, by_model in errors.items() if name != "calibration"]
    if calibration.spot_error_test_outliers:
        lines.append(("test", " outliers, not counted:", calibration.spot_error_test_outliers))
    for set_name, what, by_model in lines:
        b, a = by_model["before"]["all"], by_model["after"]["all"]
        counted = " fitted" if set_name == "calibration" and not what else ""
        print(f"{set_name:12s}{what} mean spot error {shown_mm(b['mean_mm'])} mm -> {shown_mm(a['mean_mm'])} mm "
              f"(max {shown_mm(b['max_mm'])} -> {shown_mm(a['max_mm'])}; {a['n']} spots{counted})")
    return print_warnings(list(calibration.estimate.warnings))


def cmd_identify(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    samples = load_samples(args.samples, robot)
    require_measured(samples, args.samples)
    model = SpotModel(robot, samples)
    factor, n_values = whitened_factor(model, NoiseModel(args.spot_sigma, args.joint_sigma), np.zeros(robot.n_params))
    if n_values == 0:  # a table of rank 0 for what estimate refuses as no spot to fit
        raise InputError(args.robot, f"no measured spot of {args.samples} is reached: at every one the nominal "
                                     f"model's beam misses the screen; {CHECK_UNITS}")
    print(f"{robot.name}: {len(samples)} poses, {n_values // 2} spots")
    # the given noise sets the threshold: what the poses would determine worse than 10 tolerances is listed
    print(analyse(factor, model.scales, model.names, std_factor=STD_FACTOR, amplify=AMPLIFY).table())
    return 0


def cmd_slm_calibrate(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    if robot.slm is None or not robot.lasers:  # the file written would be refused by every other command
        raise InputError(args.robot, "has no laser module ('slm:' and 'lasers:'): slm-calibrate writes the "
                                     "robot file with its lasers' angles; give the robot with its SLM")
    measurements = slm_calibration.load_measurements(args.measurements)
    result = slm_calibration.calibrate(robot, measurements, args.spot_sigma, args.accept_large_change)
    for item in result.rejected:
        print(f"rejected: {args.measurements} line {item.line}: laser {item.laser}, distance {item.distance:g} m, "
              f"residual u {item.residual[0] * 1e3:+.3g} mm, v {item.residual[1] * 1e3:+.3g} mm", file=sys.stderr)
    if result.rejected:
        print(f"outliers: {result.rule}", file=sys.stderr)
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    for j, a in enumerate(result.angles):
        left_out = sum(item.laser == j + 1 for item in result.rejected)
        print(f"laser {j + 1}: gamma = {np.degrees(a.gamma):+.4f} +- {np.degrees(a.gamma_std):.4f} deg, "
              f"beta = {np.degrees(a.beta):+.4f} +- {np.degrees(a.beta_std):.4f} deg ({a.n} spots"
              f"{f', {left_out} rejected' if left_out else ''})")
    rejected_lines = ", ".join(str(item.line) for item in result.rejected)
    plural = "s" * (len(result.rejected) > 1)
    header = f"Laser angles from {args.measurements} (laser-calib slm-calibrate)" + (
        f"; its line{plural} {rejected_lines} rejected as outlier{plural}." if rejected_lines else ".")
    try:
        save_robot(result.robot, args.out, header=header)
    except OSError as exc:  # --out was checked at the start: the disk filled or the folder went meanwhile
        raise InputError(args.out, f"cannot write ({exc.strerror or exc})") from None
    print(f"wrote {args.out}")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    """Hand over to the replay node (a ROS process): the core itself never imports rclpy."""
    bag_topics(args.bag)  # opened ROS-free first: a missing or unreadable bag is said before the lack of ROS
    executable = installed("lib/laser_calib_nodes/replay")
    if executable is None or not os.access(executable, os.X_OK):
        raise InputError("replay", "needs the ROS 2 environment: run scripts/setup, then use scripts/laser-calib "
                                   "(or source scripts/env.sh)")
    os.execv(executable, [str(executable), *replay_argv(args)])


def build_parser() -> argparse.ArgumentParser:
    # the docstring's first paragraph names every command, its second the exit statuses
    summary, statuses = (" ".join(part.split()) for part in __doc__.split("\n\n")[:2])
    parser = OneLineParser(prog="laser-calib", description=summary, epilog=statuses)
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("simulate", help="simulate the paper's session (section IV / V)")
    arm = p.add_mutually_exclusive_group(required=True)
    arm.add_argument("--case", choices=CASES, help="one of the paper's arms")
    arm.add_argument("--robot", help="any robot YAML with lasers (D-H, or 'urdf:' docs/urdf.md), in the paper's "
                                     f"session ({CASE_POSES['paper-7dof']} + {CASE_POSES['paper-7dof']} poses unless "
                                     "--poses-per-span)")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--out", required=True, type=out_folder)
    p.add_argument("--poses-per-span", type=span_poses, default=None,
                   help="poses in each of the small-range and whole-workspace sets, at least 2 (paper: 30 / 25)")
    p.add_argument("--spot-noise", type=noise_length, default=0.002,
                   help=f"half-width of uniform spot noise, m (0 .. {SIGMA_LENGTH[1]:g})")
    p.add_argument("--joint-noise-deg", type=noise_angle_deg, default=0.1,
                   help=f"half-width of joint disturbance, deg (0 .. {MAX_SIGMA_DEG:.1f})")
    p.add_argument("--random-errors", action="store_true",
                   help="true errors uniform within +-10 mm / 1 deg instead of the paper's all-positive ones")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("estimate", help="estimate the geometric errors")
    p.add_argument("--robot", required=True)
    add_sample_arguments(p)
    p.add_argument("--method", choices=METHODS, default="lm")
    p.add_argument("--spot-sigma", type=spot_sigma, default=None,
                   help="spot noise std per coordinate, m (default: estimated from the residual)")
    p.add_argument("--joint-sigma", type=sigma_angle, default=None,
                   help="joint reading noise std, rad (default: estimated from the residual, with the spot sigma "
                        "or at the one given, and used where the residual shows it)")
    p.add_argument("--prior", action="store_true", help="tolerance prior: 10 mm and 1 deg per error")
    p.add_argument("--prior-length", type=tolerance_length, default=None,
                   help=f"length tolerance, m ({SIGMA_LENGTH[0]:g} .. {SIGMA_LENGTH[1]:g}; implies --prior)")
    p.add_argument("--prior-angle-deg", type=tolerance_angle_deg, default=None, help="angle tolerance, deg (implies --prior)")
    p.add_argument("--robust", action=argparse.BooleanOptionalAction, default=True,
                   help="robust fit: outlier spots rejected and listed (default; the rule is in result.json)")
    p.add_argument("--fix", nargs="+", default=[], help="error names to hold at nominal")
    p.add_argument("--compensator", type=readable_file,
                   help="a diagnosis's compensator.json, applied to every pose (made for the robot file's model: "
                        "its robot_calibrated.yaml's effects)")
    p.add_argument("--out", required=True, type=out_folder)
    p.set_defaults(func=cmd_estimate)

    p = sub.add_parser("identify", help="identifiability table of a pose set")
    p.add_argument("--robot", required=True)
    p.add_argument("--samples", required=True)
    p.add_argument("--spot-sigma", type=spot_sigma, default=0.001)
    p.add_argument("--joint-sigma", type=sigma_angle, default=0.0)
    p.set_defaults(func=cmd_identify)

    p = sub.add_parser("slm-calibrate", help="laser angles from spots at known fixture distances (eq. 16)")
    p.add_argument("--robot", required=True)
    p.add_argument("--measurements", required=True, help="CSV laser,distance,u,v (m)")
    p.add_argument("--spot-sigma", type=spot_sigma, default=None,
                   help="spot noise std per coordinate, m (default: estimated from the residual; outliers are "
                        "judged robustly)")
    p.add_argument("--accept-large-change", action="store_true",
                   help=f"write angles more than {slm_calibration.MOUNTING_BOUND_DEG:g} deg from the robot file's "
                        "(a remounted laser), which are otherwise refused as a misread file")
    p.add_argument("--out", required=True, type=out_file, help="robot file to write")
    p.set_defaults(func=cmd_slm_calibrate)

    p = sub.add_parser("replay", help="republish a recorded session bag with its original timing (ROS)")
    add_replay_arguments(p)
    p.set_defaults(func=cmd_replay)

    diagnose_cli.register(sub)
    vision_cli.register(sub)
    real_cli.register(sub)
    plan_cli.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        status = args.func(args)
        sys.stdout.flush()  # a closed pipe shows here, not at exit as a traceback
        return status
    except BrokenPipeError:
        # What the reader wanted was printed. Python flushes stdout again at exit: devnull takes that.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except InputError as exc:
        print(f"laser-calib: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except np.linalg.LinAlgError as exc:
        # it read as bad input ('laser-calib estimate: Singular matrix', exit 2), each time a fault of ours
        print(f"laser-calib {args.command}: internal error: the fit's numerics broke down ({exc}); please report it "
              "with the input files", file=sys.stderr)
        return EXIT_INTERNAL_ERROR
    except ValueError as exc:
        print(f"laser-calib {args.command}: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        return 130

