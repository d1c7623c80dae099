"""Reproduce the paper's Tables II and III (7-DOF simulation) over many seeds.

For every seed: the paper's session (true errors +10 mm / +1 deg, joint
disturbance +-0.1 deg, spot noise +-2 mm, 30 small-range + 30 whole-workspace
poses), cases 1-3, LM and EKF (paper settings Q = R = 1e-4 I). Spot errors are
measured against the noisy measurements (as the paper does) and against the
noise-free true spots (the true robot at the joint readings), beside the
Cramer-Rao prediction of the latter for the same poses and noise:

    RMS_CR = sqrt( sum_test tr(J_t Sigma J_t^T) / n_spots ),  Sigma = (J_c^T C^-1 J_c)^-1

with J_c, J_t the measurement Jacobians at the true parameters of the
calibration and test poses and C the per-pose spot + joint noise covariance.
Case 3 has no test set in the paper; 30 extra whole-workspace poses per seed
serve to check it. Timings: our LM and EKF against
scipy.optimize.least_squares with a finite-difference Jacobian, same residual.

Usage: python bench/paper_tables.py [--seeds 30]
"""

from __future__ import annotations

import argparse
from dataclasses import replace
import time

from _common import write_results  # first: sets up the import path and BLAS threads

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

from laser_calib.estimation.estimate import EstimateOptions, estimate
from laser_calib.estimation.problem import Problem
from laser_calib.report.statistics import laser_stats, spot_distances
from laser_calib.model.kinematics import predict
from laser_calib.measurement.base import NoiseModel, whiten
from laser_calib.measurement.spot import SpotModel
from laser_calib.sim.simulation import measure, paper_session, sample_poses

# The paper's Tables II and III (mean / std / max in mm, laser 1 then laser 2).
PAPER = {
    "before": {"case1": {"cal": [84.06, 4.54, 96.03, 15.94, 6.83, 29.11], "test": [89.16, 20.48, 154.18, 29.73, 19.63, 85.49]},
               "case2": {"cal": [84.34, 15.62, 154.18, 27.07, 18.70, 85.49], "test": [88.88, 14.10, 143.93, 18.59, 11.89, 55.34]},
               "case3": {"cal": [86.61, 15.05, 154.18, 22.83, 16.24, 85.49]}},
    "lse": {"case1": {"cal": [0.42, 0.14, 0.79, 0.32, 0.13, 0.62], "test": [0.77, 0.52, 2.19, 0.82, 0.57, 2.98]},
            "case2": {"cal": [0.18, 0.13, 0.49, 0.15, 0.10, 0.53], "test": [0.22, 0.19, 0.81, 0.20, 0.17, 0.72]},
            "case3": {"cal": [0.15, 0.10, 0.47, 0.12, 0.09, 0.44]}},
    "ekf": {"case1": {"cal": [0.12, 0.04, 0.23, 0.08, 0.04, 0.16], "test": [0.27, 0.14, 0.69, 0.29, 0.13, 0.65]},
            "case2": {"cal": [0.09, 0.05, 0.26, 0.09, 0.06, 0.25], "test": [0.09, 0.06, 0.27, 0.09, 0.06, 0.28]},
            "case3": {"cal": [0.10, 0.06, 0.29, 0.08, 0.06, 0.23]}},
}


def cramer_rao_rms(session, cal, test) -> float:
    """Predicted RMS spot distance (m) to the true spots on the test poses."""
    model = SpotModel(session.nominal, session.samples.subset(cal))
    noise = NoiseModel(session.noise.spot_sigma, session.noise.joint_sigma)
    res = model.residuals(session.errors, True)
    _, jac = whiten(res, noise.whitener(res))
    covariance = np.linalg.inv(jac.T @ jac)
    test_jac = predict(session.nominal, test.q, session.errors, jacobian=True).jacobian
    seen = test.seen
    per_spot = np.einsum("plin,nm,plim->pl", test_jac, covariance, test_jac)[seen]
    return float(np.sqrt(per_spot.mean()))


def rms(d: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(d ** 2)))


def scipy_time(session, cal, options, repeats=10) -> float:
    """Median time of least_squares ('trf', 2-point finite differences) on the same whitened residual."""
    problem = Problem(SpotModel(session.nominal, session.samples.subset(cal)),
                      NoiseModel(options.spot_sigma, options.joint_sigma), np.ones(33, bool))

    # Favour scipy: its residual skips our Jacobian, with the weights fixed at the start.
    whitener = problem.noise.whitener(problem.residuals(np.zeros(33), True))

    def residual(x):
        return whiten(problem.residuals(x, False), whitener)[0]

    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        least_squares(residual, np.zeros(33), x_scale=problem.scales, jac="2-point")
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def run(seeds: int) -> dict:
    rows = []
    for seed in range(seeds):
        session = paper_session("paper-7dof", seed)
        extra_rng = np.random.default_rng(10_000 + seed)
        extra_q = sample_poses([session.nominal, session.true], 30, extra_rng, "whole")
        extra, extra_truth = measure(session.true, extra_q, extra_rng, session.noise)
        # The paper's estimators: plain least squares (the robust default is measured in robust.py).
        options = EstimateOptions(spot_sigma=session.noise.spot_sigma, joint_sigma=session.noise.joint_sigma,
                                  robust=False)
        for case, (cal, test) in session.cases.items():
            cal_s = session.samples.subset(cal)
            if len(test):
                test_s, test_truth = session.samples.subset(test), session.truth.subset(test)
            else:
                test_s, test_truth = extra, extra_truth
            crb = cramer_rao_rms(session, cal, test_truth)
            variants = {"lm": options, "ekf": replace(options, method="ekf", spot_sigma=None)}
            if case == "case1":
                variants["lm+prior"] = replace(options, prior=True)
            for method, opts in variants.items():
                est = estimate(session.nominal, cal_s, opts)
                values = est.values
                rows.append({
                    "seed": seed, "case": case, "method": method,
                    "iterations": est.fit.iterations, "converged": bool(est.fit.converged),
                    "wall_time_s": est.wall_time, "warnings": list(est.warnings),
                    "cal_before": laser_stats(spot_distances(session.nominal, cal_s)),
                    "cal_after": laser_stats(spot_distances(session.nominal, cal_s, values)),
                    "test_before": laser_stats(spot_distances(session.nominal, test_s)),
                    "test_after": laser_stats(spot_distances(session.nominal, test_s, values)),
                    "test_truth_rms_mm": rms(spot_distances(session.nominal, test_truth, values)) * 1e3,
                    "crb_rms_mm": crb * 1e3,
                    "paper_test_set": bool(len(test)),
                })
        print(f"seed {seed + 1}/{seeds} done", flush=True)
    return {"rows": rows, "timing": timing(seeds)}


def timing(seeds: int) -> dict:
    session = paper_session("paper-7dof", 0)
    cal = session.cases["case3"][0]
    options = EstimateOptions(spot_sigma=session.noise.spot_sigma, joint_sigma=session.noise.joint_sigma,
                              robust=False)
    cal_s = session.samples.subset(cal)
    lm_times = []
    for _ in range(10):
        lm_times.append(estimate(session.nominal, cal_s, options).wall_time)
    ekf = estimate(session.nominal, cal_s, replace(options, method="ekf", spot_sigma=None))
    scipy_s = scipy_time(session, cal, options)
    lm_s = float(np.median(lm_times))
    return {"case": "case3 (60 poses, 33 errors)", "lm_median_s": lm_s, "ekf_s": ekf.wall_time,
            "ekf_iterations": ekf.fit.iterations, "scipy_least_squares_fd_s": scipy_s,
            "scipy_over_lm": scipy_s / lm_s, "ekf_over_lm": ekf.wall_time / lm_s}


def summarise(data: dict) -> tuple[dict, str]:
    rows = data["rows"]
    summary: dict = {"cases": {}}
    lines = ["# Paper Tables II and III, 7-DOF simulation", "",
             f"{len({r['seed'] for r in rows})} seeds; mean over seeds of each statistic (mm). "
             "'vs meas.' = against the noisy measured spots (the paper's measure); "
             "'vs truth' = against the noise-free true spots; CR = Cramer-Rao prediction of the latter.", "",
             "| case | method | set | l1 mean | l1 std | l1 max | l2 mean | l2 std | l2 max | paper l1 mean / l2 mean |",
             "|---|---|---|---|---|---|---|---|---|---|"]

    def mean_stats(selected, key):
        return [float(np.mean([r[key][laser][stat] for r in selected]))
                for laser in ("laser1", "laser2") for stat in ("mean_mm", "std_mm", "max_mm")]

    for case in ("case1", "case2", "case3"):
        case_rows = [r for r in rows if r["case"] == case]
        base = [r for r in case_rows if r["method"] == "lm"]
        for set_key, set_name in (("cal_before", "cal"), ("test_before", "test")):
            if set_name == "test" and case == "case3":
                continue
            s = mean_stats(base, set_key)
            paper = PAPER["before"][case][set_name]
            lines.append(f"| {case} | before | {set_name} | " + " | ".join(f"{v:.2f}" for v in s)
                         + f" | {paper[0]:.2f} / {paper[3]:.2f} |")
        summary["cases"][case] = {}
        for method in sorted({r["method"] for r in case_rows}):
            sel = [r for r in case_rows if r["method"] == method]
            paper_key = {"lm": "lse", "lm+prior": "lse", "ekf": "ekf"}[method]
            for set_key, set_name in (("cal_after", "cal"), ("test_after", "test")):
                if set_name == "test" and case == "case3":
                    continue
                s = mean_stats(sel, set_key)
                paper = PAPER[paper_key][case][set_name]
                lines.append(f"| {case} | {method} | {set_name} vs meas. | " + " | ".join(f"{v:.2f}" for v in s)
                             + f" | {paper[0]:.2f} / {paper[3]:.2f} ({paper_key.upper()}) |")
            truth = np.array([r["test_truth_rms_mm"] for r in sel])
            crb = np.array([r["crb_rms_mm"] for r in sel])
            pooled = float(np.sqrt(np.mean(truth ** 2)))
            pooled_crb = float(np.sqrt(np.mean(crb ** 2)))
            summary["cases"][case][method] = {
                "test_truth_rms_mm_pooled": pooled, "crb_rms_mm_pooled": pooled_crb,
                "efficiency_ratio": pooled / pooled_crb,
                "test_truth_rms_mm_median": float(np.median(truth)),
                "worst_seed_over_crb": float(np.max(truth / crb)),
                "seeds_above_3x_crb": int(np.sum(truth > 3 * crb)),
                "converged_all": all(r["converged"] for r in sel),
                "iterations_median": float(np.median([r["iterations"] for r in sel])),
                "wall_time_median_s": float(np.median([r["wall_time_s"] for r in sel])),
                "seeds_with_warnings": sum(bool(r["warnings"]) for r in sel),
            }
    lines += ["", "## Against the true spots, beside Cramer-Rao", "",
              "| case | method | test RMS vs truth (pooled, mm) | CR prediction (mm) | ratio | median (mm) | worst seed / CR | seeds > 3x CR | median iterations | median time (ms) |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for case, by_method in summary["cases"].items():
        for method, s in by_method.items():
            lines.append(f"| {case}{' (extra test poses)' if case == 'case3' else ''} | {method} | "
                         f"{s['test_truth_rms_mm_pooled']:.3f} | {s['crb_rms_mm_pooled']:.3f} | "
                         f"{s['efficiency_ratio']:.3f} | {s['test_truth_rms_mm_median']:.3f} | "
                         f"{s['worst_seed_over_crb']:.2f} | {s['seeds_above_3x_crb']} | {s['iterations_median']:.0f} | "
                         f"{s['wall_time_median_s'] * 1e3:.1f} |")
    c1 = summary["cases"]["case1"]
    gain = 1 - c1["lm+prior"]["test_truth_rms_mm_median"] / c1["lm"]["test_truth_rms_mm_median"]
    summary["case1_prior_median_gain"] = gain
    t = data["timing"]
    summary["timing"] = t
    lines += ["", "## Targets", "",
              f"- Case 2, LM: test RMS vs truth / Cramer-Rao = {summary['cases']['case2']['lm']['efficiency_ratio']:.3f} (target within 5 %).",
              f"- Case 1: the tolerance prior lowers the median test error vs truth by {gain * 100:.0f} % (target >= 30 %).",
              f"- LM, case 3: {t['lm_median_s'] * 1e3:.1f} ms median; scipy least_squares with finite differences "
              f"{t['scipy_least_squares_fd_s'] * 1e3:.1f} ms: {t['scipy_over_lm']:.1f}x slower (targets < 20 ms, >= 10x).",
              f"- EKF (paper Q = R = 1e-4 I), case 3: {t['ekf_iterations']} iterations, {t['ekf_s']:.2f} s "
              f"({t['ekf_over_lm']:.0f}x LM).",
              f"- LM from nominal, cases 2 and 3: seeds above 3x Cramer-Rao: "
              f"{summary['cases']['case2']['lm']['seeds_above_3x_crb']} and {summary['cases']['case3']['lm']['seeds_above_3x_crb']}."]
    return summary, "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=30)
    args = parser.parse_args()
    data = run(args.seeds)
    summary, table = summarise(data)
    write_results("paper_tables", {"summary": summary, "paper": PAPER, "per_seed": data["rows"]}, table)


if __name__ == "__main__":
    main()
