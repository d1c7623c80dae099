"""The files of one geometric calibration: robot_calibrated.yaml, result.json,
report.md and its plots, all written from the one result object
(report.calibration.Calibration).

The command line, the ROS estimator service and the sequencer's end of session
all go through calibrate() and these writers, so their files are the same.
"""

from __future__ import annotations

import json
import multiprocessing
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from laser_calib import __version__
from laser_calib.estimation.estimate import EstimateOptions, spot_sigma_at_zero
from laser_calib.estimation.failures import undetermined_note
from laser_calib.estimation.identifiability import carried_note
from laser_calib.io.samples import Samples
from laser_calib.model.fit_marks import fit_marks
from laser_calib.model.robot import Robot
from laser_calib.model.robot_file import dump_robot
from laser_calib.report.calibration import MODELS, Calibration, calibrate
from laser_calib.report.pose_table import save_pose_table, spot_columns, spot_status
from laser_calib.report.urdf_export import save_calibrated_urdf
from laser_calib.report.plots import plot_convergence, plot_histogram, plot_screen, stats_table

if TYPE_CHECKING:  # scikit-learn (1 s to import): only where a compensator is loaded
    from laser_calib.diagnosis.compensator import Compensator


def run_estimate(robot: Robot, samples: Samples, options: EstimateOptions, out_dir: str | Path,
                 test: Samples | None = None, truth: np.ndarray | None = None,
                 sources: dict[str, str] | None = None, compensator: Compensator | None = None) -> Calibration:
    """calibrate(), then write_outputs() into out_dir: what `laser-calib estimate` does."""
    calibration = calibrate(robot, samples, options, test, sources, compensator)
    write_outputs(calibration, out_dir, truth, draw_apart=True)
    return calibration


def calibrated_robot_yaml(calibration: Calibration) -> str:
    """robot_calibrated.yaml: the nominal model with the identifiable errors applied."""
    est = calibration.estimate
    merged = "; ".join(f"{k}: {v}" for k, v in est.identifiability.merged.items())
    kept = calibration.compensator is not None
    return dump_robot(calibration.calibrated,
                      header=f"Calibrated by laser_calib {__version__} ({calibration.options.method}) from "
                             f"{len(calibration.samples)} poses"
                             + (f" with the effects {', '.join(e.label for e in calibration.effects)}"
                                if calibration.effects else "") + "."
                             + "".join(f"\n{line}" for line in fit_marks(calibration.failure, calibration.caution))
                             + (f"\nNot identifiable, held at nominal: {merged}" if merged else "")
                             + undetermined_note(est.undetermined)
                             + ("\nFitted with the learned compensator "
                                f"{calibration.sources.get('compensator', '')} (not in this file): predict with it "
                                "(diagnosis.compensator.load_compensator)" if kept else ""))


def result_json(calibration: Calibration) -> str:
    return json.dumps(calibration.to_json(), indent=2)


def write_outputs(calibration: Calibration, out_dir: str | Path, truth: np.ndarray | None = None,
                  draw_apart: bool = False) -> None:
    """robot_calibrated.yaml (and, for a URDF robot, robot_calibrated.urdf and
    urdf_corrections.json), result.json, residuals.csv, report.md and the plots
    into out_dir. ``truth`` (n,) true errors, when known (simulation), is drawn in
    the convergence plot. draw_apart: the plots are drawn by a forked child
    process while this one writes the tables (a command-line process: a second
    core takes the second or two of matplotlib off the wall time; a process with
    threads of its own, such as a ROS node, must not fork)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    drawing = None
    if draw_apart and "fork" in multiprocessing.get_all_start_methods():
        drawing = multiprocessing.get_context("fork").Process(target=_draw_quietly, args=(calibration, out, truth))
        drawing.start()
    try:
        _write_tables(calibration, out)
    except BaseException:  # Ctrl-C or a failure: no child left drawing into a folder being given up
        if drawing is not None:
            drawing.kill()
            drawing.join()
        raise
    if drawing is not None:
        drawing.join()
    if drawing is None or drawing.exitcode != 0:  # drawn here: a failure is this process's, reported as such
        write_plots(calibration, out, truth)
    (out / "report.md").write_text(report_markdown(calibration, truth is not None))


def _write_tables(calibration: Calibration, out: Path) -> None:
    """The calibrated robot (YAML, and URDF for a URDF robot), result.json and residuals.csv."""
    (out / "robot_calibrated.yaml").write_text(calibrated_robot_yaml(calibration))
    if calibration.robot.chain is not None:  # the URDF to apply (docs/urdf.md)
        save_calibrated_urdf(calibration.calibrated, calibration.robot, calibration.estimate.determined, out,
                             str(calibration.sources.get("robot", "")), calibration.failure, calibration.caution)
    (out / "result.json").write_text(result_json(calibration))
    save_pose_table({name: (s.samples.pose, s.samples.stamp, spot_columns(s.samples, s.calibrated, s.nominal)
                            | (spot_status(s.status) if s.status is not None else {}))
                     for name, s in calibration.sets.items()}, out / "residuals.csv")


def _draw_quietly(calibration: Calibration, out: Path, truth: np.ndarray | None) -> None:
    """write_plots in the child: a failure is only its exit status (the parent draws again and reports it)."""
    try:
        write_plots(calibration, out, truth)
    except BaseException:  # noqa: BLE001 - including Ctrl-C: the parent has it too
        raise SystemExit(1) from None


def write_plots(calibration: Calibration, out: Path, truth: np.ndarray | None) -> None:
    est, robot = calibration.estimate, calibration.robot
    n = robot.n_params  # the geometric errors (the effects' parameters are in the report's table)
    plot_convergence(est.fit.history[:, :n], est.names[:n], robot.param_kinds(), out / "convergence.png",
                     None if truth is None else truth[:n])
    calibration_set = calibration.sets["calibration"]
    plot_screen(robot.screen, calibration_set.samples.spots, calibration_set.nominal, calibration_set.calibrated,
                out / "screen.png")
    groups = {f"{name}, {model}": s.distances(model, s.counted) for name, s in calibration.sets.items()
              for model in MODELS}
    plot_histogram(groups, out / "histogram.png")


def spot_sigma_phrase(est) -> str:
    """The spot sigma as the report states it; an estimated spot component at 0 beside joint-reading
    noise is below what the data resolve (spot_sigma_at_zero)."""
    if spot_sigma_at_zero(est.sigma, est.sigma_estimated) and est.joint_sigma:
        return "Spot sigma below what the data resolve beside the joint-reading noise (estimated 0 mm)"
    return f"Spot sigma {est.sigma * 1e3:.3g} mm ({'estimated from the residual' if est.sigma_estimated else 'given'})"


def report_markdown(calibration: Calibration, truth_drawn: bool = False) -> str:
    """report.md; its plots are the PNGs write_plots puts beside it."""
    est, robot, samples = calibration.estimate, calibration.robot, calibration.samples
    test = calibration.sets["test"].samples if "test" in calibration.sets else None
    units = calibration.units()
    lines = [f"# Kinematic calibration of {robot.name}", "",
             f"Method: **{calibration.options.method}**, {len(samples)} calibration poses"
             + (f", {len(test)} test poses" if test is not None else "") + ". "
             + spot_sigma_phrase(est) + ", "
             f"joint-reading sigma {np.degrees(est.joint_sigma):.3g} deg ("
             f"{'estimated with it' if est.joint_sigma_estimated else 'given' if est.joint_sigma else 'none used'}); "
             f"{est.fit.iterations} iterations ({'converged' if est.fit.converged else 'NOT converged'}), "
             f"{est.wall_time * 1e3:.0f} ms; chi^2/dof = {est.fit.chi2 / est.fit.dof:.3f}.", ""]
    if est.warnings:
        lines += ["**Warnings**", ""] + [f"- {w}" for w in est.warnings] + [""]
    lines += ["## Spot error (distance between measured and predicted spot)", ""] + stats_table(calibration.spot_error)
    not_fitted = calibration.spot_error_not_fitted
    if not_fitted:  # measured, so reported; apart, as they are not what the calibration achieved
        lines += ["", f"The calibration set's figures are over the spots fitted; those not fitted "
                  f"({calibration.not_fitted_count().removeprefix(', ')}; residuals.csv l1_fit, l2_fit):", ""]
        lines += stats_table({f"calibration, {status}": by_model for status, by_model in not_fitted.items()})
    outliers = calibration.spot_error_test_outliers
    if outliers:  # measured, so reported; apart, as one wrong test spot outweighs every other
        lines += ["", "The test set's figures are over its spots within the outlier limit of the calibrated model; "
                  "those beyond it (residuals.csv l1_fit, l2_fit: outlier):", ""]
        lines += stats_table({"test, outlier": outliers})
    repeated = calibration.repeatability
    if repeated:
        lines += ["", "ISO 9283 on the spots of poses visited more than once (mm; AP: barycentre to the calibrated "
                  "model's spot, RP: repeatability):", "", "| set | laser | poses | AP mean | AP max | RP mean | RP max |",
                  "|---|---|---|---|---|---|---|"]
        lines += [f"| {name} | {laser[-1]} | {f['poses']} | {f['AP']['mean']:.3f} | {f['AP']['max']:.3f} | "
                  f"{f['RP']['mean']:.3f} | {f['RP']['max']:.3f} |"
                  for name, by_laser in repeated.items() for laser, f in by_laser.items() if f is not None]
    ident = est.identifiability
    lines += ["", "## Identifiability", "",
              f"Rank {ident.rank} of {len(ident.names)}, scaled condition number {ident.condition:.3g}."]
    if ident.merged:
        lines += ["", "Combinations the spots cannot determine, at the calibrated values (coefficients per 10 mm / "
                  "1 deg; result.json's identifiability.shares: each kept value's share of each held error, in full):",
                  ""]
        lines += [f"- {c}" for c in ident.null_combinations]
        lines += ["", "Held at nominal, reported without a value:", ""]
        lines += [f"- {k}: {v}" for k, v in ident.merged.items()]
    if ident.carried:
        lines += ["", "Kept, each value a combination (marked * below):", ""]
        lines += [f"- {k}: {carried_note(k, v)}" for k, v in ident.carried.items()]
    lines += ["", "## Estimated errors", "", "| # | error | value | std | unit |", "|---|---|---|---|---|"]
    for i, name in enumerate(est.names):
        factor, unit = units[i]
        digits = ".4f" if unit in ("mm", "deg") else ".4g"  # an effect's parameter in its own unit
        if est.determined[i]:
            mark = " *" if name in ident.carried else ""
            lines.append(f"| {i + 1} | {name}{mark} | {est.errors[i] * factor:+{digits}} | "
                         f"{est.std[i] * factor:{digits}} | {unit} |")
        elif est.identifiable[i]:  # a failed fit's, beyond the data at its values: written at nominal
            lines.append(f"| {i + 1} | {name} | not determined | {est.std[i] * factor:{digits}} | {unit} |")
        else:
            lines.append(f"| {i + 1} | {name} | not identifiable | - | {unit} |")
    if calibration.effects or calibration.compensator is not None:
        lines += ["", "Effects of the robot file, estimated with the geometric errors: "
                  + (", ".join(e.label for e in calibration.effects) or "none") + "."]
    if calibration.compensator is not None:
        lines += ["", f"Learned compensator applied to every pose ({calibration.sources.get('compensator', '')}; "
                  f"its diagnosis's held-out gain {100 * calibration.compensator.heldout_gain:.1f} %): a regression, "
                  "not a physical effect."]
    if est.rejected:
        lines += ["", "Rejected spots (robust rule): "
                  + ", ".join(f"pose {samples.pose[p]} laser {j + 1}" for p, j in est.rejected)]
    lines += ["", "## Plots", "", "Convergence of every error (as the paper's Fig. 4"
              + (", dotted: true values" if truth_drawn else "") + "):", "",
              "![convergence](convergence.png)", "", "Spots on the screen:", "", "![screen](screen.png)", "",
              "Spot distances:", "", "![histogram](histogram.png)", ""]
    return "\n".join(lines)
