"""A laser's spot on or beside the other laser's, masked in its colour contrast (detect.py, step 2).

Frames are rendered with fixed seeds, as in test_vision.py.
"""

import cv2
import numpy as np
import pytest

from laser_calib.vision import RenderOptions, render_fiducial_frame, render_frame
from laser_calib.vision.render import AMBIENT_BGR

BOTH = np.array([True, True])


def _beside(yz: np.ndarray, mm: float, rng: np.random.Generator) -> np.ndarray:
    """The screen point (2,) mm from yz (2,) in a random direction."""
    angle = rng.uniform(0.0, 2.0 * np.pi)
    return yz + mm / 1000.0 * np.array([np.cos(angle), np.sin(angle)])


def _names(reason: str | None, laser: int) -> bool:
    """Whether a reason names the spot of ``laser`` (0 or 1); within exclusion_px it is 'the other laser'."""
    return reason is not None and (f"laser {laser + 1}'s spot" in reason or "the other laser's spot" in reason)


@pytest.mark.parametrize("bright", [0, 1])
def test_a_dim_spot_beside_the_other_is_named_and_the_other_refused(camera, detector, bright):
    # A spot 2-8 mm (1-3 px) from the other laser's, at 20-30 % of its radiance: the other's light outshines
    # it in its colour contrast. It was not seen, unsaid, and its light in the other's fit window pulled that
    # centre toward it by 0.05-0.26 mm (means over 40 frames a case), that spot reported as good.
    dim = 1 - bright
    rng = np.random.default_rng(25 + bright)
    for ratio in (0.2, 0.3):
        for mm in (2.0, 4.0, 6.0, 8.0):
            spots = np.empty((2, 2))
            spots[bright] = rng.uniform(-0.8, 0.8, 2)
            spots[dim] = _beside(spots[bright], mm, rng)
            radiance = [600.0, 600.0]
            radiance[dim] *= ratio
            _, seen, why = detector.detect_why(render_frame(camera, spots, BOTH, rng,
                                                            RenderOptions(laser_radiance_dn=tuple(radiance))))
            assert not seen.any(), (ratio, mm, why)
            assert _names(why[dim], bright) and _names(why[bright], dim), (ratio, mm, why)


def test_spots_on_one_another_are_named_and_white_light_is_not_such_a_spot(camera, detector):
    # Two spots as bright within 1 mm: each one's colour contrast cancelled by the other's light, neither had
    # a maximum (or one, refused as white light), and neither reason said what was there.
    rng = np.random.default_rng(27)
    for mm in (0.0, 0.5, 1.0):
        for _ in range(3):
            first = rng.uniform(-0.8, 0.8, 2)
            _, seen, why = detector.detect_why(render_frame(camera, np.array([first, _beside(first, mm, rng)]),
                                                            BOTH, rng))
            assert not seen.any() and _names(why[0], 1) and _names(why[1], 0), (mm, why)
    # White light is both colours too, with blue: a glint (room light, sigma 0.8-2 px, as in test_vision's
    # test_white_glint_is_not_a_laser) and the fiducials' white cells in room and calibration light.
    rows, cols = np.mgrid[:camera.height, :camera.width]
    sites = np.where(rows % 2 == 0, np.where(cols % 2 == 0, 2, 1), np.where(cols % 2 == 0, 1, 0))  # B 0, G 1, R 2
    for options in (RenderOptions(), RenderOptions(ambient_dn=150.0)):
        for sigma_px, peak_dn in ((0.8, 1000.0), (1.2, 300.0), (2.0, 300.0)):
            frame = render_fiducial_frame(camera, rng, options)
            raw = np.take_along_axis(frame, sites[..., None], axis=2)[..., 0].astype(float)
            glint = peak_dn * np.exp(-((cols - 700.3) ** 2 + (rows - 400.6) ** 2) / (2 * sigma_px ** 2))
            mosaic = np.clip(np.rint(raw + glint * AMBIENT_BGR[sites]), 0, 255).astype(np.uint8)
            for image in (frame, cv2.cvtColor(mosaic, cv2.COLOR_BayerBG2BGR)):
                _, seen, why = detector.detect_why(image)
                assert not seen.any() and not any(_names(reason, 0) or _names(reason, 1) for reason in why), why
