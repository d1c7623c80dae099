"""What a calibration achieved, on poses the fit never saw and, when the true robot
is known (simulation), against the truth over the whole workspace (ROS-free; the
sequencer writes it after a session's estimate, the command line could as well).

- test poses: measured spots against the nominal and the calibrated model (held-out
  spot error, the only figure a real session can give beyond the fit);
- truth (simulation): at ``n_poses`` joint poses drawn uniformly over the joint
  ranges, the end-effector (SLM origin) position of the nominal and of the
  calibrated model against the true robot's, and, at the poses of those whose beams
  hit the screen, the predicted spots against the true ones. Parameters the data
  cannot determine stay at nominal in the calibrated model, so their share of the
  error stays too: this figure shows it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from laser_calib.io.samples import Samples
from laser_calib.model.kinematics import forward, predict
from laser_calib.model.robot import Robot
from laser_calib.report.statistics import laser_stats, spot_distances, summary


def truth_errors(nominal: Robot, calibrated: Robot, true: Robot, n_poses: int = 2000, seed: int = 0) -> dict:
    """{'end_effector'|'spot': {'before': stats, 'after': stats}, 'poses': n, 'spot_poses': m}."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(*true.pose_range(), (n_poses, true.n_joints))   # (K,N)
    origin = {name: forward(robot, q).origin for name, robot in (("nominal", nominal), ("calibrated", calibrated),
                                                                 ("true", true))}
    truth_spots = predict(true, q)
    on_screen = truth_spots.hit.all(axis=1) & (np.abs(truth_spots.spots[..., 0]) <= true.screen.half_y).all(axis=1) \
        & (np.abs(truth_spots.spots[..., 1]) <= true.screen.half_z).all(axis=1)
    out = {"poses": int(n_poses), "spot_poses": int(on_screen.sum()), "end_effector": {}, "spot": {}}
    for label, name, robot in (("before", "nominal", nominal), ("after", "calibrated", calibrated)):
        out["end_effector"][label] = summary(np.linalg.norm(origin[name] - origin["true"], axis=1), 1e3, "_mm")
        spots = predict(robot, q[on_screen]).spots                       # (M,2,2)
        out["spot"][label] = summary(np.linalg.norm(spots - truth_spots.spots[on_screen], axis=2), 1e3, "_mm")
    return out


def compare(nominal: Robot, calibrated: Robot, test: Samples | None, true: Robot | None, seed: int = 0) -> dict:
    """The test-pose spot errors (when test poses were measured) and the truth errors (when known)."""
    out: dict = {}
    if test is not None and len(test):
        out["test"] = {"poses": len(test), "before": laser_stats(spot_distances(nominal, test))["all"],
                       "after": laser_stats(spot_distances(calibrated, test))["all"]}
    if true is not None:
        out["truth"] = truth_errors(nominal, calibrated, true, seed=seed)
    return out


def markdown(comparison: dict) -> list[str]:
    """Report lines (a section for report.md)."""
    def mm(stats: dict, key: str) -> str:
        return "n/a" if stats[key] is None else f"{stats[key]:.3f}"

    lines = ["", "## Held-out poses and the truth", ""]
    if "test" in comparison:
        t = comparison["test"]
        lines += [f"Test poses (measured, never fitted): {t['poses']} poses, spot error mean "
                  f"{mm(t['before'], 'mean_mm')} mm -> {mm(t['after'], 'mean_mm')} mm, max "
                  f"{mm(t['before'], 'max_mm')} -> {mm(t['after'], 'max_mm')} mm.", ""]
    if "truth" in comparison:
        t = comparison["truth"]
        lines += [f"Against the true robot over the whole workspace ({t['poses']} random poses; spots at the "
                  f"{t['spot_poses']} whose beams hit the screen):", "",
                  "| error | model | mean mm | rms mm | max mm |", "|---|---|---|---|---|"]
        for what, label in (("end_effector", "end-effector position"), ("spot", "spot")):
            for when, model in (("before", "nominal"), ("after", "calibrated")):
                s = t[what][when]
                lines.append(f"| {label} | {model} | {mm(s, 'mean_mm')} | {mm(s, 'rms_mm')} | {mm(s, 'max_mm')} |")
    if len(lines) == 3:
        return []
    return lines + [""]


def append_to_report(report: Path, comparison: dict) -> None:
    lines = markdown(comparison)
    if lines:
        with open(report, "a") as handle:
            handle.write("\n".join(lines))
