"""Spot detection accuracy and speed on rendered 1280 x 1024 frames at the paper's geometry.

The default camera (vision.camera.default_camera: 2.45 m in front of the
screen, 12 degrees oblique, k1 = -0.12, 2.2-3.1 mm of screen per pixel) watches
random pairs of spots drawn uniformly over the 2 m x 2 m measuring area
(laser 1 red, laser 2 green; render.RenderOptions defaults: 2 mm spot sigma,
speckle contrast 0.1, dimmed room). Reported:

- spot error against the true spot, per coordinate (RMS of all y and z errors,
  the figure compared with the 0.1 mm target) and radial (RMS of the 2-D
  distance, sqrt(2) larger), with the exact calibration of the simulated camera
  (the detector alone) and with the one calibrate_screen estimates from 30
  rendered ChArUco views and 8 fiducial frames (end to end);
- the systematic floor (frames without speckle or sensor noise) and the
  perspective/distortion bias of a blob's centre (numerical integration of the
  exact image of a Gaussian spot; no rendering involved);
- the error against speckle contrast, which dominates: see the sweep;
- detection rate and false spots on laser-off frames;
- SpotDetector.detect frames per second on one core (cv2.setNumThreads(1),
  BLAS pinned to one thread), over the frames of the main run.

    .venv/bin/python bench/vision_bench.py [--frames 500] [--seed 0]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

from _common import write_results

import cv2
import numpy as np

from laser_calib.vision import (DetectorOptions, RenderOptions, SpotDetector, board_poses, calibrate_screen,
                                default_camera, render_board_frame, render_fiducial_frame, render_frame)

BOTH = np.array([True, True])
CALIBRATION_LIGHT = RenderOptions(ambient_dn=150.0)
NOISE_FREE = RenderOptions(speckle_contrast=0.0, read_noise_e=0.0, full_well_e=1e12, ambient_gradient=0.0)
SPECKLE = (0.0, 0.05, 0.1, 0.2, 0.3)


def statistics(errors_mm: np.ndarray, seen: np.ndarray) -> dict:
    """errors_mm (n, 2 lasers, 2 coords), NaN where not seen; seen (n, 2)."""
    found = errors_mm[seen]
    radial = np.linalg.norm(found, axis=1)
    per_laser = [np.sqrt(np.mean(errors_mm[seen[:, j], j] ** 2)) for j in range(2)]
    return {
        "rms_per_coordinate_mm": float(np.sqrt(np.mean(found ** 2))),
        "rms_radial_mm": float(np.sqrt(np.mean(radial ** 2))),
        "p95_radial_mm": float(np.percentile(radial, 95)),
        "max_radial_mm": float(radial.max()),
        "mean_mm": found.mean(axis=0).tolist(),
        "rms_laser1_mm": float(per_laser[0]),
        "rms_laser2_mm": float(per_laser[1]),
        "detected": int(seen.sum()),
        "spots": int(seen.size),
    }


def run(camera, detectors: dict, options: RenderOptions, frames: int, rng: np.random.Generator,
        timed: str | None = None) -> tuple[dict, list[float]]:
    """Render ``frames`` random spot pairs, detect with each detector; times detector ``timed``."""
    truth = rng.uniform(-1.0, 1.0, (frames, 2, 2))
    errors = {name: np.full((frames, 2, 2), np.nan) for name in detectors}
    seen = {name: np.zeros((frames, 2), bool) for name in detectors}
    times = []
    for k in range(frames):
        image = render_frame(camera, truth[k], BOTH, rng, options)
        for name, detector in detectors.items():
            start = time.perf_counter()
            spots, found = detector.detect(image)
            if name == timed:
                times.append(time.perf_counter() - start)
            errors[name][k] = (spots - truth[k]) * 1000.0
            seen[name][k] = found
    return {name: statistics(errors[name], seen[name]) for name in detectors}, times


def perspective_bias(camera, sigma_m: float, count: int, rng: np.random.Generator) -> dict:
    """Screen error (mm) of the intensity centroid of the exact image of a Gaussian spot.

    The image of the spot is its radiance carried to the image by the camera
    (perspective and distortion): the centroid is the integral of pixel(s) L(s)
    |dpixel/ds| over the screen s, divided by that of L(s) |dpixel/ds|.
    """
    g = np.linspace(-5.0, 5.0, 101) * sigma_m
    offsets = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    radiance = np.exp(-0.5 * np.sum(offsets ** 2, axis=1) / sigma_m ** 2)
    calibration = camera.ideal_calibration()
    errors, h = [], 1e-6
    for spot in rng.uniform(-1.0, 1.0, (count, 2)):
        points = spot + offsets
        p, py, pz = camera.project(points), camera.project(points + [h, 0.0]), camera.project(points + [0.0, h])
        jacobian = np.abs((py[:, 0] - p[:, 0]) * (pz[:, 1] - p[:, 1]) - (py[:, 1] - p[:, 1]) * (pz[:, 0] - p[:, 0]))
        weights = radiance * jacobian
        centre = (p * weights[:, None]).sum(axis=0) / weights.sum()
        errors.append((calibration.pixels_to_screen(centre[None])[0] - spot) * 1000.0)
    errors = np.array(errors)
    return {"rms_per_coordinate_mm": float(np.sqrt(np.mean(errors ** 2))),
            "max_mm": float(np.abs(errors).max())}


def calibrate(camera, rng: np.random.Generator) -> tuple[object, dict]:
    start = time.perf_counter()
    boards = [render_board_frame(camera, rvec, tvec, rng, options=CALIBRATION_LIGHT)
              for rvec, tvec in board_poses(camera, count=30, rng=rng)]
    screens = [render_fiducial_frame(camera, rng, CALIBRATION_LIGHT) for _ in range(8)]
    rendered = time.perf_counter()
    estimated = calibrate_screen(boards, screens)
    solved = time.perf_counter()
    g = np.linspace(-1.0, 1.0, 41)
    points = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    error = (estimated.pixels_to_screen(camera.project(points)) - points) * 1000.0
    return estimated, {
        "board_views": len(boards), "fiducial_frames": len(screens),
        "focal_error_px": (np.diag(estimated.K)[:2] - np.diag(camera.K)[:2]).tolist(),
        "principal_point_error_px": (estimated.K[:2, 2] - camera.K[:2, 2]).tolist(),
        "map_rms_per_coordinate_mm": float(np.sqrt(np.mean(error ** 2))),
        "map_max_mm": float(np.abs(error).max()),
        "render_s": rendered - start, "calibrate_s": solved - rendered,
    }


def table(results: dict) -> str:
    main = results["main"]
    fps = results["speed"]["frames_per_s"]
    target_rms = main["ideal"]["rms_per_coordinate_mm"]
    lines = [
        "# Laser spot detection on rendered frames (vision_bench.py)",
        "",
        f"{results['frames']} frames of 1280 x 1024, random spot pairs over the 2 m x 2 m screen, default camera "
        "and RenderOptions (speckle contrast 0.1). Errors against the true spots, mm.",
        "",
        "## Targets",
        "",
        f"- spot error RMS per coordinate (exact calibration): **{target_rms:.3f} mm** (target <= 0.1 mm): "
        f"{'met' if target_rms <= 0.1 else 'NOT met'}; radial RMS {main['ideal']['rms_radial_mm']:.3f} mm",
        f"- same with the estimated calibration (end to end): {main['estimated']['rms_per_coordinate_mm']:.3f} mm",
        f"- detector speed on one core: **{fps:.0f} frames/s** (target >= 60): {'met' if fps >= 60 else 'NOT met'}"
        f"; median {results['speed']['median_ms']:.2f} ms per frame",
        "",
        "## Accuracy",
        "",
        "| run | calibration | RMS per coord | RMS radial | p95 radial | max radial | laser 1 RMS | laser 2 RMS "
        "| mean (y, z) | detected |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    rows = [("default noise", "exact", main["ideal"]), ("default noise", "estimated", main["estimated"]),
            ("noise-free frames", "exact", results["noise_free"])]
    for label, calibration, s in rows:
        lines.append(f"| {label} | {calibration} | {s['rms_per_coordinate_mm']:.4f} | {s['rms_radial_mm']:.4f} "
                     f"| {s['p95_radial_mm']:.4f} | {s['max_radial_mm']:.4f} | {s['rms_laser1_mm']:.4f} "
                     f"| {s['rms_laser2_mm']:.4f} | ({s['mean_mm'][0]:+.4f}, {s['mean_mm'][1]:+.4f}) "
                     f"| {s['detected']}/{s['spots']} |")
    bias = results["perspective_bias"]
    lines += [
        "",
        f"Perspective and distortion bias of the blob's centre (exact image of a 2 mm spot, numerical "
        f"integration, 200 spots): {bias['rms_per_coordinate_mm']:.4f} mm RMS, {bias['max_mm']:.4f} mm max.",
        "",
        "## Speckle contrast (exact calibration, detector told the contrast)",
        "",
        "| speckle contrast | RMS per coord | RMS radial | laser 1 (red) RMS | laser 2 (green) RMS | detected "
        "| detected, detector assuming 0.1 |",
        "|---|---|---|---|---|---|---|",
    ]
    for contrast, s in results["speckle"].items():
        lines.append(f"| {contrast} | {s['rms_per_coordinate_mm']:.4f} | {s['rms_radial_mm']:.4f} "
                     f"| {s['rms_laser1_mm']:.4f} | {s['rms_laser2_mm']:.4f} | {s['detected']}/{s['spots']} "
                     f"| {s['detected_assuming_0.1']}/{s['spots']} |")
    c = results["calibration"]
    lines += [
        "",
        "Speckle sets the floor: an independent factor of contrast c on each photosite moves the fitted "
        "centre by c p / sqrt(8 pi) px rms per coordinate, p the pitch of the laser's photosites (2 px for red, "
        "sqrt(2) px for green on the Bayer mosaic), i.e. 0.10 mm (red) and 0.07 mm (green) at c = 0.1 and "
        "~2.6 mm per pixel. Without speckle (first row) what remains is sensor noise (shot, read, 8-bit "
        "quantisation) and the systematic floor of the noise-free frames. A detector assuming less speckle "
        "than there is refuses clean spots (last column): their fit's chi^2 exceeds what its noise model "
        "allows (DetectorOptions.false_refusal_rate).",
        "",
        "## Calibration (calibrate_screen)",
        "",
        f"{c['board_views']} ChArUco views and {c['fiducial_frames']} fiducial frames; focal length error "
        f"({c['focal_error_px'][0]:+.2f}, {c['focal_error_px'][1]:+.2f}) px, principal point error "
        f"({c['principal_point_error_px'][0]:+.2f}, {c['principal_point_error_px'][1]:+.2f}) px; "
        f"pixel-to-screen map against the truth over the screen: {c['map_rms_per_coordinate_mm']:.4f} mm RMS, "
        f"{c['map_max_mm']:.4f} mm max (rendering {c['render_s']:.1f} s, solving {c['calibrate_s']:.2f} s).",
        "",
        "## Robustness",
        "",
        f"Laser-off frames: {results['false_spots']['spots']} spots reported in "
        f"{results['false_spots']['frames']} frames (must be 0). Spots that are not one clean Gaussian "
        "(touching, reflections, JPEG, image edge, defocus): spot_refusal.md.",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=500, help="frames of the main run")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    rng = np.random.default_rng(args.seed)
    camera = default_camera()
    estimated, calibration = calibrate(camera, rng)
    detectors = {"ideal": SpotDetector(camera.ideal_calibration()), "estimated": SpotDetector(estimated)}
    defaults = RenderOptions()

    main_run, times = run(camera, detectors, defaults, args.frames, rng, timed="ideal")
    noise_free, _ = run(camera, {"ideal": detectors["ideal"]}, NOISE_FREE, max(args.frames // 5, 20), rng)
    speckle = {}
    for c in SPECKLE:
        told = SpotDetector(camera.ideal_calibration(), DetectorOptions(speckle_contrast=max(c, 0.01)))
        sweep = run(camera, {"told": told, "assumed": detectors["ideal"]}, replace(defaults, speckle_contrast=c),
                    max(args.frames // 3, 20), rng)[0]
        speckle[str(c)] = {**sweep["told"], "detected_assuming_0.1": sweep["assumed"]["detected"]}
    false_frames = 50
    false_spots = sum(int(detectors["ideal"].detect(render_fiducial_frame(camera, rng, options))[1].sum())
                      for options in (defaults, CALIBRATION_LIGHT) for _ in range(false_frames // 2))

    results = {
        "frames": args.frames, "seed": args.seed,
        "main": main_run,
        "noise_free": noise_free["ideal"],
        "perspective_bias": perspective_bias(camera, defaults.spot_sigma_m, 200, rng),
        "speckle": speckle,
        "calibration": calibration,
        "false_spots": {"frames": false_frames, "spots": false_spots},
        "speed": {"frames_per_s": float(len(times) / np.sum(times)), "median_ms": float(np.median(times) * 1e3),
                  "p95_ms": float(np.percentile(times, 95) * 1e3), "threads": 1},
    }
    write_results("vision", results, table(results))


if __name__ == "__main__":
    main()
