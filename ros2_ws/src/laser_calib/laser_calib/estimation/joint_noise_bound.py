"""The joint-reading noise a residual allows, against the noise the fit assumed.

Without a joint sigma, `estimate` weighs the fit with the joint-reading noise only where
the residual shows it (estimate.JOINT_NOISE_ALPHA); elsewhere its covariance assumes none.
But a joint read wrong at one pose moves that pose's spots as the joint's own errors do, so
the fit takes up much of that noise and its residual hides it, while the errors' spread
grows: on a UR10e with 0.058 deg joint noise and 1.15 mm spots, 6 of 7 sessions found
none, and the standard deviations were 1.3 times too small (mean z^2 1.76 against the
truth; 1.0 with both sigmas given).

hidden bounds the joint sigma from above by the profile of the residual's
restricted likelihood (redundancy.joint_noise's; one-sided 95 %: a deviance rise of
chi^2_1's 90 % quantile, the boundary's halved tail) and gives the covariance of the same estimate under that noise,
the sandwich N^-1 (J^T C J) N^-1 with N = J^T J and C each pose's covariance
spot^2 I + joint^2 G G^T (G = jac_q). What it finds is said, not used: the data cannot
decide between the two, and the encoders' rating (--joint-sigma) can.

given_warnings says a given joint sigma far above that bound: 0.02 typed for 0.02 deg is
1.1 deg, and the fit weighs each pose by a noise its spots do not show (a probe's 0.5 rad
left the calibration 53 mm off, with exit 0).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.special import chdtri

from laser_calib.estimation.problem import Fit, residuals_at
from laser_calib.estimation.redundancy import NOISE_RATIO, determined_jacobian
from laser_calib.measurement.base import MeasurementModel, Residuals
from laser_calib.measurement.noise_components import deviance, joint_noise_evidence, noise_components

RISE = float(chdtri(1, 0.10))   # 2.71: one-sided 95 % bound of a sigma whose null lies on its boundary
MAX_JOINT_SIGMA = 0.05          # rad: noise_components' own bound (2.9 deg)
STD_RATIO = 1.5                 # said when a standard deviation could be this much larger (1.2-1.7 on clean 4-DOF sets)


@dataclass(frozen=True)
class HiddenJointNoise:
    """joint_sigma (rad): the largest the residual allows (95 %); spot_sigma (m) with it;
    std_ratio (n,): each parameter's std under that noise over its std without (NaN where
    not free)."""

    joint_sigma: float
    spot_sigma: float
    std_ratio: np.ndarray


def upper_joint_sigma(res: Residuals, jac: np.ndarray, joint: float) -> tuple[float, float]:
    """(joint sigma, spot sigma) where the profile deviance (restricted by ``jac``) has risen
    by RISE above its minimum at ``joint`` (the estimate), by bisection in log sigma; the
    bound MAX_JOINT_SIGMA where it never does."""
    value = deviance(res, 1.0, jac)

    def profile(j: float) -> tuple[float, float]:
        spot = noise_components(res, 1.0, None, j, jac)[0]
        return value(spot, j), spot

    lowest = profile(joint)[0]
    high = (MAX_JOINT_SIGMA, *profile(MAX_JOINT_SIGMA)[::-1])
    if high[2] - lowest < RISE:
        return high[0], high[1]
    low = max(joint, 1e-7)
    for _ in range(40):  # the bound to 1 % of itself: it is said, not used
        middle = float(np.sqrt(low * high[0]))
        rise, spot = profile(middle)
        if rise - lowest < RISE:
            low = middle
        else:
            high = (middle, spot, rise)
        if high[0] / low < 1.01:
            break
    return high[0], high[1]


def fitted(model: MeasurementModel, fit: Fit, excluded: np.ndarray | None) -> tuple[Residuals, np.ndarray] | None:
    """The fit's residuals over the units it kept and its determined Jacobian (redundancy's);
    None when the measurements do not depend on the joint readings or the fit determined nothing."""
    if not fit.free.any():
        return None
    res = residuals_at(model, fit.x, jacobian=True)
    if res.jac_q is None:
        return None
    res = replace(res, valid=res.valid if excluded is None else res.valid & ~excluded)
    return res, determined_jacobian(model, fit, res)


def hidden(model: MeasurementModel, fit: Fit, excluded: np.ndarray | None, joint: float) -> HiddenJointNoise | None:
    """The bound and the stds under it for a fit weighted without joint noise (``joint``: the
    residual's ML joint sigma, which did not pass the test); None when the measurements do not
    depend on the joint readings."""
    if (found := fitted(model, fit, excluded)) is None:
        return None
    res, determined = found
    valid, (n_poses, dims) = res.valid, (res.r.shape[0], res.r.shape[2])
    joint_up, spot_up = upper_joint_sigma(res, determined, joint)
    rows = np.repeat(valid, dims, axis=1)                                          # (P, C*D)
    jac = determined.reshape(n_poses, -1, int(fit.free.sum())) * rows[..., None]
    jac_q = res.jac_q.reshape(n_poses, -1, res.jac_q.shape[-1]) * rows[..., None]
    normal = np.einsum("pmi,pmj->ij", jac, jac)
    moved = np.einsum("pmi,pmq->piq", jac, jac_q)                                 # J_p^T G_p (P, n, N)
    meat = spot_up ** 2 * normal + joint_up ** 2 * np.einsum("piq,pjq->ij", moved, moved)
    inverse = np.linalg.pinv(normal)
    sandwich = inverse @ meat @ inverse
    # without joint noise the covariance is sigma^2 N^-1, sigma the residual's (the variance factor)
    plain = np.diag(inverse) * float(np.sum((res.r * valid[..., None]) ** 2)) / fit.dof
    ratio = np.full(len(fit.x), np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):   # an exact fit: no ratio (NaN, which hidden_warnings skips)
        ratio[fit.free] = np.sqrt(np.diag(sandwich) / plain)
    return HiddenJointNoise(joint_up, spot_up, ratio)


def hidden_warnings(found: HiddenJointNoise | None, names: tuple[str, ...]) -> list[str]:
    """One line when a standard deviation could be STD_RATIO times larger or more."""
    if found is None or not np.nanmax(found.std_ratio, initial=0.0) >= STD_RATIO:
        return []
    worst = int(np.nanargmax(found.std_ratio))
    return [f"noise: no joint-reading noise shows in the residual, but up to {np.degrees(found.joint_sigma):.3g} deg "
            f"fits it as well (95 %), and the fit would take most of it up: the standard deviations assume none and "
            f"could be up to {found.std_ratio[worst]:.2g} times larger ({names[worst]}); give the joint-reading "
            "noise the encoders are rated for (--joint-sigma; the nodes' joint_sigma)"]


def given_warnings(model: MeasurementModel, fit: Fit, excluded: np.ndarray | None, given: float) -> list[str]:
    """One line when the joint sigma ``given`` (rad) exceeds NOISE_RATIO times the largest the
    fit's residual allows (95 %)."""
    if (found := fitted(model, fit, excluded)) is None:
        return []
    res, determined = found
    joint = joint_noise_evidence(res, 1.0, determined)[1]
    bound = upper_joint_sigma(res, determined, joint)[0]
    if given <= NOISE_RATIO * bound:
        return []
    return [f"noise: the residual allows at most {np.degrees(bound):.3g} deg of joint-reading noise (95 %), far below "
            f"the joint sigma given, {given:g} rad ({np.degrees(given):.3g} deg; degrees typed as radians?): the fit "
            "weighs each pose by a noise its spots do not show"]
