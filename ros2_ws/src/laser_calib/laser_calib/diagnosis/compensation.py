"""Fitting the learned compensator (compensator.py) from the detector's finding.

The detector (detector.py) decides whether the residual follows the inputs
and where: its best sub-model is one direction (a joint angle or a link
parameter) following one input or a pair of joint readings, on a basis kept
small for the test's power (N_KNOTS cubic splines per input, a pair as the
product of its readings). Once that is decided, the shape is the
compensator's to get right: the chosen direction and inputs are refitted on
richer bases (refined), the one of the best held-out gain over the same folds
chosen, the detector's own among them. A harmonic of a joint's angle needs
more knots than four over its range (sin(3 q1): three periods), an error of
two joints' angles (sin q1 sin q7) the products of their splines
(Basis.tensor). Then the model and the regression are fitted together (backfit).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from sklearn.base import clone

from laser_calib.diagnosis.compensator import Compensator
from laser_calib.diagnosis.detector import (ALPHAS, Basis, Detection, FoldRidge, OffsetRegression, design,
                                            input_table)
from laser_calib.effects.effect_model import EffectModel
from laser_calib.estimation.estimate import EstimateOptions, estimate_model
from laser_calib.measurement.base import NoiseModel

BACKFIT = 3  # rounds of model refit / regression refit
KNOTS = (4, 6, 8, 12)  # spline knots per input the refinement tries (the detector's N_KNOTS first)


def refined(regression: OffsetRegression, X: np.ndarray, y: np.ndarray, fold: np.ndarray) -> OffsetRegression:
    """The regression's directions and inputs on the basis (KNOTS; a pair's product or, with
    tensor, the products of its splines) and penalty (ALPHAS) of the best held-out gain over
    the folds ``fold`` (P,) of the poses, fitted on all rows. X (P*V, d+m) and y (P,V) as
    detector.design gives them; a regression of every column (columns None) is returned as it is."""
    if regression.columns is None:
        return regression
    basis, n_inputs = regression.basis, regression.n_inputs
    width, n = basis(basis.mean[None, :]).shape[1], basis.splines_per_input
    directions, local = np.unique(regression.columns // width), np.unique(regression.columns % width)
    inputs = np.unique(local[local < n_inputs * n] // n)
    pairs = basis.pairs[local[local >= n_inputs * n] - n_inputs * n]
    z = X[:, :n_inputs]
    zs = (z - basis.mean) / basis.std
    rows = np.repeat(fold, y.shape[1])
    held = [rows == k for k in np.unique(fold)]
    target = y.ravel()
    best = (-np.inf, regression)
    for n_knots in KNOTS:
        for tensor in (False, True) if len(pairs) else (False,):
            richer = Basis(basis.mean, basis.std, np.linspace(zs.min(axis=0), zs.max(axis=0), n_knots), pairs,
                           basis.size, tensor)
            values = richer(z)
            n_richer = richer.splines_per_input
            own = np.concatenate([np.arange(k * n_richer, (k + 1) * n_richer) for k in inputs]
                                 + [np.arange(n_inputs * n_richer, values.shape[1])])
            columns = np.concatenate([j * values.shape[1] + own for j in directions])
            features = OffsetRegression(richer, n_inputs).formed(X, values, columns)
            gram, cross = features.T @ features, features.T @ target
            sse = np.zeros(len(ALPHAS))
            for part in held:
                h = features[part]
                ridge = FoldRidge.of(gram - h.T @ h, h.T @ h)
                cross_held = h.T @ target[part]
                sse += ridge.sse((cross - cross_held)[:, None], cross_held[:, None],
                                 np.array([target[part] @ target[part]]))[:, 0]
            a = int(np.argmin(sse))
            gain = 1.0 - sse[a] / max(float(target @ target), 1e-300)
            if gain > best[0]:
                best = (gain, OffsetRegression(richer, n_inputs, float(ALPHAS[a]), columns))
    return best[1].fit(X, target)


def backfit(detection: Detection, model: EffectModel, x: np.ndarray, options: EstimateOptions,
            noise: NoiseModel, fold: np.ndarray) -> Compensator:
    """The compensator and the model's values fitted together by backfitting:
    the detector's regression refined (refined, over the folds ``fold`` (P,) of
    the model's poses), the model refitted with the compensation's offsets
    fixed, the regression refitted to the residual the model alone leaves,
    BACKFIT times (the geometric errors had absorbed part of what the
    compensation now carries)."""
    names, z = input_table(model.samples.q, model.samples.stamp, dict(model.samples.extra))
    z = z[:, [names.index(n) for n in detection.inputs]]
    X, y, _, _ = design(model.names, model.residuals(x, True), noise, z)
    regression = refined(detection.regression, X, y, fold)
    compensator = Compensator.of(regression, detection, model.names, x)
    for _ in range(BACKFIT):
        x = estimate_model(compensator.apply(model), replace(options, restarts=0), None, x).values
        X, y, _, _ = design(model.names, model.residuals(x, True), noise, z)
        regression = clone(regression).fit(X, y.ravel())
        compensator = Compensator.of(regression, detection, model.names, x)
    return replace(compensator, values=estimate_model(compensator.apply(model), replace(options, restarts=0), None,
                                                      x).values)
