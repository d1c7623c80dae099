"""Every image encoding camera drivers publish, from rendered frames of known spots, through
vision.encodings.to_bgr8 into the spot detector."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from laser_calib.vision import RenderOptions, default_camera, render_frame
from laser_calib.vision.camera import ScreenCalibration
from laser_calib.vision.detect import DetectorOptions, SpotDetector
from laser_calib.vision.encodings import BAYER, pattern_of, to_bgr8

CAMERA = default_camera()
CALIBRATION = CAMERA.ideal_calibration()
TRUE_SPOTS = [np.array([[-0.4, 0.3], [0.5, -0.2]]), np.array([[0.1, -0.6], [-0.7, 0.6]]),
              np.array([[0.65, 0.55], [0.0, 0.0]])]


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(11)
    return [render_frame(CAMERA, s, np.ones(2, bool), rng, RenderOptions()) for s in TRUE_SPOTS]


def mosaic(bgr: np.ndarray) -> np.ndarray:
    """The RGGB photosites of a rendered frame (the renderer demosaics exactly these)."""
    raw = bgr[:, :, 1].copy()
    raw[0::2, 0::2] = bgr[0::2, 0::2, 2]
    raw[1::2, 1::2] = bgr[1::2, 1::2, 0]
    return raw


def cropped(rows: int, cols: int) -> ScreenCalibration:
    """The calibration of the image cropped by rows at the top and cols at the left (pixel origin moved)."""
    c = CALIBRATION
    K = c.K.copy()
    K[0, 2] -= cols
    K[1, 2] -= rows
    shift = np.array([[1.0, 0, cols], [0, 1.0, rows], [0, 0, 1.0]])
    return ScreenCalibration(c.width - cols, c.height - rows, K, c.dist, c.homography @ shift)


def yuv422(bgr: np.ndarray, order: str) -> bytes:
    """BT.601 video-range 4:2:2, chroma averaged over pixel pairs; order 'UYVY' or 'YUYV'."""
    b, g, r = (bgr[:, :, i].astype(float) for i in range(3))
    y = 16 + 0.257 * r + 0.504 * g + 0.098 * b
    u = 128 - 0.148 * r - 0.291 * g + 0.439 * b
    v = 128 + 0.439 * r - 0.368 * g - 0.071 * b
    u = (u[:, 0::2] + u[:, 1::2]) / 2
    v = (v[:, 0::2] + v[:, 1::2]) / 2
    out = np.empty((bgr.shape[0], bgr.shape[1] // 2, 4))
    if order == "UYVY":
        out[..., 0], out[..., 1], out[..., 2], out[..., 3] = u, y[:, 0::2], v, y[:, 1::2]
    else:
        out[..., 0], out[..., 1], out[..., 2], out[..., 3] = y[:, 0::2], u, y[:, 1::2], v
    return np.clip(np.rint(out), 0, 255).astype(np.uint8).tobytes()


def detect(image: np.ndarray, pattern: str | None = "RGGB", calibration=CALIBRATION) -> np.ndarray:
    spots, seen = SpotDetector(calibration, dataclasses.replace(DetectorOptions(), bayer_pattern=pattern)).detect(image)
    assert seen.all()
    return spots


def test_colour_and_raw_encodings_give_the_bgr8_spots(frames):
    h, w = CALIBRATION.height, CALIBRATION.width
    for frame in frames:
        reference = detect(frame)
        rgb = to_bgr8(frame[:, :, ::-1].tobytes(), w, h, 3 * w, "rgb8")
        np.testing.assert_array_equal(rgb, frame)
        padded = np.zeros((h, 3 * w + 8), np.uint8)   # rows padded by the driver: step > 3 width
        padded[:, :3 * w] = frame.reshape(h, -1)
        np.testing.assert_array_equal(to_bgr8(padded.tobytes(), w, h, 3 * w + 8, "bgr8"), frame)
        raw = mosaic(frame)
        # the raw mosaic demosaiced as the renderer does: the same image (OpenCV keeps each measured
        # photosite except in the outermost pixels), the same spots
        for image in (to_bgr8(raw.tobytes(), w, h, w, "bayer_rggb8"),
                      to_bgr8(raw.tobytes(), w, h, w, "mono8", mono_pattern="RGGB")):
            np.testing.assert_array_equal(image[2:-2, 2:-2], frame[2:-2, 2:-2])
            np.testing.assert_array_equal(detect(image), reference)
        # the other three mosaics: the same sensor cropped by a row and/or a column
        for (rows, cols), encoding in (((0, 1), "bayer_grbg8"), ((1, 0), "bayer_gbrg8"), ((1, 1), "bayer_bggr8")):
            part = np.ascontiguousarray(raw[rows:, cols:])
            image = to_bgr8(part.tobytes(), w - cols, h - rows, w - cols, encoding)
            spots = detect(image, pattern_of(encoding, None), cropped(rows, cols))
            # identical photosites, the same fit: equal to rounding in the pixel-to-screen map
            np.testing.assert_allclose(spots, reference, rtol=0, atol=1e-9)


def test_yuv422_spots_within_the_detector_noise(frames):
    """4:2:2 halves the horizontal chroma resolution the lasers are told apart by, so its spots
    differ from bgr8's; the bound is the detector's own scatter on these frames, 3 sigma."""
    h, w = CALIBRATION.height, CALIBRATION.width
    bgr_error = np.array([detect(f) - s for f, s in zip(frames, TRUE_SPOTS)])      # (F,2,2) m
    noise = np.sqrt(np.mean(bgr_error ** 2))
    for encoding, order in (("yuv422", "UYVY"), ("yuv422_yuy2", "YUYV")):
        errors = []
        for frame, truth in zip(frames, TRUE_SPOTS):
            image = to_bgr8(yuv422(frame, order), w, h, 2 * w, encoding)
            errors.append(detect(image, None) - truth)
        rms = np.sqrt(np.mean(np.array(errors) ** 2))
        print(encoding, f"rms {rms * 1e3:.4f} mm, bgr8 {noise * 1e3:.4f} mm")
        assert rms < 3 * noise, (encoding, rms, noise)


@pytest.mark.parametrize("args, message", [
    ((b"\0" * 12, 2, 2, 6, "bgr16"), "encoding 'bgr16' not supported"),
    ((b"\0" * 10, 2, 2, 6, "bgr8"), "do not hold the image"),
    ((b"\0" * 4, 2, 2, 2, "mono8"), "cannot tell the two lasers apart"),
    ((b"\0" * 6, 3, 1, 6, "yuv422"), "width 3 is odd"),
])
def test_bad_images_are_one_line(args, message):
    with pytest.raises(ValueError, match=message):
        to_bgr8(*args)


def test_every_bayer_encoding_names_its_pattern():
    assert {pattern_of(e, None) for e in BAYER} == {"RGGB", "BGGR", "GBRG", "GRBG"}
    assert pattern_of("rgb8", "RGGB") is None and pattern_of("mono8", "GRBG") == "GRBG"
