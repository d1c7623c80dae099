"""laser-calib plan: D-optimal calibration poses for a robot file (planning.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from laser_calib.cli.arguments import (non_negative, non_negative_int, out_file, positive_int, print_warnings,
                                      sigma_angle, spot_sigma)
from laser_calib.estimation.redundancy import NO_VARIANCE_DOF, NOISE_RATIO, sigma_upper
from laser_calib.io.errors import InputError
from laser_calib.model.robot_file import load_robot
from laser_calib.planning import NotPlannable, PlanOptions, plan
from laser_calib.report.progress import Progress
from laser_calib.session.poses import format_poses


def _same_file(a: str, b: str) -> bool:
    try:
        return Path(a).samefile(b)
    except OSError:  # either does not exist (yet)
        return False


def cmd_plan(args: argparse.Namespace) -> int:
    robot = load_robot(args.robot)
    if _same_file(args.out, args.robot):  # the pose list would replace the robot file it was planned for
        raise InputError(args.out, "is the --robot file: the pose list would replace it; give --out another name")
    options = PlanOptions(n=args.n, spot_sigma=args.spot_sigma, joint_sigma=args.joint_sigma,
                          candidates=args.candidates, margin=args.margin, seed=args.seed)
    with Progress("plan", unit="pose") as progress:
        try:
            result = plan(robot, options, progress)
        except NotPlannable as exc:  # the planner knows why, the command the file
            raise InputError(args.robot, str(exc)) from None
    try:
        Path(args.out).write_text(format_poses(result.q))
    except OSError as exc:  # --out was checked at the start: the disk filled or the folder went meanwhile
        raise InputError(args.out, f"cannot write ({exc.strerror or exc})") from None
    identifiable = int(result.free.sum())
    print(f"wrote {args.out}: {args.n} poses of {robot.name} (D-optimal, log det {result.log_det:.2f} over "
          f"{identifiable} identifiable errors; these poses determine {result.determined} of them)")
    spare = 4 * args.n - result.determined   # the residual values an estimate with the noise unknown rests on
    if result.determined == identifiable and sigma_upper(max(spare, 1)) > NOISE_RATIO:
        print_warnings([f"{args.n} poses give {4 * args.n} values for {identifiable} errors: an estimate that "
                        f"takes the noise from the residual rests on {spare} spare values, and its noise (so every "
                        f"standard deviation) may be {sigma_upper(max(spare, 1)):.2g} times larger (95 %)"
                        + ("; from 1 or 2 spare values it is no calibration" if spare <= NO_VARIANCE_DOF else "")
                        + f"; plan at least {-(-(identifiable + 8) // 4)} poses, or give the noise"])
    if result.determined < identifiable:
        remedy = (f"plan more poses (more than {identifiable // 4}: fewer give no more values than errors)"
                  if 4 * args.n <= identifiable else "plan more poses, or wider joint ranges if a joint barely moves")
        print_warnings([f"{args.n} poses give {4 * args.n} values and determine {result.determined} of the "
                        f"{identifiable} errors at the noise given (estimate's rule): a calibration from them would "
                        f"hold the others at nominal; {remedy}"])
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add plan to cli.py's subcommands."""
    p = sub.add_parser("plan", help="D-optimal calibration poses (spot and joint noise)")
    p.add_argument("--robot", required=True)
    p.add_argument("--n", type=int, required=True, help="number of poses (the planner checks it)")
    p.add_argument("--out", required=True, type=out_file, help="CSV pose,q1..qN (rad)")
    p.add_argument("--spot-sigma", type=spot_sigma, default=PlanOptions(1).spot_sigma,
                   help="spot noise std per coordinate, m (default: the paper's +-2 mm uniform)")
    p.add_argument("--joint-sigma", type=sigma_angle, default=PlanOptions(1).joint_sigma,
                   help="joint disturbance std, rad (default: the paper's +-0.1 deg uniform)")
    p.add_argument("--candidates", type=positive_int, default=PlanOptions(1).candidates,
                   help="random poses to choose from (at least --n)")
    p.add_argument("--margin", type=non_negative, default=PlanOptions(1).margin,
                   help="keep both nominal spots this far inside the screen edge, m")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.set_defaults(func=cmd_plan)
