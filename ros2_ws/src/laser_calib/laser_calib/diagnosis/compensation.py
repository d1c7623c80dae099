"""Fitting the learned compensator (compensator.py) from the detector's finding.

The detector (detector.py) decides whether the residual follows the inputs
and where: its best sub-model is one direction (a joint angle or a link
parameter) following one input or a pair of joint readings, on a basis kept
small for the test's power (N_KNOTS cubic splines per input, a pair as the
product of its readings). Once that is decided, the shape is the
compensator's to get right: the chosen direction and inputs are refitted on
richer bases (refined), the one of the best held-out gain over the same folds
chosen where it beats the detector's own per pose. A harmonic of a joint's
angle needs more knots than four over its range (sin(3 q1): three periods), an
error of two joints' angles (sin q1 sin q7) the products of their splines
(Basis.tensor). Then the model and the regression are fitted together (backfit).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import stats
from sklearn.base import clone

from laser_calib.diagnosis.compensator import Compensator
from laser_calib.diagnosis.detector import (ALPHAS, N_KNOTS, Detection, FoldRidge, OffsetRegression, design,
                                            input_table)
from laser_calib.diagnosis.options import EQUIVALENT_P
from laser_calib.effects.effect_model import EffectModel
from laser_calib.estimation.estimate import EstimateOptions, estimate_model
from laser_calib.measurement.base import NoiseModel

BACKFIT = 3  # rounds of model refit / regression refit
KNOTS = (N_KNOTS, 6, 8, 12)  # spline knots per input the refinement tries, the detector's first


def refined(regression: OffsetRegression, X: np.ndarray, y: np.ndarray, fold: np.ndarray) -> OffsetRegression:
    """The regression's directions and inputs on the basis (KNOTS; a pair's product or, with
    tensor, the products of its splines) and penalty (ALPHAS) of the best held-out gain over
    the folds ``fold`` (P,) of the poses, fitted on all rows, where its held-out squared
    errors per pose are below those of the detector's basis by a one-sided paired t test at
    EQUIVALENT_P; else the detector's. The best of up to eight bases on 80 poses is partly
    the folds' chance: without the test, the effects bench's compensated test RMS moved by
    up to 13 % either way where the detector's basis was right. The test is not corrected for
    the choice among them: on a pure-noise residual a richer basis is taken in about a
    quarter of draws (10 of 40 seeds; 39 of 40 without the test). That is a shape chosen,
    not a finding: the compensator exists only where the detector found structure.
    X (P*V, d+m) and y (P,V) as detector.design gives them; a regression of every column
    (columns None) is returned as it is."""
    if regression.columns is None:
        return regression
    basis, n_inputs = regression.basis, regression.n_inputs
    width, n = basis.width, basis.splines_per_input
    directions, local = np.unique(regression.columns // width), np.unique(regression.columns % width)
    inputs = np.unique(local[local < n_inputs * n] // n)
    pairs = basis.pairs[local[local >= n_inputs * n] - n_inputs * n]
    z = X[::y.shape[1], :n_inputs]                       # each pose's inputs (X repeats them per value)
    pose = np.repeat(np.arange(len(fold)), y.shape[1])   # the pose of each row
    held = [fold[pose] == k for k in np.unique(fold)]
    target = y.ravel()
    candidates = []   # (held-out SSE, regression, its features)
    for n_knots in KNOTS:
        for tensor in (False, True) if len(pairs) else (False,):
            # the detector's standardisation and knot span (its first and last knots: the inputs' range)
            richer = replace(basis, knots=np.linspace(basis.knots[0], basis.knots[-1], n_knots), pairs=pairs,
                             tensor=tensor)
            values = np.repeat(richer(z), y.shape[1], axis=0)
            n_richer = richer.splines_per_input
            own = np.concatenate([np.arange(k * n_richer, (k + 1) * n_richer) for k in inputs]
                                 + [np.arange(n_inputs * n_richer, values.shape[1])])
            columns = np.concatenate([j * values.shape[1] + own for j in directions])
            features = OffsetRegression(richer, n_inputs).formed(X, values, columns)
            sse = heldout_sse(features, target, held)
            a = int(np.argmin(sse))
            candidates.append((sse[a], OffsetRegression(richer, n_inputs, float(ALPHAS[a]), columns), features))
    detector = candidates[0]   # KNOTS[0] is the detector's N_KNOTS, the pair its product
    best = min(candidates, key=lambda c: c[0])
    if best is not detector:
        difference = np.bincount(pose, pose_errors(detector, target, held) - pose_errors(best, target, held))
        if stats.ttest_1samp(difference, 0.0, alternative="greater").pvalue >= EQUIVALENT_P:
            best = detector
    return best[1].fit(X, target)


def heldout_sse(features: np.ndarray, target: np.ndarray, held: list[np.ndarray]) -> np.ndarray:
    """(len(ALPHAS),) held-out sums of squares over the folds (rows ``held`` each) of the ridge
    fits of target on features at every penalty (detector.FoldRidge: one eigendecomposition each)."""
    gram, cross = features.T @ features, features.T @ target
    sse = np.zeros(len(ALPHAS))
    for part in held:
        rows = features[part]
        ridge = FoldRidge.of(gram - rows.T @ rows, rows.T @ rows)
        cross_held = rows.T @ target[part]
        sse += ridge.sse((cross - cross_held)[:, None], cross_held[:, None],
                         np.array([target[part] @ target[part]]))[:, 0]
    return sse


def pose_errors(candidate: tuple, target: np.ndarray, held: list[np.ndarray]) -> np.ndarray:
    """Each row's held-out squared error of a candidate of refined (its ridge at its penalty), each
    fold's training sums as all rows' less its held rows', as heldout_sse forms them."""
    _, regression, features = candidate
    gram, cross = features.T @ features, features.T @ target
    penalty = regression.alpha * np.eye(features.shape[1])
    out = np.zeros(len(target))
    for part in held:
        rows = features[part]
        w = np.linalg.solve(gram - rows.T @ rows + penalty, cross - rows.T @ target[part])
        out[part] = (target[part] - rows @ w) ** 2
    return out


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
                                                      x).values, held=tuple(options.fixed))
