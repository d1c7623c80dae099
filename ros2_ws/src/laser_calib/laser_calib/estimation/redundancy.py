"""What a fit's spare values allow: the values less the parameters fitted to them, its
residual degrees of freedom nu, are all that judges an outlier or estimates the noise.

- outlier_limit: a unit's d^2 over a variance estimated from nu residual values follows
  D F_{D,nu} (Fisher's F), not chi^2_D, which assumes the variance known exactly. With
  thousands of values the two limits agree (20,000 spots: 29.03 against 29.02); with a
  handful the F limit grows without bound (nu = 6, 12 spots: 58 against 14), as it must:
  a variance from a few residual values can be far too small by chance. With nu < 1
  nothing judges anything (robust.py rejects nothing then).
- deletion_distances: a unit left out of a least-squares fit is judged by its residual
  there against its noise plus the fit's own uncertainty where it lies (the externally
  studentised residual, D F_{D,nu} for a clean unit of a linear model). With few values
  to spare that uncertainty is as large as the noise or larger, and a unit the others
  predict loosely looks like an outlier without being one.
- sigma_warnings: a spot sigma estimated from the residual rests on nu values: from 1 or 2
  no standard deviation means anything (Student's t with nu <= 2 has no finite variance):
  NOT A CALIBRATION; up to 7 the noise may be more than NOISE_RATIO times larger (95 %).
- joint_noise: the residual's two noise components (spot, joint reading) and whether it
  shows any joint-reading noise at all, by the restricted likelihood (the part of the
  noise the fit took up allowed for: noise_components).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
# F and chi^2 quantiles without importing scipy.stats (seconds)
from scipy.special import betaincinv, chdtri

from laser_calib.estimation.failures import NOT_A_CALIBRATION
from laser_calib.estimation.problem import Fit, Problem, n_poses, residuals_at
from laser_calib.measurement.base import MeasurementModel, NoiseModel, Residuals
from laser_calib.measurement.noise_components import joint_noise_evidence

FAMILY_FALSE_REJECTION = 0.01  # probability that a clean set loses a unit
NOISE_RATIO = 2.0  # the residual's noise beyond 2x or below 1/2 the given sigma: a warning
# A spot sigma estimated from at most this many residual degrees of freedom is no basis for standard
# deviations: with the noise estimated, (value - truth) / std follows Student's t with that many, which has a
# finite variance only beyond 2.
NO_VARIANCE_DOF = 2


def outlier_limit(dims: int, dof: int, units: int) -> float:
    """D F_{D,dof}(1 - FAMILY_FALSE_REJECTION / units): the limit of d^2 / s^2 for a unit of D values
    when s^2 is a residual variance with ``dof`` degrees of freedom; chi^2_D's quantile as dof grows. F's
    upper tail through the beta law of y = dof / (dof + D F) ~ Beta(dof / 2, D / 2), whose lower tail is
    F's upper one (precise at the small probabilities of thousands of units)."""
    y = float(betaincinv(dof / 2, dims / 2, FAMILY_FALSE_REJECTION / units))
    return dof * (1.0 - y) / y


def unit_covariances(res: Residuals, noise: NoiseModel) -> np.ndarray:
    """(P,C,D,D) each unit's own block of its pose's noise covariance."""
    n_poses, channels, dims = res.r.shape
    inverse_factor = noise.whitener(res)                       # (P, CD, CD), W^T W = C^-1
    covariance = np.linalg.inv(np.einsum("pki,pkj->pij", inverse_factor, inverse_factor))
    return np.stack([covariance[:, c * dims:(c + 1) * dims, c * dims:(c + 1) * dims] for c in range(channels)],
                    axis=1)


def deletion_distances(problem: Problem, fit: Fit, units: np.ndarray) -> tuple[np.ndarray, int]:
    """t^2 (P,C) of the ``units`` (P,C) the least-squares ``fit`` of ``problem`` left out (0 elsewhere), and
    the fit's residual degrees of freedom nu: t^2 = r_u^T (C_u + J_u Cov J_u^T)^-1 r_u / s^2, a unit's
    residual at the fit against its noise C_u plus the fit's uncertainty carried to it, over the fit's
    residual variance s^2 = chi^2 / nu (the prior's rows left out). A unit whose beam misses the screen at
    the fit (no residual there) is as far off as can be: inf. The model runs on the units' poses only."""
    free = problem.free
    dof = fit.n_values - int(np.count_nonzero(free))
    t2 = np.zeros(units.shape)
    if dof < 1:
        return t2, dof
    variance = (fit.chi2 - 2.0 * problem.prior_cost(fit.x)) / dof
    poses = np.flatnonzero(units.any(axis=1))
    if n_poses(problem.model) is not None:
        res = problem.model.subset(poses).residuals(fit.x, True)
    else:  # a model that cannot be cut: all its poses
        full = problem.model.residuals(fit.x, True)
        res = Residuals(full.r[poses], full.valid[poses], full.jac[poses],
                        None if full.jac_q is None else full.jac_q[poses], full.predicted[poses])
    jac = res.jac[..., free]                                                     # (p, C, D, k)
    spread = (jac @ fit.covariance[np.ix_(free, free)]) @ jac.swapaxes(-1, -2)   # (p, C, D, D)
    covariance = unit_covariances(res, problem.noise.for_poses(poses)) + spread
    mine = units[poses] & res.valid
    z = np.linalg.solve(covariance[mine], res.r[mine][..., None])[..., 0]
    inner = np.where(units[poses], np.inf, 0.0)                                  # off the screen: inf
    inner[mine] = np.einsum("ui,ui->u", res.r[mine], z) / max(variance, np.finfo(float).tiny)
    t2[poses] = inner
    return t2, dof


def sigma_upper(dof: int) -> float:
    """How many times larger than its estimate sqrt(chi^2 / dof) the noise's sigma may be: sqrt(dof /
    chi^2_dof(0.025)), the upper end of its 95 % interval: 32 at 1 degree of freedom, 6.3 at 2, 2.2 at 6,
    1.9 at 8."""
    return float(np.sqrt(dof / chdtri(dof, 0.975)))


def sigma_warnings(sigma: float, dof: int, remedy: str = "measure more poses or give the spot sigma") -> list[str]:
    """What a spot sigma (m) estimated from ``dof`` residual degrees of freedom allows (module docstring); the
    remedy is the command's (more poses, more fixture distances)."""
    if dof < 1:  # an exact fit or one that lost its measurements: said elsewhere
        return []
    plural = "s" * (dof > 1)
    if dof <= NO_VARIANCE_DOF:
        return [f"{NOT_A_CALIBRATION}: the spot sigma {sigma * 1e3:.3g} mm is estimated from only {dof} residual "
                f"degree{plural} of freedom (the values less the parameters fitted): the fit is nearly exact, "
                "nothing checks it, and its standard deviations are no bound (with the noise estimated, an "
                f"error's spread is Student's t with {dof} degree{plural} of freedom, which has no finite "
                f"variance); {remedy}"]
    if sigma_upper(dof) > NOISE_RATIO:
        return [f"noise: the spot sigma {sigma * 1e3:.3g} mm is estimated from {dof} residual degrees of freedom "
                f"(the values less the parameters fitted): the true one may be {sigma_upper(dof):.2g} times larger "
                "(95 %), and every standard deviation with it; the values are less precise than their standard "
                f"deviations say ({remedy})"]
    return []


def joint_noise(model: MeasurementModel, trial: Fit, excluded: np.ndarray | None,
                spot: float | None = None) -> tuple[float, float, float]:
    """(spot sigma, joint sigma, p of no joint noise) of the trial fit's residual over the units it
    fitted, by the restricted likelihood of the parameters it determined, the spot sigma held at
    ``spot`` when given; p 1 for a model whose measurements do not depend on joint readings."""
    res = residuals_at(model, trial.x, jacobian=True)
    if res.jac_q is None:
        return spot or 0.0, 0.0, 1.0
    if excluded is not None:
        res = replace(res, valid=res.valid & ~excluded)
    return joint_noise_evidence(res, 1.0, determined_jacobian(model, trial, res), spot)


def determined_jacobian(model: MeasurementModel, fit: Fit, res: Residuals) -> np.ndarray:
    """(P,C,D,k) the Jacobian of the k parameters ``fit`` determined, each in its scale (the
    restricted likelihood's log|X^T C^-1 X| then stays well conditioned)."""
    return res.jac[..., fit.free] * model.scales[fit.free]
