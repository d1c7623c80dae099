"""One geometric calibration, end to end: estimate, evaluate, write the outputs.

The command line, the ROS estimator service and the sequencer's end of session
all call run_estimate, so their files are the same.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path

import numpy as np

from laser_calib import __version__
from laser_calib.estimation.estimate import Estimate, EstimateOptions, estimate
from laser_calib.report.statistics import laser_stats, spot_distances
from laser_calib.model.robot import Robot
from laser_calib.report.plots import display_units, plot_convergence, plot_histogram, plot_screen, stats_table
from laser_calib.model.robot_file import save_robot
from laser_calib.io.samples import Samples


def _finite_or_none(value: float):
    return float(value) if math.isfinite(value) else None


def spot_error_table(robot: Robot, values: np.ndarray, sets: dict[str, Samples]) -> dict:
    """{set: {"before": per-laser stats, "after": ...}} against the measured spots."""
    return {name: {"before": laser_stats(spot_distances(robot, s)),
                   "after": laser_stats(spot_distances(robot, s, values[:robot.n_params]))}
            for name, s in sets.items()}


def result_dict(robot: Robot, est: Estimate, options: EstimateOptions, spot_error: dict, samples: Samples) -> dict:
    units = display_units(robot.n_joints)
    errors = []
    for i, name in enumerate(est.names):
        entry = {"name": name, "value": _finite_or_none(est.errors[i]), "std": _finite_or_none(est.std[i]),
                 "identifiable": bool(est.identifiable[i]),
                 "unit": "m" if units[i] == 1e3 else "rad"}
        if name in est.identifiability.merged:
            entry["note"] = est.identifiability.merged[name]
        errors.append(entry)
    ident = est.identifiability
    options_dict = {k: v for k, v in asdict(options).items() if k not in ("lm", "ekf")}
    solver = asdict(options.ekf if options.method == "ekf" else options.lm)
    solver.pop("progress", None)
    options_dict[options.method] = solver
    return {
        "robot": robot.name,
        "software": f"laser_calib {__version__}",
        "method": options.method,
        "options": options_dict,
        "errors": errors,
        "identifiability": {"rank": ident.rank, "parameters": len(ident.names),
                            "condition_number": _finite_or_none(ident.condition),
                            "unseen_combinations": list(ident.null_combinations), "merged": ident.merged},
        "spot_sigma_m": est.sigma,
        "spot_sigma_estimated": est.sigma_estimated,
        "chi2": est.fit.chi2,
        "dof": est.fit.dof,
        "spot_error": spot_error,
        "iterations": est.fit.iterations,
        "converged": bool(est.fit.converged),
        "restarts": est.restarts,
        "wall_time_s": est.wall_time,
        "rejected_spots": [{"pose": int(samples.pose[p]), "laser": j + 1} for p, j in est.rejected],
        "warnings": list(est.warnings),
    }


def run_estimate(robot: Robot, samples: Samples, options: EstimateOptions, out_dir: str | Path,
                 test: Samples | None = None, truth: np.ndarray | None = None,
                 sources: dict[str, str] | None = None) -> dict:
    """Estimate, then write robot_calibrated.yaml, result.json and report.md (+ PNGs)
    into out_dir. ``truth`` (n,) true errors, when known (simulation), is drawn
    in the convergence plot. Returns the result dictionary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    est = estimate(robot, samples, options)
    sets = {"calibration": samples} | ({"test": test} if test is not None else {})
    spot_error = spot_error_table(robot, est.values, sets)
    result = result_dict(robot, est, options, spot_error, samples)
    result["inputs"] = sources or {}
    calibrated = est.corrected(robot)
    merged = "; ".join(f"{k}: {v}" for k, v in est.identifiability.merged.items())
    save_robot(calibrated, out / "robot_calibrated.yaml",
               header=f"Calibrated by laser_calib {__version__} ({options.method}) from {len(samples)} poses."
                      + (f"\nNot identifiable, held at nominal: {merged}" if merged else ""))
    (out / "result.json").write_text(json.dumps(result, indent=2))
    write_report(robot, samples, test, est, result, out, truth)
    return result


def write_report(robot: Robot, samples: Samples, test: Samples | None, est: Estimate, result: dict,
                 out: Path, truth: np.ndarray | None) -> None:
    plot_convergence(est.fit.history, est.names, robot.n_joints, out / "convergence.png", truth)
    plot_screen(robot, samples, est.values, out / "screen.png")
    groups = {"calibration, nominal": spot_distances(robot, samples),
              "calibration, calibrated": spot_distances(robot, samples, est.values)}
    if test is not None:
        groups["test, nominal"] = spot_distances(robot, test)
        groups["test, calibrated"] = spot_distances(robot, test, est.values)
    plot_histogram(groups, out / "histogram.png")

    units = display_units(robot.n_joints)
    lines = [f"# Kinematic calibration of {robot.name}", "",
             f"Method: **{result['method']}**, {len(samples)} calibration poses"
             + (f", {len(test)} test poses" if test is not None else "") + ". "
             f"Spot sigma {est.sigma * 1e3:.3g} mm ({'estimated from the residual' if est.sigma_estimated else 'given'}); "
             f"{est.fit.iterations} iterations ({'converged' if est.fit.converged else 'NOT converged'}), "
             f"{est.wall_time * 1e3:.0f} ms; chi^2/dof = {est.fit.chi2 / est.fit.dof:.3f}.", ""]
    if est.warnings:
        lines += ["**Warnings**", ""] + [f"- {w}" for w in est.warnings] + [""]
    lines += ["## Spot error (distance between measured and predicted spot)", ""] + stats_table(result["spot_error"])
    ident = est.identifiability
    lines += ["", "## Identifiability", "",
              f"Rank {ident.rank} of {len(ident.names)}, scaled condition number {ident.condition:.3g}."]
    if ident.merged:
        lines += ["", "Combinations the spots cannot see (coefficients per 10 mm / 1 deg):", ""]
        lines += [f"- {c}" for c in ident.null_combinations]
        lines += ["", "Held at nominal, reported without a value:", ""]
        lines += [f"- {k}: {v}" for k, v in ident.merged.items()]
    lines += ["", "## Estimated errors", "", "| # | error | value | std | unit |", "|---|---|---|---|---|"]
    for i, name in enumerate(est.names):
        unit = "mm" if units[i] == 1e3 else "deg"
        if est.identifiable[i]:
            lines.append(f"| {i + 1} | {name} | {est.errors[i] * units[i]:+.4f} | {est.std[i] * units[i]:.4f} | {unit} |")
        else:
            lines.append(f"| {i + 1} | {name} | not identifiable | - | {unit} |")
    if est.rejected:
        lines += ["", "Rejected spots (robust rule): "
                  + ", ".join(f"pose {samples.pose[p]} laser {j + 1}" for p, j in est.rejected)]
    lines += ["", "## Plots", "", "Convergence of every error (as the paper's Fig. 4"
              + (", dotted: true values" if truth is not None else "") + "):", "",
              "![convergence](convergence.png)", "", "Spots on the screen:", "", "![screen](screen.png)", "",
              "Spot distances:", "", "![histogram](histogram.png)", ""]
    (out / "report.md").write_text("\n".join(lines))
