"""Weighted Gaussian fit of one laser spot, and the test that the window holds one clean spot.

The fit is weighted by the camera's noise model, so for a clean spot its
weighted residual sum (chi^2) follows the chi^2 distribution of the window's
degrees of freedom (photosites fitted minus the 7 parameters). A window that
holds more than the model (a second spot or the other laser's crosstalk
touching it, a reflection, JPEG blocks, a spot cut by the image) leaves
residual structure the noise cannot explain, and that structure is what moves
the centre: such a fit is refused, as a spot that is not seen, with the reason.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import chdtri

_PARAMETERS = 7  # amplitude, centre (2), sigma, plane (3)
# A clean Gaussian thresholded at 10 % of its peak has a weighted second moment of 0.604 s^2 per axis:
# <x^2> = s^2 (1 - t - t u - t u^2 / 2) / (1 - t - t u), t = 0.1, u = -ln t.
_THRESHOLD = 0.1
_MOMENT_PER_VARIANCE = 0.604


def background_and_width(window: np.ndarray) -> tuple[float, np.ndarray, float]:
    """(background DN, thresholded signal weights, starting sigma px) of the spot in ``window``.

    The background is the median of the window's rim; the width is the spot's second moment over its
    pixels above 10 % of the peak (a defocused spot of several px is lost if the fit starts at a fixed
    width). 0 if the window holds no signal.
    """
    rim = np.concatenate([window[0], window[-1], window[1:-1, 0], window[1:-1, -1]])
    background = float(np.median(rim))
    signal = window - background
    weights = np.maximum(signal - _THRESHOLD * signal.max(), 0.0)
    total = weights.sum()
    if total <= 0.0:
        return background, weights, 0.0
    w = window.shape[0] // 2
    offsets = np.arange(-w, w + 1, dtype=float)
    mean_u, mean_v = weights.sum(axis=0) @ offsets / total, weights.sum(axis=1) @ offsets / total
    moment = (weights.sum(axis=0) @ (offsets - mean_u) ** 2 + weights.sum(axis=1) @ (offsets - mean_v) ** 2) / total
    return background, weights, math.sqrt(max(0.5 * moment / _MOMENT_PER_VARIANCE, 0.0))


def fit_spot(window: np.ndarray, spread: tuple[float, np.ndarray, float], photosites: np.ndarray,
             noise: tuple[float, float, float], rate: float | None) -> tuple[np.ndarray, float] | str:
    """(offset (du, dv) of the spot from the window centre, its sigma px) by a weighted Gaussian fit.

    Model: A exp(-r^2 / 2 s^2) + b0 + bu du + bv dv over the unsaturated
    photosites (a clipped core carries no shape information), weighted by the
    noise model ``noise`` = (read noise DN, gain e-/DN, speckle contrast),
    re-weighted each Gauss-Newton step with the current model. Start:
    thresholded centroid and second moment, from ``spread`` =
    background_and_width(window). Why it is refused instead, if the
    fit does not settle on a plausible spot (centre inside the window, s > 0.4
    px, A > 0) or its chi^2 exceeds the upper ``rate`` quantile of chi^2 with its
    degrees of freedom (no test if ``rate`` is None: pixels whose noise is not
    the model's).
    """
    read, gain, speckle = noise
    w = window.shape[0] // 2
    background, weights, width = spread
    use = photosites & (window < 255)
    if weights.sum() <= 0.0 or use.sum() < 2 * _PARAMETERS:
        return "too few unsaturated photosites of its colour to fit"
    offsets = np.arange(-w, w + 1, dtype=float)
    start = np.array([weights.sum(axis=0) @ offsets, weights.sum(axis=1) @ offsets]) / weights.sum()
    du, dv = np.meshgrid(offsets, offsets)
    du, dv, z = du[use], dv[use], window[use]
    q = np.array([window.max() - background, start[0], start[1], max(width, 0.5), background, 0.0, 0.0])
    for _ in range(15):
        amplitude, u0, v0, s = q[:4]
        x, y = du - u0, dv - v0
        gauss = np.exp(-(x * x + y * y) / (2 * s * s))
        spot = amplitude * gauss
        model = spot + q[4] + q[5] * du + q[6] * dv
        sigma = np.sqrt(read ** 2 + np.maximum(model, 0.0) / gain + (speckle * spot) ** 2)
        jacobian = np.column_stack([gauss, spot * x / s ** 2, spot * y / s ** 2, spot * (x * x + y * y) / s ** 3,
                                    np.ones_like(x), du, dv]) / sigma[:, None]
        residual = (z - model) / sigma
        step = np.linalg.lstsq(jacobian, residual, rcond=None)[0]
        q = q + step
        if np.max(np.abs(step[1:3])) < 1e-4:
            break
    else:
        return "its fit did not settle"
    if not (q[0] > 0 and q[3] > 0.4 and np.all(np.abs(q[1:3]) < w - 1)):
        return "its fit settled on no plausible spot"
    # The residual of the last step, less what that step removed (linear in it): chi^2 at the solution.
    chi2 = float(np.sum((residual - jacobian @ step) ** 2))
    dof = int(use.sum()) - _PARAMETERS
    if rate is not None and chi2 > (limit := float(chdtri(dof, rate))):
        return (f"not one clean spot: its fit's chi^2 is {chi2:.0f} on {dof} dof, beyond {limit:.0f} (a second "
                "spot or a reflection in the window, compression, or more noise than the detector's gain, read "
                "noise and speckle contrast say)")
    return q[1:3], float(q[3])
