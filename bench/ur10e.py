"""Real data: a UR10e measured by motion capture (23 6-DOF poses), calibrated
straight from its own URDF (data/real/ur10e_mocap, README.md there).

1. `laser-calib calibrate-poses --robot ur10_robot.urdf --base base_link --tip
   wrist_3_link --samples calibration.csv`: the source's CSV as it is (FIGAROH's
   format: poses as x, y, z and roll-pitch-yaw, joints named as in the URDF;
   io/figaroh.py), the joint-placement model (7 values per joint), the unknown
   measurement frame (sensor) and the measured frame on wrist_3_link (target)
   estimated together; it writes robot_calibrated.urdf.
2. Leave-one-out held-out position and rotation errors (23 folds: each pose
   predicted by the calibration on the other 22), nominal (frames fitted, the
   URDF as designed) and calibrated: mean, RMS and max.

Usage: python bench/ur10e.py
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

from _common import ROOT, write_results  # first: sets up the import path and BLAS threads

import numpy as np  # noqa: E402

from laser_calib.cli.main import main  # noqa: E402
from laser_calib.estimation.sensor_fit import SensorFitOptions, kfold  # noqa: E402
from laser_calib.io.sensor_samples import load_sensor_samples  # noqa: E402
from laser_calib.model.urdf import load_urdf_robot  # noqa: E402

DATA = ROOT / "data" / "real" / "ur10e_mocap"
URDF, BASE, TIP = DATA / "ur10_robot.urdf", "base_link", "wrist_3_link"


def stats(values: np.ndarray, factor: float) -> dict:
    v = values[np.isfinite(values)] * factor
    return {"mean": float(v.mean()), "rms": float(np.sqrt(np.mean(v ** 2))), "max": float(v.max())}


def run() -> dict:
    robot = load_urdf_robot(URDF, BASE, TIP)
    samples_path = DATA / "calibration.csv"
    samples = load_sensor_samples(samples_path, robot)
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        code = main(["calibrate-poses", "--robot", str(URDF), "--base", BASE, "--tip", TIP,
                     "--samples", str(samples_path), "--out", out, "--folds", "0"])
        cli_s = time.perf_counter() - start
        written = sorted(p.name for p in Path(out).iterdir())
    start = time.perf_counter()
    held = kfold(robot, samples, SensorFitOptions(), k=len(samples), seed=0)
    loo_s = time.perf_counter() - start
    deg = 180 / math.pi
    return {
        "robot": robot.name, "poses": len(samples), "parameters": robot.n_params,
        "cli_exit": code, "cli_files": written, "cli_s": cli_s, "leave_one_out_s": loo_s,
        "nominal_heldout_mean_mm": stats(held.nominal_position, 1e3)["mean"],
        "calibrated_heldout_mean_mm": stats(held.position, 1e3)["mean"],
        "nominal_heldout_mm": stats(held.nominal_position, 1e3),
        "calibrated_heldout_mm": stats(held.position, 1e3),
        "nominal_heldout_deg": stats(held.nominal_rotation, deg),
        "calibrated_heldout_deg": stats(held.rotation, deg),
    }


def table(r: dict) -> str:
    lines = ["# UR10e, motion capture (23 real poses), calibrated from its URDF", "",
             f"`laser-calib calibrate-poses --robot data/real/ur10e_mocap/ur10_robot.urdf --base {BASE} "
             f"--tip {TIP} --samples data/real/ur10e_mocap/calibration.csv` (FIGAROH's file as it is): exit {r['cli_exit']}, wrote {', '.join(r['cli_files'])} in {r['cli_s']:.1f} s "
             f"({r['parameters']} joint-placement parameters, sensor and target frames).", "",
             "Leave-one-out held-out errors (each pose predicted by the calibration on the other 22):", "",
             "| model | position mean (mm) | RMS (mm) | max (mm) | rotation mean (deg) | RMS (deg) | max (deg) |",
             "|---|---|---|---|---|---|---|"]
    for key, label in (("nominal", "nominal URDF, frames fitted"), ("calibrated", "calibrated")):
        p, a = r[f"{key}_heldout_mm"], r[f"{key}_heldout_deg"]
        lines.append(f"| {label} | {p['mean']:.3f} | {p['rms']:.3f} | {p['max']:.3f} | "
                     f"{a['mean']:.3f} | {a['rms']:.3f} | {a['max']:.3f} |")
    lines += ["", f"Leave-one-out: {r['leave_one_out_s']:.1f} s."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    # no options; --help says what it does instead of running it (and rewriting bench/results/ur10e.*)
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    result = run()
    write_results("ur10e", result, table(result))
