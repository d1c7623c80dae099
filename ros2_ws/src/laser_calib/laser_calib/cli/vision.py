"""Command line of the camera-to-screen calibration:

    laser-calib screen-calibrate --board-images DIR --screen-images DIR --out calibration.yaml
    laser-calib render-calibration-images --out DIR [--seed N]

screen-calibrate fits the camera intrinsics, lens distortion and the
homography from undistorted pixels to screen (y, z) metres (vision.calibrate_screen)
and writes the file the spot_detector node reads (its ``calibration``
parameter). render-calibration-images makes both image sets with the simulated
camera, to try the step or test it. cli.py calls register().
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from laser_calib.cli.arguments import non_negative_int, out_file, out_folder, positive_int, staged_folder
from laser_calib.io.errors import InputError
from laser_calib.vision.screen_calibration import ScreenViewMoved, TooFewBoardViews, TooFewFiducials
from laser_calib.vision import (RenderOptions, board_poses, calibrate_screen, default_camera, detect_fiducials,
                     render_board_frame, render_fiducial_frame, save_calibration)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
# cv2.calibrateCamera's RMS above which the intrinsics are suspect (OpenCV's rule of thumb): sharp, still
# views of a flat board give 0.12 px here; a third of the views sheared by 8 % (a board bent, or moved
# during a rolling-shutter exposure) gave 1.6 px, and the fiducials through the map 6 mm RMS (0.3 honest).
SUSPECT_RMS_PX = 1.0
# Calibration images are taken in good light (vision.screen_calibration).
CALIBRATION_LIGHT = RenderOptions(ambient_dn=150.0)


def load_images(folder: str) -> list[np.ndarray]:
    """Every image in folder, in name order, as bgr8 arrays."""
    return [image for _, image in load_image_files(folder)]


def load_image_files(folder: str) -> list[tuple[Path, np.ndarray]]:
    """Every image in folder, in name order, with its file, as bgr8 arrays of one size."""
    path = Path(folder)
    if not path.is_dir():
        raise InputError(folder, "no such folder")
    files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise InputError(folder, f"no images ({', '.join(IMAGE_SUFFIXES)})")
    images = []
    for file in files:
        image = cv2.imread(str(file), cv2.IMREAD_COLOR)
        if image is None:
            raise InputError(str(file), "not a readable image")
        if images and image.shape != images[0][1].shape:
            raise InputError(str(file), f"size {image.shape[1]}x{image.shape[0]} differs from "
                                        f"{images[0][1].shape[1]}x{images[0][1].shape[0]} of the first image")
        images.append((file, image))
    return images


def cmd_screen_calibrate(args: argparse.Namespace) -> int:
    boards, screen_files = load_images(args.board_images), load_image_files(args.screen_images)
    screens = [image for _, image in screen_files]
    if screens[0].shape != boards[0].shape:  # one camera at one resolution: each folder's own size is checked
        raise InputError(str(screen_files[0][0]), f"size {screens[0].shape[1]}x{screens[0].shape[0]} differs from "
                                                  f"{boards[0].shape[1]}x{boards[0].shape[0]} of the board images "
                                                  "(one camera, one resolution, for both)")
    try:
        calibration = calibrate_screen(boards, screens)
    except ScreenViewMoved as exc:
        raise InputError(str(screen_files[exc.index][0]), str(exc)) from None
    except TooFewBoardViews as exc:  # the calibration counts them, the command knows the folder
        raise InputError(args.board_images, f"{exc} (ChArUco board views: are these the board images?)") from None
    except TooFewFiducials as exc:
        raise InputError(args.screen_images, f"{exc} (views of the screen's fiducials: are these the screen "
                                             "images?)") from None
    # How well the map puts the fiducial corners (undistorted pixels) where they are on the screen.
    undistorted, known = detect_fiducials(screens[0], calibration.K, calibration.dist)
    mapped = cv2.perspectiveTransform(undistorted.reshape(-1, 1, 2), calibration.homography).reshape(-1, 2)
    error_mm = np.linalg.norm(mapped - known, axis=1) * 1e3
    try:
        save_calibration(calibration, args.out)
    except OSError as exc:  # --out was checked at the start: the disk filled or the folder went meanwhile
        raise InputError(args.out, f"cannot write ({exc.strerror or exc})") from None
    print(f"camera {calibration.width}x{calibration.height}: fx {calibration.K[0, 0]:.1f} px, "
          f"fy {calibration.K[1, 1]:.1f} px, k1 {calibration.dist[0]:+.4f}; {len(boards)} board views, "
          f"{len(screens)} screen views; reprojection RMS {calibration.reprojection_rms_px:.3f} px")
    print(f"fiducial corners through the map: RMS {np.sqrt(np.mean(error_mm ** 2)):.3f} mm, "
          f"max {error_mm.max():.3f} mm ({len(known)} corners)")
    if calibration.reprojection_rms_px > SUSPECT_RMS_PX:
        print(f"warning: the intrinsics fit their views with a reprojection RMS of "
              f"{calibration.reprojection_rms_px:.2f} px (sharp, still views of a flat board give well under "
              f"{SUSPECT_RMS_PX:g} px): look for blurred or bent board views in {args.board_images}",
              file=sys.stderr)
    centre = ", ".join(f"{v:.3f}" for v in calibration.centre)
    print(f"camera centre in frame {{0}}: [{centre}] m (the robot file's screen: camera:, which a screen that is "
          "not flat needs)")
    print(f"wrote {args.out}")
    return 0


def cmd_render_calibration_images(args: argparse.Namespace) -> int:
    camera = default_camera()
    rng = np.random.default_rng(args.seed)
    with staged_folder(args.out) as out:
        # each image written as it is rendered: a list of 100000 screen views held 24 GB until the OOM killer
        for name, images in (("board", (render_board_frame(camera, rvec, tvec, rng, options=CALIBRATION_LIGHT)
                                        for rvec, tvec in board_poses(camera, count=args.board_views, rng=rng))),
                             ("screen", (render_fiducial_frame(camera, rng, CALIBRATION_LIGHT)
                                         for _ in range(args.screen_views)))):
            (out / name).mkdir()
            for k, image in enumerate(images):
                _write_image(out / name / f"{name}_{k:03d}.png", image)
    print(f"wrote {args.board_views} board views to {args.out}/board and {args.screen_views} screen views to "
          f"{args.out}/screen (simulated camera, seed {args.seed})")
    return 0


def _write_image(path: Path, image: np.ndarray) -> None:
    """cv2.imwrite says a failed write only by returning False: an OSError, so the stage is removed."""
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cannot write {path.name}")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("screen-calibrate", help="camera intrinsics and image-to-screen map from fiducial images")
    p.add_argument("--board-images", required=True, help="folder of ChArUco board views (intrinsics)")
    p.add_argument("--screen-images", required=True, help="folder of screen fiducial views from the fixed camera")
    p.add_argument("--out", required=True, type=out_file, help="calibration YAML for the spot_detector")
    p.set_defaults(func=cmd_screen_calibrate)

    p = sub.add_parser("render-calibration-images", help="calibration images of the simulated camera")
    p.add_argument("--out", required=True, type=out_folder, help="folder of the board/ and screen/ image folders "
                                                                  "(each replaced as a whole)")
    p.add_argument("--seed", type=non_negative_int, default=0)
    # As calibrate_screen recommends (20-30 tilted board views, 5-10 screen views).
    p.add_argument("--board-views", type=positive_int, default=30)
    p.add_argument("--screen-views", type=positive_int, default=8)
    p.set_defaults(func=cmd_render_calibration_images)
