"""Pose planning on the paper's 7-DOF arm: planned against random poses.

Per seed: the true robot (the paper's errors, +10 mm / +1 deg on every
parameter; a second run draws them uniformly within those sizes), 30
calibration poses from each design, measured with the paper's noise (spot
+-2 mm, joint disturbance +-0.1 deg, uniform), LM with the known noise model
(spot and joint sigma), and the RMS test error against the true spots (the
true robot at the joint readings, no noise) on 200 whole-workspace test poses.

Designs:
- random: the paper's poses, uniform over the whole workspace with both
  beams on the screen (simulation.sample_poses, which also checks the true
  robot);
- planned: planning.plan, D-optimal with the full per-pose noise (spot noise
  and the joint disturbance through the joint Jacobian), nominal model only;
- naive: the same D-optimal search with the joint disturbance left out of
  the weighting (spot noise only).

Usage: python bench/planning_bench.py [--seeds 20] [--poses 30]
"""

from __future__ import annotations

import argparse
import time

from _common import write_results  # first: sets up the import path and BLAS threads

import numpy as np  # noqa: E402

from laser_calib.estimation.estimate import EstimateOptions, estimate  # noqa: E402
from laser_calib.model.kinematics import predict  # noqa: E402
from laser_calib.planning import PlanOptions, plan  # noqa: E402
from laser_calib.sim.simulation import NoiseSpec, bundled_robot, measure, sample_poses, true_errors  # noqa: E402

DESIGNS = ("random", "planned", "naive")
TEST_POSES = 200


def run(seeds: int, poses: int, random_errors: bool) -> dict:
    noise = NoiseSpec()
    nominal = bundled_robot("paper-7dof")
    options = EstimateOptions(spot_sigma=noise.spot_sigma, joint_sigma=noise.joint_sigma)
    rms = {d: [] for d in DESIGNS}
    spots = {d: [] for d in DESIGNS}
    beam = {d: [] for d in DESIGNS}
    plan_time = []
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        true = nominal.with_errors(true_errors(nominal, rng if random_errors else None))
        q_test = sample_poses([nominal, true], TEST_POSES, rng, "whole")
        t0 = time.perf_counter()
        planned = plan(nominal, PlanOptions(poses, noise.spot_sigma, noise.joint_sigma, seed=seed)).q
        plan_time.append(time.perf_counter() - t0)
        designs = {"random": sample_poses([nominal, true], poses, rng, "whole"), "planned": planned,
                   "naive": plan(nominal, PlanOptions(poses, noise.spot_sigma, 0.0, seed=seed)).q}
        truth = predict(true, q_test).spots
        for name, q in designs.items():
            samples, _ = measure(true, q, rng, noise)
            est = estimate(nominal, samples, options)
            predicted = predict(nominal, q_test, est.values[:nominal.n_params]).spots
            rms[name].append(float(np.sqrt(np.mean(np.sum((truth - predicted) ** 2, axis=2)))) * 1e3)
            spots[name].append(int(samples.seen.sum()))
            beam[name].append(float(np.mean(predict(nominal, q).k)))
    medians = {d: float(np.median(rms[d])) for d in DESIGNS}
    return {"seeds": seeds, "poses": poses, "random_errors": random_errors,
            "random_rms_mm": medians["random"], "planned_rms_mm": medians["planned"],
            "naive_rms_mm": medians["naive"],
            "planned_gain": 1 - medians["planned"] / medians["random"],
            "naive_gain": 1 - medians["naive"] / medians["random"],
            "planned_better_seeds": int(np.sum(np.array(rms["planned"]) < np.array(rms["random"]))),
            "per_seed_rms_mm": rms, "spots_measured": {d: float(np.mean(v)) for d, v in spots.items()},
            "spots_possible": 2 * poses, "mean_beam_length_m": {d: float(np.mean(v)) for d, v in beam.items()},
            "plan_seconds_median": float(np.median(plan_time))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--poses", type=int, default=30)
    args = parser.parse_args()
    start = time.perf_counter()
    paper = run(args.seeds, args.poses, False)
    drawn = run(args.seeds, args.poses, True)
    data = {**{k: paper[k] for k in ("random_rms_mm", "planned_rms_mm", "naive_rms_mm", "planned_gain")},
            "paper_errors": paper, "random_errors": drawn, "wall_time_s": time.perf_counter() - start}
    rows = []
    for label, r in (("paper errors (+10 mm, +1 deg)", paper), ("errors drawn within +-10 mm, +-1 deg", drawn)):
        rows.append(f"| {label} | {r['random_rms_mm']:.3f} | {r['planned_rms_mm']:.3f} "
                    f"({100 * r['planned_gain']:.0f} % lower; better in {r['planned_better_seeds']}/{r['seeds']} "
                    f"seeds) | {r['naive_rms_mm']:.3f} ({100 * r['naive_gain']:.0f} % lower) |")
    table = "\n".join([
        "# Pose planning, 7-DOF paper arm", "",
        f"{args.poses} calibration poses, paper noise (spot +-2 mm, joints +-0.1 deg, uniform), LM with the known "
        f"noise model; median over {args.seeds} seeds of the RMS spot error against the true spots on {TEST_POSES} "
        "whole-workspace test poses (mm).", "",
        "| true errors | random (paper) | planned: D-optimal, spot + joint noise | naive: D-optimal, spot noise only |",
        "|---|---|---|---|", *rows, "",
        f"Spots measured (of {2 * args.poses}), paper errors: " + ", ".join(
            f"{d} {paper['spots_measured'][d]:.1f}" for d in DESIGNS) + ". Mean beam length (m): " + ", ".join(
            f"{d} {paper['mean_beam_length_m'][d]:.2f}" for d in DESIGNS) + ".",
        f"Planning time (3000 candidates, 30 poses): median {paper['plan_seconds_median']:.2f} s.",
        "", f"Target: planned at least 20 % below random -> {100 * paper['planned_gain']:.0f} % "
        f"({'met' if paper['planned_gain'] >= 0.2 else 'NOT met'}).", ""])
    write_results("planning", data, table)


if __name__ == "__main__":
    main()
