"""Cost against the number of poses: estimate (LM, EKF), identify, diagnose, plan.

Data: the paper's 7-DOF arm with its true errors (+10 mm / +1 deg), N poses
uniform over the whole workspace with both beams on the screen, the paper's
noise (spot +-2 mm, joints +-0.1 deg, uniform), written as the CSV a user
would have. Each command runs as its own process, as a user runs it (default
options: spot sigma estimated from the residual), under /usr/bin/time -v,
which gives the wall time, the CPU time and the peak resident memory. The
growth exponent is the slope of log(CPU time) against log(N) over the three
largest N (below them the interpreter's start and the imports dominate).

Also, in this process: our LM against scipy.optimize.least_squares ('trf' and
'lm') given our analytic whitened Jacobian, on the same cost (joint sigma 0,
so the weights do not depend on x and both minimise one function), at 60 and
200,000 poses; planning 1,000 poses from 100,000 candidates (a process); the
online EKF's time per pose at 33 errors.

Usage: python bench/scale.py [--sizes 60 600 6000 60000 200000] [--timeout 300] [--data DIR]
                             [--commands diagnose ...]
With --commands, only those rows are rerun (and their own extras: diagnose the
10,000-pose row, plan the 1,000 of 100,000, estimate (LM) the scipy comparison
and the online EKF); the other rows are kept from bench/results/scale.json, and
the table says which run each row is from.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import CORE, RESULTS, ROOT, write_results  # first: sets up the import path and BLAS threads

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

from laser_calib.estimation.lm import levenberg_marquardt  # noqa: E402
from laser_calib.estimation.online import OnlineEkf  # noqa: E402
from laser_calib.estimation.problem import Problem  # noqa: E402
from laser_calib.io.samples import Samples, load_samples, save_samples  # noqa: E402
from laser_calib.measurement.base import NoiseModel, whiten  # noqa: E402
from laser_calib.measurement.spot import SpotModel  # noqa: E402
from laser_calib.model.robot_file import save_robot  # noqa: E402
from laser_calib.sim.simulation import NoiseSpec, bundled_robot, measure, sample_poses, true_errors  # noqa: E402

SIZES = (60, 600, 6000, 60000, 200000)
COMMANDS = ("estimate (LM)", "estimate (EKF)", "identify", "diagnose", "plan")
KEYS = dict(zip(("lm", "ekf", "identify", "diagnose", "plan"), COMMANDS))  # --commands names
PLAN_POSES = 30       # the plan row: 30 poses (the paper's count) from a pool of N candidates
BLOCK = 10000         # poses simulated at a time (bounded memory while writing the data)


def simulate(n: int, folder: Path) -> Path:
    """robot.yaml (nominal) and samples.csv of n poses in folder; returns folder."""
    samples_file = folder / "samples.csv"
    if samples_file.exists():
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    nominal = bundled_robot("paper-7dof")
    true = nominal.with_errors(true_errors(nominal))
    rng = np.random.default_rng(n)
    parts = []
    for start in range(0, n, BLOCK):
        count = min(BLOCK, n - start)
        q = sample_poses([nominal, true], count, rng, "whole")
        parts.append(measure(true, q, rng, NoiseSpec(), stamps=(start + np.arange(count)) * 5.0,
                             first_pose=start)[0])
    samples = Samples(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("pose", "stamp", "q", "spots")))
    save_robot(nominal, folder / "robot.yaml", header="The paper's 7-DOF arm, nominal.")
    partial = folder / "samples.csv.part"  # renamed when complete: an interrupted run leaves no short file
    save_samples(samples, partial)
    partial.rename(samples_file)
    return folder


def timed(argv: list[str], timeout: float) -> dict:
    """Wall time (s), peak resident memory (MB) and exit status of one process."""
    command = ["/usr/bin/time", "-v", sys.executable, "-m", "laser_calib.cli"] + argv
    start = time.perf_counter()
    # its own process group, so that a time-out ends the command and not only /usr/bin/time
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                               env=os.environ | {"PYTHONPATH": str(CORE)}, start_new_session=True)
    try:
        _, stderr = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.communicate()
        return {"wall_s": None, "cpu_s": None, "peak_mb": None, "status": f"killed at {timeout:.0f} s"}
    wall = time.perf_counter() - start

    def figure(label: str) -> float:
        return float(re.search(label + r": ([\d.]+)", stderr).group(1))

    status = "ok" if process.returncode == 0 else f"exit {process.returncode}: {stderr.strip().splitlines()[-1]}"
    return {"wall_s": wall, "cpu_s": figure(r"User time \(seconds\)") + figure(r"System time \(seconds\)"),
            "peak_mb": figure(r"Maximum resident set size \(kbytes\)") / 1024, "status": status}


def command_line(name: str, folder: Path, out: Path) -> list[str]:
    robot, samples = str(folder / "robot.yaml"), str(folder / "samples.csv")
    if name == "estimate (LM)":
        return ["estimate", "--robot", robot, "--samples", samples, "--out", str(out / "lm")]
    if name == "estimate (EKF)":
        return ["estimate", "--robot", robot, "--samples", samples, "--method", "ekf", "--out", str(out / "ekf")]
    if name == "identify":
        return ["identify", "--robot", robot, "--samples", samples]
    if name == "diagnose":
        return ["diagnose", "--robot", robot, "--samples", samples, "--out", str(out / "diagnose")]
    n = sum(1 for _ in open(samples)) - 1
    return ["plan", "--robot", robot, "--n", str(PLAN_POSES), "--candidates", str(max(n, PLAN_POSES)),
            "--out", str(out / "plan.csv")]


def exponent(sizes: list[int], times: list[float | None]) -> float | None:
    points = [(n, t) for n, t in zip(sizes, times) if t is not None][-3:]
    if len(points) < 2:
        return None
    return float(np.polyfit(np.log([n for n, _ in points]), np.log([t for _, t in points]), 1)[0])


def against_scipy(folder: Path) -> dict:
    """Our LM and least_squares ('trf', 'lm') with our Jacobian on one cost: CPU seconds, costs."""
    robot = bundled_robot("paper-7dof")
    samples = load_samples(folder / "samples.csv", robot)
    noise = NoiseModel(NoiseSpec().spot_sigma, 0.0)
    problem = Problem(SpotModel(robot, samples), noise, np.ones(robot.n_params, bool))
    x0 = np.zeros(robot.n_params)
    start = time.process_time()
    ours = levenberg_marquardt(problem, x0)
    row = {"poses": len(samples), "ours_s": time.process_time() - start, "ours_cost": ours.cost}
    whitener = noise.whitener(problem.residuals(x0, False))  # constant: joint sigma 0

    def residual(x):
        return -whiten(problem.residuals(x, False), whitener)[0]

    def jacobian(x):
        return whiten(problem.residuals(x, True), whitener)[1]

    for method in ("trf", "lm"):
        start = time.process_time()
        fit = least_squares(residual, x0, jac=jacobian, method=method, x_scale=problem.scales)
        row[f"{method}_s"] = time.process_time() - start
        row[f"{method}_cost"] = float(fit.cost)
        row[f"{method}_nfev"] = int(fit.nfev)
    return row


def online_time(folder: Path, count: int = 2000) -> dict:
    """Wall and CPU time of one OnlineEkf.update, mean over ``count`` poses."""
    robot = bundled_robot("paper-7dof")
    samples = load_samples(folder / "samples.csv", robot)
    count = min(count, len(samples))
    ekf = OnlineEkf(robot)
    start, cpu = time.perf_counter(), time.process_time()
    for p in range(count):
        ekf.update(samples.q[p], samples.spots[p])
    return {"errors": robot.n_params, "poses": count, "per_pose_ms": (time.perf_counter() - start) / count * 1e3,
            "per_pose_cpu_ms": (time.process_time() - cpu) / count * 1e3}


def _cell(r: dict) -> str:
    return (f"{r['wall_s']:.1f} s / {r['cpu_s']:.1f} s / {r['peak_mb']:.0f} MB" if r["status"] == "ok"
            else r["status"])


def table(rows: dict, sizes: list[int], exponents: dict, scipy_rows: list[dict], big_plan: dict,
          diagnose_10k: dict, online: dict, runs: dict) -> str:
    lines = ["# Cost against the number of poses (paper 7-DOF, simulated)", "",
             "Each command as a user runs it (its own process, default options), one run each: wall time / "
             "CPU time (user + system) / peak resident memory, from /usr/bin/time -v. The machine is shared "
             "(2 cores, other work running), so the CPU time is the steadier figure. Exponent: slope of log "
             "CPU time against log N over the three largest N that finished (below them the interpreter's "
             "start and the imports dominate).", "",
             "| command | " + " | ".join(f"N = {n:,}" for n in sizes) + " | exponent | run |",
             "|---|" + "---|" * (len(sizes) + 2)]
    for name in COMMANDS:
        cells = [_cell(rows[name][str(n)]) if str(n) in rows[name] else "not run" for n in sizes]
        e = exponents[name]
        lines.append(f"| {name} | " + " | ".join(cells) + (f" | {e:.2f}" if e is not None else " | -")
                     + f" | {runs.get(name, '-')} |")
    lines += ["", f"plan {big_plan['n']:,} poses from {big_plan['candidates']:,} candidates: {_cell(big_plan)} "
              "(target under 60 s).", "", f"diagnose at 10,000 poses: {_cell(diagnose_10k)} (target under 60 s, 2 GB).",
              "",
              "## Our LM against scipy.optimize.least_squares with our analytic Jacobian", "",
              "Same whitened cost (spot sigma known, joint sigma 0), all 33 errors free, from nominal.", "",
              "| poses | ours (CPU s) | trf (CPU s) | lm (CPU s) | trf / ours | lm / ours | cost ours | cost trf - ours | "
              "cost lm - ours |", "|---|---|---|---|---|---|---|---|---|"]
    for r in scipy_rows:
        lines.append(f"| {r['poses']:,} | {r['ours_s']:.3f} | {r['trf_s']:.3f} | {r['lm_s']:.3f} | "
                     f"{r['trf_s'] / r['ours_s']:.1f} | {r['lm_s'] / r['ours_s']:.1f} | {r['ours_cost']:.6g} | "
                     f"{r['trf_cost'] - r['ours_cost']:+.3g} | {r['lm_cost'] - r['ours_cost']:+.3g} |")
    lines += ["", f"Online EKF ({online['errors']} errors): {online['per_pose_ms']:.3f} ms wall, "
              f"{online['per_pose_cpu_ms']:.3f} ms CPU per synchronized pose (mean over {online['poses']} poses; "
              "target under 1 ms).", ""]
    return "\n".join(lines)


def run_label() -> str:
    """When and at which commit this run is, and the machine's load then: the table's 'run' column."""
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT)
    return (f"{time.strftime('%Y-%m-%d %H:%M')} at {commit.stdout.strip() or 'unknown'}, load average "
            f"{os.getloadavg()[0]:.1f} at its start")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds before a command is killed")
    parser.add_argument("--data", type=Path, default=Path(tempfile.gettempdir()) / "laser_calib_scale",
                        help="folder of the simulated data sets (kept between runs)")
    parser.add_argument("--commands", nargs="+", choices=list(KEYS), default=list(KEYS),
                        help="rows to rerun (the others are kept from bench/results/scale.json)")
    args = parser.parse_args()
    chosen = [KEYS[key] for key in args.commands]
    kept = json.loads((RESULTS / "scale.json").read_text()) if len(chosen) < len(COMMANDS) else {}
    sizes = kept.get("sizes", args.sizes)
    rows: dict = {name: dict(kept["commands"][name]) if name not in chosen else {} for name in COMMANDS}
    runs = {name: kept.get("runs", {}).get(name, "before the run column") for name in COMMANDS if name not in chosen}
    runs |= {name: run_label() for name in chosen}
    with tempfile.TemporaryDirectory() as scratch:
        for n in args.sizes:
            folder = simulate(n, args.data / str(n))
            for name in chosen:
                rows[name][str(n)] = timed(command_line(name, folder, Path(scratch) / str(n)), args.timeout)
                print(f"N = {n}: {name}: {rows[name][str(n)]}", flush=True)
        big_plan = kept.get("plan_1000_of_100000")
        if "plan" in chosen:
            robot_file = args.data / str(args.sizes[0]) / "robot.yaml"
            big_plan = timed(["plan", "--robot", str(robot_file), "--n", "1000", "--candidates", "100000",
                              "--out", str(Path(scratch) / "plan1000.csv")], args.timeout)
            big_plan |= {"n": 1000, "candidates": 100000}
            print(f"plan 1000 of 100000: {big_plan}", flush=True)
        diagnose_10k = kept.get("diagnose_10000")
        if "diagnose" in chosen:
            diagnose_10k = timed(command_line("diagnose", simulate(10000, args.data / "10000"),
                                              Path(scratch) / "10000"), args.timeout)
            print(f"diagnose at 10000: {diagnose_10k}", flush=True)
    sizes = sorted(set(sizes) | set(args.sizes))
    exponents = {name: exponent([n for n in sizes if str(n) in rows[name]],
                                [rows[name][str(n)]["cpu_s"] for n in sizes if str(n) in rows[name]])
                 for name in COMMANDS}
    scipy_rows, online = kept.get("lm_against_scipy"), kept.get("online_ekf")
    if "estimate (LM)" in chosen:
        scipy_rows = [against_scipy(simulate(n, args.data / str(n))) for n in (min(args.sizes), max(args.sizes))]
        online = online_time(simulate(max(args.sizes), args.data / str(max(args.sizes))))
    data = {"sizes": sizes, "commands": rows, "exponents": exponents, "plan_1000_of_100000": big_plan,
            "diagnose_10000": diagnose_10k, "lm_against_scipy": scipy_rows, "online_ekf": online, "runs": runs}
    write_results("scale", data, table(rows, sizes, exponents, scipy_rows, big_plan, diagnose_10k, online, runs))


if __name__ == "__main__":
    main()
