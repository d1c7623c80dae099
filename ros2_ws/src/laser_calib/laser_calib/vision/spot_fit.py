"""Weighted Gaussian fit of one laser spot, and the test that the window holds one clean spot.

The spot is an elliptical Gaussian: a beam meeting the screen at incidence i
draws an ellipse stretched by 1 / cos i along the plane of incidence (the paper
arms' beams meet it at a median 48 deg, 1.2:1 in the image, a tenth beyond 70
deg, 2:1 and more), and a round model of such a spot leaves the residual the
chi^2 test below refuses: 16 of 16 spots at 1.3:1 were lost. The centre of an
elliptical Gaussian is still the beam's axis on the screen.

The fit is weighted by the camera's noise model, so for a clean spot its
weighted residual sum (chi^2) follows the chi^2 distribution of the window's
degrees of freedom (photosites fitted minus the 9 parameters). A window that
holds more than the model (a second spot or the other laser's crosstalk
touching it, a reflection, JPEG blocks, a spot cut by the image) leaves
residual structure the noise cannot explain, and that structure is what moves
the centre: such a fit is refused, as a spot that is not seen, with the reason.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.special import chdtri

_PARAMETERS = 9  # amplitude, centre (2), inverse covariance (3), plane (3)
# A clean Gaussian thresholded at 10 % of its peak has a weighted second moment of 0.604 s^2 per axis:
# <x^2> = s^2 (1 - t - t u - t u^2 / 2) / (1 - t - t u), t = 0.1, u = -ln t.
_THRESHOLD = 0.1
_MOMENT_PER_VARIANCE = 0.604
# A refused spot with a clipped core says so: with a few photosites at 255 the fit of its wings still
# measures it (50 times over-exposed: 0.07 mm rms), beyond that it cannot settle
_SATURATED = 4


class SpotFit(NamedTuple):
    """A fitted spot: offset (2,) px of its centre from the window centre, sigma_px along its major axis,
    covariance (2, 2) px^2 of the offset under the noise model, precision (2, 2) 1/px^2 the inverse of the
    spot's covariance."""

    offset: np.ndarray
    sigma_px: float
    covariance: np.ndarray
    precision: np.ndarray


def background_and_width(window: np.ndarray) -> tuple[float, np.ndarray, float]:
    """(background DN, thresholded signal weights, starting sigma px) of the spot in ``window``.

    The background is the median of the window's rim; the width is the spot's second moment along its
    major axis over its pixels above 10 % of the peak (a defocused or grazing spot of several px is lost if
    the fit starts at a fixed width, or in a window sized for its minor axis). 0 if the window holds no signal.
    """
    rim = np.concatenate([window[0], window[-1], window[1:-1, 0], window[1:-1, -1]])
    background = float(np.median(rim))
    signal = window - background
    weights = np.maximum(signal - _THRESHOLD * signal.max(), 0.0)
    if weights.sum() <= 0.0:
        return background, weights, 0.0
    moments = _moments(weights)[1]
    return background, weights, math.sqrt(max(np.linalg.eigvalsh(moments)[-1] / _MOMENT_PER_VARIANCE, 0.0))


def _moments(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centroid (du, dv) from the window centre, second-moment matrix (2,2)) of the weights (2w+1, 2w+1)."""
    w = weights.shape[0] // 2
    offsets = np.arange(-w, w + 1, dtype=float)
    du, dv = np.meshgrid(offsets, offsets)
    total = weights.sum()
    mean = np.array([np.sum(weights * du), np.sum(weights * dv)]) / total
    x, y = du - mean[0], dv - mean[1]
    cross = np.sum(weights * x * y)
    return mean, np.array([[np.sum(weights * x * x), cross], [cross, np.sum(weights * y * y)]]) / total


def fit_spot(window: np.ndarray, spread: tuple[float, np.ndarray, float], photosites: np.ndarray,
             noise: tuple[float, float, float], rate: float | None) -> SpotFit | str:
    """The spot in ``window`` by a weighted Gaussian fit.

    Model: A exp(-(a x^2 + 2 b x y + c y^2) / 2) + b0 + bu du + bv dv, (x, y) the
    offset from the centre and [[a, b], [b, c]] the inverse of the spot's
    covariance, over the unsaturated photosites (a clipped core carries no
    shape information), weighted by the noise model ``noise`` = (read noise DN,
    gain e-/DN, speckle contrast), re-weighted each Gauss-Newton step with the
    current model. Start: thresholded centroid and second moments, from
    ``spread`` = background_and_width(window). Why it is refused instead, if the
    fit does not settle on a plausible spot (centre inside the window, both
    sigmas > 0.4 px, A > 0) or its chi^2 exceeds the upper ``rate`` quantile of chi^2 with its
    degrees of freedom (no test if ``rate`` is None: pixels whose noise is not
    the model's).
    """
    fit = _fit(window, spread, photosites, noise, rate)
    saturated = int(np.sum(photosites & (window >= 255)))
    if isinstance(fit, str) and saturated >= _SATURATED:
        return f"{fit}, {saturated} of its photosites saturated (lower the exposure or the laser's power)"
    return fit


def _fit(window: np.ndarray, spread: tuple[float, np.ndarray, float], photosites: np.ndarray,
         noise: tuple[float, float, float], rate: float | None) -> SpotFit | str:
    """fit_spot, but for the word on saturation."""
    read, gain, speckle = noise
    w = window.shape[0] // 2
    background, weights, width = spread
    use = photosites & (window < 255)
    if weights.sum() <= 0.0 or use.sum() < 2 * _PARAMETERS:
        return "too few unsaturated photosites of its colour to fit"
    start, moments = _moments(weights)
    # the thresholded moments are 0.604 of the spot's variances; a start no narrower than half a pixel
    precision = np.linalg.inv(moments / _MOMENT_PER_VARIANCE + 0.25 * np.eye(2))
    offsets = np.arange(-w, w + 1, dtype=float)
    du, dv = np.meshgrid(offsets, offsets)
    du, dv, z = du[use], dv[use], window[use]
    q = np.array([window.max() - background, start[0], start[1], precision[0, 0], precision[0, 1], precision[1, 1],
                  background, 0.0, 0.0])
    for _ in range(20):
        amplitude, u0, v0, a, b, c = q[:6]
        x, y = du - u0, dv - v0
        gauss = np.exp(-0.5 * (a * x * x + 2 * b * x * y + c * y * y))
        spot = amplitude * gauss
        model = spot + q[6] + q[7] * du + q[8] * dv
        sigma = np.sqrt(read ** 2 + np.maximum(model, 0.0) / gain + (speckle * spot) ** 2)
        jacobian = np.column_stack([gauss, spot * (a * x + b * y), spot * (b * x + c * y), -0.5 * spot * x * x,
                                    -spot * x * y, -0.5 * spot * y * y, np.ones_like(x), du, dv]) / sigma[:, None]
        residual = (z - model) / sigma
        step = np.linalg.lstsq(jacobian, residual, rcond=None)[0]
        q = q + step
        # a step that leaves the ellipses (an inverse covariance not positive definite) has lost the spot
        if not (np.all(np.isfinite(q)) and q[3] > 0 and q[3] * q[5] > q[4] ** 2):
            return "its fit did not settle"
        if np.max(np.abs(step[1:3])) < 1e-4:
            break
    else:
        return "its fit did not settle"
    precision = np.array([[q[3], q[4]], [q[4], q[5]]])   # the inverse of the spot's covariance
    inverse = np.linalg.eigvalsh(precision)              # 1 / sigma^2, ascending
    if not (q[0] > 0 and inverse[0] > 0 and inverse[1] < 1 / 0.4 ** 2 and np.all(np.abs(q[1:3]) < w - 1)):
        return "its fit settled on no plausible spot"
    # The residual of the last step, less what that step removed (linear in it): chi^2 at the solution.
    residual = residual - jacobian @ step
    chi2 = float(residual @ residual)
    dof = int(use.sum()) - _PARAMETERS
    # the jacobian is whitened: the inverse of its normal matrix is the parameters' covariance (Cramer-Rao)
    found = SpotFit(q[1:3], float(1.0 / math.sqrt(inverse[0])), np.linalg.inv(jacobian.T @ jacobian)[1:3, 1:3],
                    precision)
    if rate is None:
        return found
    # two tests at half the rate each: the family's false refusals stay at the rate
    if chi2 > (limit := float(chdtri(dof, rate / 2))):
        return (f"not one clean spot: its fit's chi^2 is {chi2:.0f} on {dof} dof, beyond {limit:.0f} (a second "
                "spot or a reflection in the window, compression, or more noise than the detector's gain, read "
                "noise and speckle contrast say)")
    if (skew := _skewness(residual, jacobian, spot / sigma, x, y, precision)) > (limit := float(chdtri(4, rate / 2))):
        return (f"not one symmetric spot: its skewness (score chi^2 {skew:.0f} on 4 dof, beyond {limit:.0f}) says a "
                "second spot or a reflection overlaps it, or an edge cuts it")
    return found


def off_centre(window: np.ndarray, photosites: np.ndarray, fit: SpotFit, noise: tuple[float, float, float]
               ) -> float:
    """The score statistic, chi^2(2) if ``window``'s light on ``photosites`` (another colour's) is that of
    the spot ``fit`` (crosstalk: the same light, the same centre), of that light's centre shifted off the
    spot's. Model: alpha g + (du, dv) . grad g + plane, g the fitted spot's Gaussian, linear and weighted by
    the noise model at the model (a second pass); under the spot's light alone the gradient's coefficients
    are alpha times the fit's centre error, whence its covariance. With the fitted shape held, not fitted
    again to the crosstalk's few DN, the statistic keeps to chi^2(2) (a free fit's covariance was 30 % short)."""
    read, gain, speckle = noise
    w = window.shape[0] // 2
    offsets = np.arange(-w, w + 1, dtype=float)
    du, dv = np.meshgrid(offsets, offsets)
    use = photosites & (window < 255)
    du, dv, z = du[use], dv[use], window[use]
    x, y = du - fit.offset[0], dv - fit.offset[1]
    gradient = fit.precision @ np.vstack([x, y])
    g = np.exp(-0.5 * np.sum(np.vstack([x, y]) * gradient, axis=0))
    design = np.column_stack([g, g * gradient[0], g * gradient[1], np.ones_like(x), du, dv])   # (n, 6)
    model, spot = np.maximum(z, 0.0), np.maximum(z - np.median(z), 0.0)
    for _ in range(2):  # weights from the data, then from the model: data weights bias a linear fit
        sigma = np.sqrt(read ** 2 + np.maximum(model, 0.0) / gain + (speckle * spot) ** 2)
        coefficients = np.linalg.lstsq(design / sigma[:, None], z / sigma, rcond=None)[0]
        model, spot = design @ coefficients, coefficients[0] * g
    whitened = design / sigma[:, None]
    covariance = np.linalg.inv(whitened.T @ whitened)[1:3, 1:3] + coefficients[0] ** 2 * fit.covariance
    shift = coefficients[1:3]
    return float(shift @ np.linalg.solve(covariance, shift))


def _skewness(residual: np.ndarray, jacobian: np.ndarray, spot: np.ndarray, x: np.ndarray, y: np.ndarray,
              precision: np.ndarray) -> float:
    """The score statistic, chi^2(4) for one clean spot, of skewness: the third-order terms of the
    Gram-Charlier series of the spot, spot * H_ijk(a, b), (a, b) = L^T (x, y) the offsets whitened by
    the spot's covariance (P = L L^T) and H the Hermite polynomials of order 3 (the first two orders
    are the centre and the covariance, fitted). A spot and a reflection overlapping it, or a spot an
    edge cuts, is skewed, and an elliptical Gaussian fit takes the rest of it in, centre and all:
    a reflection of 20 % of the spot 3 px off moved it 1.7 mm under a chi^2 the noise allows, and a
    test with 4 degrees of freedom sees what one with the window's 100 does not. Residual (n,) and
    jacobian (n, k) whitened at the fit, spot (n,) the fitted spot whitened, (x, y) offsets (n,)."""
    a, b = np.linalg.cholesky(precision).T @ np.vstack([x, y])
    hermite = np.column_stack([a ** 3 - 3 * a, (a * a - 1) * b, a * (b * b - 1), b ** 3 - 3 * b]) * spot[:, None]
    basis = np.linalg.qr(jacobian)[0]
    skew = hermite - basis @ (basis.T @ hermite)       # what the fitted model cannot take in
    coefficients = np.linalg.lstsq(skew, residual, rcond=None)[0]
    return float(residual @ (skew @ coefficients))

