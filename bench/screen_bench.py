"""Curved screens outside the library's quadratic (issue 13: "a generic screen surface").

On both paper arms, 80 calibration and 80 test poses (effects_bench's session,
noise and sizing): the screen is a cylinder section, a cubic sag or a gaussian
bump (the shapes the screen surface was built on), or a wave (held out: never
looked at while building it) (sim.effect_truth.curved_screen: width, direction
or centre drawn per seed), sized to leave a chi^2 excess of VISIBILITY in the
geometric fit (small to large), seen by the project's camera
(vision.camera.default_camera, 2.45 m in front of the screen) whose centre the
robot file states (screen.camera; --camera unknown: it does not, none: no
camera parallax in the truth either), diagnosed with the spot and joint sigma
given. Per case: the chosen effects, the test RMS of the geometric fit, of the
final model and of the true model (the geometric errors plus the true shape
with its amplitude fitted), the same ratio over the test spots inside the
calibration spots' convex hull (where a surface learned from the data can be
known; a few grazing beams beyond it carry most of some cases' error), the
nested held-out RMS (selection inside the folds) and the target: final within
15 % of the true model's test RMS. Seeds 1-2 of the first three shapes are the
cases the surface was built on; seed 3 and the wave are reported apart.

    .venv/bin/python bench/screen_bench.py [--seeds 1 2 3] [--sizes 150 600] [--jobs 2] [--camera given]
"""

from __future__ import annotations

import argparse
import multiprocessing
import time
from dataclasses import replace

from _common import verdict_cell, warned_worse_on_test, worse_on_test_warned, write_results

import numpy as np
from effects_bench import N_CAL, N_TEST, NOISE, PERIOD, RMS_MARGIN
from scipy.spatial import Delaunay

from laser_calib.diagnosis.engine import diagnose
from laser_calib.effects.effect_model import EffectModel
from laser_calib.estimation.estimate import EstimateOptions, estimate_model
from laser_calib.measurement.spot import SpotModel
from laser_calib.sim.effect_truth import HELD_OUT_SHAPES, SCREEN_SHAPES, TrueEffect, curved_screen, effect_session, sized
from laser_calib.vision.camera import default_camera

ARMS = ("paper-4dof", "paper-7dof")
TUNED_SEEDS = (1, 2)


def true_model_distances(session, truth: list[TrueEffect], options: EstimateOptions) -> np.ndarray:
    """Test spot distances (P,L) m of the geometric errors plus the true effect fitted on the calibration set."""
    effects = [t.effect for t in truth]
    est = estimate_model(EffectModel(SpotModel(session.nominal, session.cal), effects), options)
    test = EffectModel(SpotModel(session.nominal, session.test), effects).residuals(est.values, False)
    return np.where(test.valid, np.linalg.norm(test.r, axis=-1), np.nan)


def rms_mm(distances: np.ndarray, mask: np.ndarray) -> float:
    return float(np.sqrt(np.mean(distances[mask] ** 2)) * 1e3)


def run_case(arm: str, shape: str, seed: int, visible: float, camera: str) -> dict:
    options = EstimateOptions(spot_sigma=NOISE.spot_sigma, joint_sigma=NOISE.joint_sigma)
    truth: list[TrueEffect] = []

    def make_truth(robot, errors, context, rng):
        drawn = TrueEffect(curved_screen(robot, shape, rng), np.array([2e-3]))
        truth.append(sized(robot, errors, context, drawn, NOISE, visible))
        return list(truth)

    centre = None if camera == "none" else tuple(float(v) for v in default_camera().position)
    session = effect_session(arm, seed, make_truth, N_CAL, N_TEST, NOISE, PERIOD, camera=centre)
    nominal = session.nominal
    if camera == "unknown":
        nominal = replace(nominal, screen=replace(nominal.screen, camera=None))
    start = time.process_time()
    diagnosis = diagnose(nominal, session.cal, session.test, NOISE.spot_sigma, NOISE.joint_sigma)
    cpu = time.process_time() - start
    result = diagnosis.to_json()
    stages = result["stages"]
    true = true_model_distances(session, truth, options)
    final = diagnosis.stages[-1].test
    seen = np.isfinite(true) & np.isfinite(final)
    hull = Delaunay(session.cal.spots[session.cal.seen])
    inside = seen.copy()
    inside[seen] = hull.find_simplex(session.test.spots[seen]) >= 0
    final_rms, true_rms = rms_mm(final, seen), rms_mm(true, seen)
    return {"arm": arm, "shape": shape, "seed": seed, "visibility": visible, "camera": camera,
            "held_out": shape in HELD_OUT_SHAPES or seed not in TUNED_SEEDS, "truth": truth[0].effect.label,
            "amplitude_mm": float(truth[0].values[0]) * 1e3,
            "chosen": [e["name"] + (f" ({surface(e)}, rho {e['smoothing_m'] * 1e3:.2g} mm)"
                                    if "smoothing_m" in e else "") for e in result["effects"]],
            "verdict": result["verdict"], "warned_worse_on_test": warned_worse_on_test(result),
            "geometric_test_rms_mm": stages[0]["test"]["rms_mm"],
            "final_test_rms_mm": final_rms, "true_model_test_rms_mm": true_rms,
            "ratio": final_rms / true_rms, "ratio_inside_hull": rms_mm(final, inside) / rms_mm(true, inside),
            "test_spots_outside_hull": int(seen.sum() - inside.sum()),
            "nested_heldout_rms_mm": result["heldout_nested"]["rms_mm"], "cpu_s": cpu,
            "within_15pct": final_rms <= RMS_MARGIN * true_rms}


def surface(effect: dict) -> str:
    """The screen spline's kind as the table names it: its penalty order, or its Matern length."""
    if "matern_length" in effect:
        return f"Matern, length {effect['matern_length']:g}"
    return f"order {effect['penalty_order']}"


def _case(job: tuple) -> dict:
    return run_case(*job)


def counts(rows: list[dict]) -> str:
    within = sum(r["within_15pct"] for r in rows)
    inside = sum(r["ratio_inside_hull"] <= RMS_MARGIN for r in rows)
    warned, worse = worse_on_test_warned(rows)
    return (f"{within} of {len(rows)} within 15 % of the true model's test RMS "
            f"({inside} of {len(rows)} over the test spots inside the calibration spots' hull); "
            f"{warned} of the {worse} whose final model is worse on the "
            "test poses than the geometric fit warned so")


def table(rows: list[dict], camera: str) -> str:
    seen_by = {"given": "the project's camera 2.45 m in front of the screen, its centre given in the robot file",
               "unknown": "the project's camera 2.45 m in front of the screen, its centre NOT given",
               "none": "no camera parallax (a camera far along the screen normal)"}[camera]
    lines = ["# Curved screens: the screen spline of cross-validated smoothing", "",
             f"{N_CAL} calibration and {N_TEST} test poses, spot noise uniform +-{NOISE.spot * 1e3:g} mm, joint "
             f"noise uniform +-{np.degrees(NOISE.joint):g} deg (both given); screen seen by {seen_by}; test RMS "
             "of the spot error (mm). Visibility: the chi^2 excess the screen leaves in the geometric fit; "
             "amplitude: the shape's size on the screen (mm); ratio: final / true model's test RMS, over all test "
             "spots and over those inside the convex hull of the calibration spots (outside: how many lie "
             "beyond it); CPU time of the diagnosis with its nested held-out error.", ""]
    for title, part in (("Built on (seeds 1-2 of cylinders, cubic sags, bumps)", [r for r in rows if not r["held_out"]]),
                        ("Held out (seed 3, and the wave)", [r for r in rows if r["held_out"]])):
        if not part:
            continue
        lines += [f"## {title}", "",
                  "| arm | screen | seed | visibility | amplitude (mm) | chosen | verdict | geometric | final | true "
                  "model | ratio | ratio inside hull (outside) | nested held-out | CPU (s) | within 15 % |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in part:
            lines.append(
                f"| {r['arm']} | {r['truth']} | {r['seed']} | {r['visibility']:g} | {r['amplitude_mm']:.2f} | "
                f"{'; '.join(r['chosen']) or 'nothing'} | {verdict_cell(r)} | {r['geometric_test_rms_mm']:.3f} | "
                f"{r['final_test_rms_mm']:.3f} | {r['true_model_test_rms_mm']:.3f} | {r['ratio']:.2f} | "
                f"{r['ratio_inside_hull']:.2f} ({r['test_spots_outside_hull']}) | {r['nested_heldout_rms_mm']:.3f} | "
                f"{r['cpu_s']:.0f} | {'yes' if r['within_15pct'] else 'NO'} |")
        lines += ["", counts(part) + ".", ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--sizes", type=float, nargs="+", default=[150.0, 600.0], help="visibilities")
    parser.add_argument("--arms", nargs="+", default=list(ARMS))
    parser.add_argument("--shapes", nargs="+", default=list(SCREEN_SHAPES + HELD_OUT_SHAPES))
    parser.add_argument("--camera", choices=("given", "unknown", "none"), default="given")
    parser.add_argument("--jobs", type=int, default=1, help="cases run in parallel (processes)")
    parser.add_argument("--name", default="screen", help="results file name in bench/results (NAME.md, .json)")
    args = parser.parse_args()
    jobs = [(arm, shape, seed, visible, args.camera) for arm in args.arms for shape in args.shapes
            for visible in args.sizes for seed in args.seeds]
    rows = []
    start = time.perf_counter()
    # Each case is seeded on its own, so the rows do not depend on --jobs (their times do: shared cores).
    with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
        for row in pool.imap(_case, jobs):
            print(f"{row['arm']} {row['truth']} seed {row['seed']} x{row['visibility']:g}: {row['chosen']}, final "
                  f"{row['final_test_rms_mm']:.3f} true {row['true_model_test_rms_mm']:.3f} "
                  f"(ratio {row['ratio']:.2f}, inside hull {row['ratio_inside_hull']:.2f}; {row['cpu_s']:.0f} s CPU)",
                  flush=True)
            rows.append(row)
    write_results(args.name, {"noise": {"spot_halfwidth_m": NOISE.spot, "joint_halfwidth_rad": NOISE.joint},
                              "camera": args.camera, "wall_time_s": time.perf_counter() - start, "cases": rows},
                  table(rows, args.camera))


if __name__ == "__main__":
    main()
