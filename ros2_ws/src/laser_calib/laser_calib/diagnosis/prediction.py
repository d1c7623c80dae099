"""The predictive test on the test poses: do they follow the model the calibration poses chose?

The selection and every structure test see the calibration poses only. An effect that
differs between the calibration sequence and a test one (the order of the moves, for a
friction loop; the region of the screen, for a surface extrapolated beyond the calibration
spots) can be fitted there as well as the truth would be and still miss the test poses:
such verdicts said "explained" while the test RMS was 1.3 to 2 times the true model's.
Chow's (1960) predictive-failure test: under the final model a test pose's whitened residual
r_t (m_t,) has covariance s^2 (I + J_t C J_t^T), C (k,k) the estimate's covariance at unit
scale and J_t (m_t,k) the test Jacobian in the free parameters, so that

    T = r_t^T (I + J_t C J_t^T)^-1 r_t,    F = (T / m_t) / (RSS / dof) ~ F(m_t, dof)

with RSS the calibration poses' whitened residual sum of squares on dof degrees of freedom.
The noise scale s^2 cancels: no sigma needs to be given, and what is tested is only that the
test poses are fitted as the calibration poses are. Two nulls are tested: the ratio is 1
(p: at alpha, a chance in 1 / alpha data sets; a warning), and the ratio is at most
MARGIN^2 (p_margin: the test poses missed by more than MARGIN times in RMS what the model
predicts for them, past chance; the verdict's structure). F / MARGIN^2 is F(m_t, dof) on the
second null's boundary. With C = L L^T and A = J_t L (m_t,k),
(I + A A^T)^-1 = I - A (I + A^T A)^-1 A^T (Woodbury), summed block by block of poses.

A wrong spot in the test file would fail the test as structure does, and the data cannot
tell them apart (a grazing beam on a curved screen misses by 30 sigma where the surface is
extrapolated). Test units beyond the robust rule's limit chi^2_D(1 - 0.01 / N)
(estimation.robust) at the calibration's scale are left out of the test and listed; the
verdict counts them as it counts the calibration's (verdict.predicted).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from laser_calib.diagnosis.data import Data
from laser_calib.diagnosis.result import Fitted, Prediction
from laser_calib.diagnosis.screening import named, within_limit
from laser_calib.effects.effect_model import EffectModel
from laser_calib.estimation.problem import pose_blocks, residuals_at
from laser_calib.estimation.robust import distances_at
from laser_calib.measurement.base import NoiseModel, whiten

# How much worse in RMS than predicted the test poses may be fitted before the verdict calls it
# structure: the bound issue 13 sets on an "explained" model's test RMS against the true model's.
# A smaller excess, significant, is warned of: at alpha, effect-free data sets give one by chance
# once in 1 / alpha (a 7-DOF one of the effects bench: ratio 1.32, p = 0.008).
MARGIN = 1.3


def predictive_test(final: Fitted, test: Data, noise: NoiseModel) -> Prediction | None:
    """The predictive-failure F test of ``test`` under ``final`` and the verdict's noise
    model (module docstring); None when no test value is left to test or no calibration
    degree of freedom."""
    x = final.estimate.values
    res = residuals_at(final.model, x, jacobian=noise.joint_noise, parameters=False)
    r, _ = whiten(res, noise.whitener(res))
    m = int(res.valid.sum()) * res.r.shape[2]
    dof = round(m - final.n_free)  # effective parameters: a penalised screen spends fewer than it has
    if dof < 1:
        return None
    scale2 = float(r @ r) / dof
    d2, valid, dims = distances_at(EffectModel(test.base(), final.effects), noise, x)
    beyond = valid & ~within_limit(d2, valid, dims, scale2)
    kept = test.without(beyond) if beyond.any() else test
    fit = final.estimate.fit
    w, v = np.linalg.eigh(fit.covariance[np.ix_(fit.free, fit.free)])
    root = v * np.sqrt(np.clip(w, 0.0, None))  # (k,k) L with C = L L^T
    k = root.shape[1]
    total, a_r, a_a, m_test = 0.0, np.zeros(k), np.zeros((k, k)), 0
    for _, block in pose_blocks(EffectModel(kept.base(), final.effects)):
        block_res = block.residuals(x, True)
        r_t, jac = whiten(block_res, noise.whitener(block_res))
        a = jac[:, fit.free] @ root
        total += float(r_t @ r_t)
        a_r += a.T @ r_t
        a_a += a.T @ a
        m_test += int(block_res.valid.sum()) * block_res.r.shape[2]
    if m_test < 1 and beyond.any():
        # Every test measurement grossly missed: the model does not predict the test poses at all (a test
        # set 50 mm off kept "explained", nothing said). No F to compute; it fails any margin.
        return Prediction(math.inf, (0, dof), 0.0, 0.0, MARGIN, int(beyond.sum()), named(test, beyond))
    if m_test < 1 or scale2 <= 0:
        return None
    quadratic = total - float(a_r @ np.linalg.solve(np.eye(k) + a_a, a_r))
    ratio = quadratic / m_test / scale2
    return Prediction(ratio, (m_test, dof), float(stats.f.sf(ratio, m_test, dof)),
                      float(stats.f.sf(ratio / MARGIN ** 2, m_test, dof)), MARGIN, int(beyond.sum()),
                      named(test, beyond) if beyond.any() else "")
