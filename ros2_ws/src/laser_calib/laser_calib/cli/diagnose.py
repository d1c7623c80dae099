"""laser-calib diagnose: find what the geometric model lacks, add it, report before and after.

cli.main calls register(subparsers). Bad input gives one line on stderr and
exit status 2, as for every command; a final model whose fit is no calibration
(NOT CONVERGED, NOT A CALIBRATION), an error line and exit status 3.
"""

from __future__ import annotations

import argparse

from laser_calib.cli.arguments import (fold_count, no_spot_to_fit, non_negative_int, out_folder, print_notes,
                                      print_warnings, sigma_angle, spot_sigma, staged_folder)
from laser_calib.cli.sample_sets import add_sample_arguments, read_sample_sets
from laser_calib.diagnosis.options import DiagnoseOptions
from laser_calib.estimation.estimate import METHODS
from laser_calib.io.errors import InputError
from laser_calib.model.robot_file import load_robot
from laser_calib.report.progress import Progress


def cmd_diagnose(args: argparse.Namespace) -> int:
    # The engine pulls in scikit-learn and scipy.stats (0.8 s): only this command pays for them.
    from laser_calib.diagnosis.engine import TooFewPoses, diagnose, write_outputs
    from laser_calib.estimation.failures import FitMovedBeams, NoSpotToFit
    from laser_calib.estimation.identifiability import TooFewValues

    robot = load_robot(args.robot)
    sets = read_sample_sets(args, robot)
    samples, test = sets.samples, sets.test
    # said once the first fit has begun: input refused before it (too few poses) is its error line alone
    header = f"diagnosing {robot.name} from {len(samples)} poses" + (f", testing on {len(test)}" if test else "")
    sources = {"robot": str(args.robot), "samples": sets.source, "test": sets.test_source}
    # The folder first: one that cannot be written fails before the work, and a failed run leaves none.
    with staged_folder(args.out) as out:
        # per model fitted: its fit on all poses and one per fold
        with Progress("diagnose", unit="fit", header=header) as progress:
            options = DiagnoseOptions(method=args.method, spot_sigma=args.spot_sigma, joint_sigma=args.joint_sigma,
                                      folds=args.folds, max_effects=args.max_effects, seed=args.seed,
                                      compensate=not args.no_compensator, nested=True, robust=args.robust,
                                      progress=progress)
            try:
                diagnosis = diagnose(robot, samples, test, options=options, sources=sources)
            except TooFewPoses as exc:  # the engine knows the count, the command the file
                raise InputError(sets.source, exc.problem) from None
            except TooFewValues as exc:  # a fit's counts of the values (estimate says them the same way)
                raise InputError(sets.source, str(exc)) from None
            except FitMovedBeams as exc:  # a fit knows the beams it moved, the command the robot file
                raise InputError(str(args.robot), exc.problem) from None
            except NoSpotToFit:  # every measured spot refused at the nominal model: the robot file's doing
                raise no_spot_to_fit(str(args.robot), sets.source) from None
        result = write_outputs(diagnosis, out, sources)
    for stage in result["stages"]:
        where = "test" if stage["test"] else "cv"
        s = stage[where]
        print(f"{stage['model']}: {where} spot error mean {s['mean_mm']:.3f} mm, rms {s['rms_mm']:.3f} mm, "
              f"max {s['max_mm']:.3f} mm")
    nested = result["heldout_nested"]
    print("held out with the selection inside the folds: " + (f"spot error rms {nested['rms_mm']:.3f} mm" if nested
                                                              else "not computed (the notes say why)"))
    kept = result["compensator"]
    if kept:
        test = kept["test"]
        print(f"learned compensator kept: held-out gain {100 * kept['heldout_gain']:.1f} %"
              + (f", test spot error rms {test['rms_mm']:.3f} mm" if test else ""))
    print(f"verdict: {result['verdict']}. {result['evidence']}")
    print_notes(result["notes"])
    print(f"wrote {args.out}/diagnosis.json, robot_calibrated.yaml, report.md" + (", compensator.json" if kept else ""))
    # the final model's fit: a failure (what it wrote shows where the fit went) is no calibration, exit 3
    return print_warnings(result["warnings"])


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``diagnose`` subcommand to laser-calib's parser."""
    p = subparsers.add_parser("diagnose", help="find and add the effects the geometric model lacks",
                              description=__doc__.splitlines()[0])
    p.add_argument("--robot", required=True, help="nominal robot model (YAML)")
    add_sample_arguments(p, "calibration samples (CSV, rows in measurement order)")
    p.add_argument("--spot-sigma", type=spot_sigma, default=None,
                   help="spot noise std per coordinate, m (default: estimated from the residual; the level is then tested against repeated poses, if any)")
    p.add_argument("--joint-sigma", type=sigma_angle, default=None,
                   help="joint reading noise std, rad (default: estimated from the residual)")
    p.add_argument("--method", choices=METHODS, default="lm", help="estimator of every fit")
    p.add_argument("--folds", type=fold_count, default=5, help="cross-validation folds (at least 2)")
    p.add_argument("--max-effects", type=non_negative_int, default=4, help="effects added at most")
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of the fold split")
    p.add_argument("--robust", action=argparse.BooleanOptionalAction, default=True,
                   help="leave out the measurements estimate's robust rule rejects, listed in the notes (default)")
    p.add_argument("--no-compensator", action="store_true",
                   help="do not keep the learned compensator even when it wins held-out")
    p.add_argument("--out", required=True, type=out_folder, help="output folder")
    p.set_defaults(func=cmd_diagnose)

