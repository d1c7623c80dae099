"""Laser spot detection: bgr8 frame -> screen (y, z) of each laser, in metres.

Per laser (1: red, 2: green, see render.py):

1. colour contrast: own channel minus the other (R - G for laser 1, G - R for
   laser 2, saturating at 0). White room light, the black and white fiducials
   and the other laser all drop out; a spot of this laser stays.
2. find: box-filter the contrast image (a cheap matched filter for a blob of
   sigma ~1.3 px) and take its maximum. Below ``min_peak_dn`` the laser is
   not seen (too dim). If a second maximum outside ``exclusion_px`` reaches
   ``ambiguity_ratio`` of the first, which spot is the laser is unknown: not
   seen. Nor is a spot whose other channel rises with its own (by over
   ``max_other_ratio`` above the background): white or warm light, such as a
   glint off the arm, whose small blob demosaicing fringes with colour. Nor
   are two lasers whose maxima are within ``exclusion_px``: each one's
   crosstalk is in the other's fit. A spot on or 1-5 px beside the other
   laser's, up to half as bright, has no maximum of its own: the other's light
   outshines it in its contrast. It is found in the other's fit window
   instead (its channel's light there is off the other's centre, where that
   one's crosstalk is not; or, on one another, a spot of both colours without
   the blue of white light): neither laser is seen, each reason names the
   other. Unsaid, it had pulled the brighter one's centre by up to 0.4 mm.
3. locate: weighted least-squares fit of an elliptical Gaussian (an oblique
   beam's footprint is stretched along its plane of incidence) on a tilted
   plane to the laser's own channel in a window around the maximum, using only photosites
   of the laser's colour (Bayer mosaic) that are not saturated, weighted by the
   camera's noise model (read noise, shot noise, speckle); spot_fit.py. Its
   error is close to the shot- and speckle-limited floor; a thresholded
   centroid (tried) was 15-25 % worse under speckle and locked to the pixel
   grid by up to 0.05 px. The window grows with the spot (second moment, then
   the fitted sigma) to 5 sigmas. A spot whose window leaves the image, that
   is too large for the largest window, whose fit does not settle, or whose
   fit's chi^2 or skewness says the window holds more than one clean spot (a
   touching spot, a reflection, compression artefacts) is not seen: each of
   these moved the centre by 0.3-2 px while the spot was reported. Not told
   apart by shape: a reflection within about 2 px (1.5 spot sigmas), whose sum
   with the spot is an elliptical Gaussian within the noise, and a spot an edge
   in front of the screen (the arm) hides partly, which is a narrower one
   (0.8 mm off with the edge 1.5 px from the centre, the arm as bright as the
   screen); poses whose beams the arm hides from the camera are for the plan
   to avoid, and such a spot is for the robust rule to reject.
4. map: undistort the fitted centre (cv2.undistortPoints, P = K) and apply the
   homography to screen metres. A spot outside the measuring area
   (|y| > half_y or |z| > half_z) is not a measurement (conventions.md): not seen.

A laser that is not seen is reported as NaN, never guessed.

The centre of the blob in the image is not the image of the spot's centre:
perspective and lens distortion make the blob slightly asymmetric. The shift
is of order sigma^2 times the relative change of the pixel scale across the
spot; for the 2 mm spot at the default geometry, the intensity centroid of the
exact (noise-free, continuous) image, mapped back to the screen, is off by
0.001 mm rms and 0.002 mm at most over the screen (bench/vision_bench.py
integrates it numerically), 50 times below the detector's noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
from scipy.special import chdtri

from laser_calib.vision.camera import ScreenCalibration
from laser_calib.vision.spot_fit import SpotFit, background_and_width, fit_spot, off_centre


@dataclass(frozen=True)
class DetectorOptions:
    """Tuning of SpotDetector. DN: digital number of the 8-bit image.

    half_y, half_z: measuring area of the screen, m (conventions.md ``screen``).
    bayer_pattern: photosite colours of the camera, row-major over a 2 x 2
        cell ("RGGB"), or None for a camera that measures every colour at every
        pixel. Only photosites of the laser's own colour are fitted: the
        demosaiced values between them are interpolations, not measurements.
    smooth_px: side of the box filter used to find spots (~4 spot sigmas).
    min_peak_dn: least smoothed colour contrast of a spot. Room light leaves
        ~5 DN in the green contrast (15 DN in the bright light of calibration
        images), sensor noise < 1 DN rms after smoothing; a spot of
        render.RenderOptions defaults gives 25 (screen corners, where
        vignetting dims it) to 70.
    exclusion_px, ambiguity_ratio: a second maximum farther than exclusion_px
        from the first and at least ambiguity_ratio of it makes the laser ambiguous. The two lasers'
        maxima within exclusion_px: each laser's crosstalk (6-12 %) is in the other's fit window, and
        moved the centres by up to 0.46 px at 2-4 px apart (bench/results/spot_refusal.md): neither is seen.
    max_other_ratio: over the unsaturated pixels of the smoothing box, a spot of this laser
        raises the other channel by its crosstalk only (5-21 % of its own rise in the renderer,
        up to 0.6 for a spot 50 times overexposed, blooming or not); white light raises both
        alike, though bilinear demosaicing leaves a small saturated glint >= 15 DN of colour
        contrast. Above it: not seen. Of 150 frames with the lasers off and a white glint
        (sigma 0.5-3 px, 100-3000 DN), 22 gave a spot without this test, 3 with it (glints
        narrower than a spot: fitted sigma 0.57-0.92 px).
    window_half_px, max_window_half_px: the fit window is (2 w + 1)^2 pixels, w >= 5 spot sigmas: it
        starts at window_half_px and grows with the spot; a spot of sigma > max_window_half_px / 5 px
        (defocused) is not seen.
    false_refusal_rate: the fit's chi^2, weighted by the noise model below, of a clean spot follows the
        chi^2 distribution of the window's fitted photosites less 9 parameters (~50 red, ~105 green in a
        15 x 15 window; clean spots: chi^2 / dof 1.00-1.02), and its skewness score chi^2 with 4 (spot_fit:
        mean 3.7-4.5 on clean spots in room and calibration light, 5x over-exposure, defocus). Above the
        upper quantile of half the rate, either says the window holds more than one clean spot: not seen.
        A rate, not a tuned threshold: the quantile follows the window's photosite count. Measured: 1 of
        3000 clean spots refused (room and calibration light, screen corners, 5x over-exposure, beams up to
        70 deg oblique; bench/results/spot_refusal.md), 1 of 1000 in vision_bench's main run. Of the spots a
        touching spot, a reflection or JPEG (quality <= 90) moved by > 0.3 px, 4 of 192 still pass (a
        reflection of 35 % 3 px off, 0.9 px, that the round model's chi^2 refused; JPEG at quality 50).
        With one laser not seen, a third test at half the rate: is its colour's light in the other's fit
        window off that spot's centre (a spot masked in its colour contrast; spot_fit.off_centre)? 1 of 600
        spots of one laser, the other off, refused by it (bench/results/spot_refusal.md); it refuses JPEG
        frames' spots too (4 more of 80 at quality 95, and that at quality 50 above). Only with a
        bayer_pattern: without one the pixels are interpolations (demosaiced, 4:2:2 chroma) whose noise
        is not the model's (chi^2 / dof 1.4-2.5).
    gain_e_per_dn, read_noise_dn, speckle_contrast: the noise model that
        weights the fit: variance = read^2 + signal / gain + (contrast * spot)^2.
        read_noise_dn includes the 8-bit quantisation (0.29 DN). Defaults are
        those of render.RenderOptions; for a real camera take the
        gain and read noise from its data sheet and the speckle contrast from
        the scatter of fits to a still spot. Overestimating it costs little accuracy but blunts the
        chi^2 test (false_refusal_rate); underestimating it refuses clean spots (bench/vision_bench.py).
    """

    half_y: float = 1.0
    half_z: float = 1.0
    bayer_pattern: str | None = "RGGB"
    smooth_px: int = 5
    min_peak_dn: float = 15.0
    exclusion_px: int = 12
    ambiguity_ratio: float = 0.5
    max_other_ratio: float = 0.7
    window_half_px: int = 7
    max_window_half_px: int = 40
    false_refusal_rate: float = 1e-3
    gain_e_per_dn: float = 10000.0 / 255.0
    read_noise_dn: float = 0.4
    speckle_contrast: float = 0.1


# Channel of bgr8 that sees each laser, the channel subtracted for contrast, and its Bayer letter.
_OWN_CHANNEL = (2, 1)
_OTHER_CHANNEL = (1, 2)
_COLOUR = ("R", "G")
_WHITE = "white light (a glint, a lamp), not the laser's colour"


class _Spot(NamedTuple):
    """A laser's spot: centre (u, v) px (2,) in the image, its fit, and the window it was fitted in: (u, v)
    pixel of its centre, w its half side."""

    centre: np.ndarray
    fit: SpotFit
    window: tuple[int, int, int]


class SpotDetector:
    """Finds the two laser spots in bgr8 frames (H, W, 3) uint8 of a calibrated camera."""

    def __init__(self, calibration: ScreenCalibration, options: DetectorOptions = DetectorOptions()):
        pattern = options.bayer_pattern
        if pattern is not None and (len(pattern) != 4 or set(pattern) - set("RGB") or not {"R", "G"} <= set(pattern)):
            raise ValueError(f"bayer_pattern must be 4 letters of R, G, B with both R and G, got {pattern!r}")
        self.calibration = calibration
        self.options = options
        # see false_refusal_rate: no chi^2 test on interpolated pixels
        self._refusal_rate = options.false_refusal_rate if pattern is not None else None

    def detect(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(spots_yz (2,2) float m, NaN where not seen; seen (2,) bool) of lasers 1 and 2."""
        return self.detect_why(image)[:2]

    def detect_why(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[str | None, str | None]]:
        """detect, and why each laser's spot was refused (None where it is seen or none is there)."""
        calibration = self.calibration
        if image.shape != (calibration.height, calibration.width, 3) or image.dtype != np.uint8:
            raise ValueError(f"expected a bgr8 image of {calibration.width} x {calibration.height}, "
                             f"got {image.dtype} {image.shape}")
        channels = cv2.split(image)
        maxima, centres = zip(*(self._locate(channels[_OWN_CHANNEL[j]], channels[_OTHER_CHANNEL[j]], _COLOUR[j])
                                for j in range(2)))
        if None not in maxima and (apart := float(np.hypot(*np.subtract(*maxima)))) <= self.options.exclusion_px:
            # each laser's crosstalk is in the other's fit: both centres pulled
            centres = (f"the other laser's spot is {apart:.0f} px away, within exclusion_px: each one's light is in "
                       "the other's fit",) * 2
        elif not all(isinstance(centre, _Spot) for centre in centres):
            centres = self._masked(channels, centres)
        why = tuple(c if isinstance(c, str) else None for c in centres)
        spots = np.full((2, 2), np.nan)
        found = [j for j in range(2) if isinstance(centres[j], _Spot)]
        if found:
            spots[found] = calibration.pixels_to_screen(np.array([centres[j].centre for j in found]))
        inside = (np.abs(spots[:, 0]) <= self.options.half_y) & (np.abs(spots[:, 1]) <= self.options.half_z)
        why = tuple(reason if reason or inside[j] or j not in found else "outside the screen's measuring area"
                    for j, reason in enumerate(why))
        spots[~inside] = np.nan
        return spots, inside, why

    def _masked(self, channels: tuple[np.ndarray, ...], centres: tuple) -> tuple:
        """centres (a _Spot, a reason or None per laser), with reasons where a laser not seen is there, its
        colour contrast masked by the other's light: the contrast saturates at 0 where the other laser's
        channel outshines its own, so a spot on or 1-5 px beside the other's (up to half its radiance) was lost
        unsaid, and its light in the other's fit window pulled that one's centre toward it by up to 0.4 mm
        (0.13 mm on average for laser 1, 0.06 mm for laser 2, at 10-50 % of its radiance 2-8 mm away)."""
        for j, k in ((0, 1), (1, 0)):
            if isinstance(centres[j], _Spot):
                continue
            if isinstance(centres[k], _Spot) and (mm := self._neighbour(channels[_OWN_CHANNEL[j]], _COLOUR[j],
                                                                         centres[k])) is not None:
                # a reason of its own stands (compression, say, moves the other colour's light too)
                said = [None, None]
                said[j] = centres[j] or (f"within {mm:.0f} mm of laser {k + 1}'s spot, whose light masks its colour "
                                         "contrast: the two cannot be told apart")
                said[k] = (f"light of laser {j + 1}'s colour off its centre in the fit window (laser {j + 1}'s spot "
                           f"within {mm:.0f} mm, masked by this one's light?): it pulls the centre")
                return tuple(said)
        if all(centre is None or centre == _WHITE for centre in centres) and self._both_colours(channels):
            return tuple(f"on laser {k + 1}'s spot, one spot of both colours: the two cannot be told apart"
                         for k in (1, 0))
        return centres

    def _neighbour(self, own: np.ndarray, colour: str, spot: _Spot) -> float | None:
        """Half the side (mm on the screen) of ``spot``'s fit window if this laser's channel ``own`` holds light
        of its own there, else None. Its channel holds the other laser's crosstalk, of the same centre; a spot
        of this laser beside it shifts that light off the centre (spot_fit.off_centre), beyond the upper
        quantile of chi^2 with 2 dof at half false_refusal_rate. No test without a bayer_pattern: the noise is
        not the model's in interpolated pixels."""
        if self._refusal_rate is None:
            return None
        o = self.options
        u, v, w = spot.window
        window = own[v - w:v + w + 1, u - w:u + w + 1].astype(float)
        score = off_centre(window, self._photosites(u - w, v - w, w, colour), spot.fit,
                           (o.read_noise_dn, o.gain_e_per_dn, o.speckle_contrast))
        if score <= chdtri(2, self._refusal_rate / 2):
            return None
        corners = self.calibration.pixels_to_screen(spot.centre + np.array([[0.0, 0.0], [w, 0.0], [0.0, w]]))
        return 1000.0 * float(np.max(np.linalg.norm(corners[1:] - corners[0], axis=1)))

    def _both_colours(self, channels: tuple[np.ndarray, ...]) -> bool:
        """Whether the frame (B, G, R channels) holds a spot of both lasers' colours: the two lasers' spots on
        one another, each one's colour contrast cancelled by the other's light. Neither laser's light has blue,
        white light does (blue rises 0.8 of red and green): at the maximum of min(R, G) - B, the box's mean of
        min(R, G) rises above all of the fit window's rim by min_peak_dn, its blue by under max_other_ratio of
        that. Above the rim's maximum, not its median: a white fiducial cell's corner on black ink rises above
        the median, and bilinear demosaicing blurs its blue edge (0.56 of red and green, not 0.84)."""
        o = self.options
        blue, lasers = channels[0], cv2.min(channels[1], channels[2])
        contrast = cv2.blur(cv2.subtract(lasers, blue), (o.smooth_px, o.smooth_px))
        _, peak, _, (u, v) = cv2.minMaxLoc(contrast)
        w, h = o.window_half_px, o.smooth_px // 2
        height, width = blue.shape
        if peak < o.min_peak_dn or u - w < 0 or v - w < 0 or u + w >= width or v + w >= height:
            return False
        rises = []
        for channel in (lasers, blue):
            window = channel[v - w:v + w + 1, u - w:u + w + 1].astype(float)
            rim = np.concatenate([window[0], window[-1], window[1:-1, 0], window[1:-1, -1]])
            rises.append(window[w - h:w + h + 1, w - h:w + h + 1].mean() - rim.max())
        return rises[0] >= o.min_peak_dn and rises[1] <= o.max_other_ratio * rises[0]

    def _locate(self, own: np.ndarray, other: np.ndarray, colour: str
                ) -> tuple[tuple[int, int] | None, _Spot | str | None]:
        """(Pixel of the maximum of this laser's colour contrast, None if too dim; its fitted spot, None if
        there is none, or why it is refused: ambiguous, not one clean spot, ...)."""
        o = self.options
        contrast = cv2.blur(cv2.subtract(own, other), (o.smooth_px, o.smooth_px))
        _, peak, _, (u, v) = cv2.minMaxLoc(contrast)
        if peak < o.min_peak_dn:
            return None, None
        return (u, v), self._centre(own, other, contrast, peak, u, v, colour)

    def _centre(self, own: np.ndarray, other: np.ndarray, contrast: np.ndarray, peak: float, u: int, v: int,
                colour: str) -> _Spot | str:
        """The fitted spot whose contrast peaks at pixel (u, v), or why it is refused."""
        o = self.options
        r = o.exclusion_px
        contrast[max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1] = 0
        if cv2.minMaxLoc(contrast)[1] >= o.ambiguity_ratio * peak:
            return f"a second spot of its colour, farther than {r} px, is at least {o.ambiguity_ratio:g} of it"
        height, width = own.shape
        w = o.window_half_px
        edge = "its fit window is cut by the image edge"   # no trustworthy centre
        if u - w < 0 or v - w < 0 or u + w >= width or v + w >= height:
            return edge
        own_rise, other_rise = self._rises(own, other, u, v)
        if other_rise > o.max_other_ratio * own_rise:
            return _WHITE
        width_px = 0.0
        for _ in range(4):  # the window grows with the spot until it holds 5 of its sigmas
            if u - w < 0 or v - w < 0 or u + w >= width or v + w >= height:
                return edge
            window = own[v - w:v + w + 1, u - w:u + w + 1].astype(float)
            spread = background_and_width(window)
            width_px = max(width_px, spread[2])
            if 5.0 * width_px <= w:
                fit = fit_spot(window, spread, self._photosites(u - w, v - w, w, colour),
                               (o.read_noise_dn, o.gain_e_per_dn, o.speckle_contrast), self._refusal_rate)
                if isinstance(fit, str):
                    return fit  # no spot, or not one clean spot: its centre would be biased
                width_px = fit.sigma_px
                if 5.0 * width_px <= w:
                    return _Spot(fit.offset + (u, v), fit, (u, v, w))
            w = int(math.ceil(5.0 * width_px))
            if w > o.max_window_half_px:
                return (f"a spot of sigma {width_px:.1f} px (defocused?) is larger than the largest fit window "
                        f"holds (max_window_half_px / 5 = {o.max_window_half_px / 5:g} px)")
        return "its fit window did not settle on the spot's size"

    def _rises(self, own: np.ndarray, other: np.ndarray, u: int, v: int) -> tuple[float, float]:
        """Mean rise (DN) of the own and the other channel above the median of the fit window's rim, over
        the pixels of the smoothing box at (u, v) saturated in neither: a clipped pixel, or a column
        blooming from a saturated spot, says nothing of the light's colour. (0, 0) if none is left."""
        w, h = self.options.window_half_px, self.options.smooth_px // 2
        rises, boxes = [], []
        for channel in (own, other):
            window = channel[v - w:v + w + 1, u - w:u + w + 1].astype(float)
            rim = np.concatenate([window[0], window[-1], window[1:-1, 0], window[1:-1, -1]])
            boxes.append(window[max(w - h, 0):w + h + 1, max(w - h, 0):w + h + 1])
            rises.append(np.median(rim))
        keep = (boxes[0] < 255) & (boxes[1] < 255)
        if not keep.any():
            return 0.0, 0.0
        return float(boxes[0][keep].mean() - rises[0]), float(boxes[1][keep].mean() - rises[1])

    def _photosites(self, col0: int, row0: int, w: int, colour: str) -> np.ndarray:
        """(2w+1, 2w+1) bool: which pixels of the window starting at (col0, row0) measured ``colour``."""
        size = 2 * w + 1
        pattern = self.options.bayer_pattern
        if pattern is None:
            return np.ones((size, size), bool)
        rows = (row0 + np.arange(size))[:, None] % 2
        cols = (col0 + np.arange(size))[None, :] % 2
        return np.array([letter == colour for letter in pattern])[2 * rows + cols]
