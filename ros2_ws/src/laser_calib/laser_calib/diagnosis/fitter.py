"""Fits and cross-validation of candidate models on one calibration set."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Sequence

import numpy as np
from scipy import stats

from laser_calib.diagnosis.data import Data
from laser_calib.diagnosis.noise import noise_components
from laser_calib.diagnosis.options import DiagnoseOptions
from laser_calib.diagnosis.result import Fitted
from laser_calib.effects.base import Effect
from laser_calib.effects.effect_model import EffectModel
from laser_calib.estimation.estimate import EstimateOptions, estimate_model
from laser_calib.estimation.folds import kfold_labels
from laser_calib.measurement.base import NoiseModel, whiten

def distances(model: EffectModel, x: np.ndarray) -> np.ndarray:
    res = model.residuals(x, False)
    return np.where(res.valid, np.linalg.norm(res.r, axis=-1), np.nan)


class Fitter:
    """Fits and cross-validates models on one calibration set, all with
    estimate_model, the same folds and one reference noise model: the noise
    given, with the components not given estimated once from the geometric
    fit (start)."""

    def __init__(self, data: Data, options: DiagnoseOptions):
        self.base = data.base()
        self.fixed = data.fixed
        self.options = options
        # Plain least squares: the structure the diagnosis looks for shows as large
        # residuals, which the robust rule would weigh down (the effects bench was
        # measured so); gross outliers are the estimate's to reject first.
        self.fit_options = EstimateOptions(method=options.method, spot_sigma=options.spot_sigma,
                                           joint_sigma=options.joint_sigma or 0.0, restarts=options.restarts,
                                           seed=options.seed, fixed=data.fixed, robust=False)
        self.fold = kfold_labels(len(data.samples.q), options.folds, options.seed)
        self.reference = NoiseModel(options.spot_sigma or 1.0, options.joint_sigma or 0.0)
        self.merged: dict[str, str] = {}

    def start(self) -> Fitted:
        """The geometric fit under the reference noise model.

        Noise components not given are estimated by maximum likelihood from the
        residual of a first geometric fit (noise_components) and the fit is
        repeated with them, so that poses are weighted by their real noise
        (joint-reading noise correlates a pose's four values; ignoring it makes
        every test overconfident). An effect still in that residual inflates
        the estimates, which only makes the tests more cautious.
        """
        first = estimate_model(EffectModel(self.base, ()), self.fit_options)
        # What the nominal geometry cannot separate stays fixed in every later fit: a warm
        # start at estimated errors would see such pairs as barely separable and creep along them.
        self.merged = dict(first.identifiability.merged)
        self.fit_options = replace(self.fit_options, fixed=self.fixed + tuple(self.merged))
        if self.options.spot_sigma is not None and self.options.joint_sigma is not None:
            return self.fit((), first.values)
        res = self.base.residuals(first.values, True)
        m = int(res.valid.sum()) * res.r.shape[2]
        scale = math.sqrt(m / max(m - int(first.identifiable.sum()), 1))
        spot, joint = noise_components(res, scale, self.options.spot_sigma, self.options.joint_sigma)
        self.fit_options = replace(self.fit_options, spot_sigma=spot, joint_sigma=joint)
        self.reference = NoiseModel(spot, joint)
        return self.fit((), first.values)

    def fit(self, effects: tuple[Effect, ...], x0: np.ndarray) -> Fitted:
        """Fit and cross-validate the geometric errors plus ``effects`` from the
        warm start x0. No LM restarts: x0 is a converged fit (the first
        geometric fit had them), and the folds start from the full fit."""
        model = EffectModel(self.base, effects)
        options = replace(self.fit_options, restarts=0)
        est = estimate_model(model, options, None, x0)
        res = model.residuals(est.values, True)
        cv = np.full(res.valid.shape, np.nan)
        cv_chi2 = np.zeros(len(cv))
        for k in range(self.options.folds):
            held = self.fold == k
            train = estimate_model(model.subset(~held), options, None, est.values)
            held_res = model.subset(held).residuals(train.values, True)
            cv[held] = np.where(held_res.valid, np.linalg.norm(held_res.r, axis=-1), np.nan)
            white = np.einsum("pij,pj->pi", self.reference.whitener(held_res),
                              held_res.r.reshape(len(held_res.r), -1))
            cv_chi2[held] = (white ** 2).sum(axis=1)
        r, _ = whiten(res, self.reference.whitener(res))
        cal = np.where(res.valid, np.linalg.norm(res.r, axis=-1), np.nan)
        return Fitted(effects, model, est, cv, cv_chi2, cal, float(r @ r), int(res.valid.sum()) * res.r.shape[2],
                      int(est.identifiable.sum()))

    def screen(self, current: Fitted, pool: Sequence[Effect]) -> list[tuple[Effect, float, float]]:
        """Linearised cross-validation of the current model plus each candidate:
        (effect, held-out chi^2 per measured value, held-out MSE in m^2), best first.

        All candidates are evaluated in one joint model at the current fit with
        their parameters at 0; per fold, one least-squares solve in the current
        model's free parameters and the candidate's, on the training poses'
        whitened rows, predicts the held-out poses' rows.
        """
        model = EffectModel(self.base, current.effects + tuple(pool))
        x = np.concatenate([current.estimate.values, np.zeros(len(model.names) - len(current.model.names))])
        res = model.residuals(x, True)
        r_white, jac_white = whiten(res, self.reference.whitener(res))
        jac_white = jac_white * model.scales
        n_poses, dims = res.r.shape[0], res.r.shape[2]
        raw_jac = res.jac.reshape(n_poses, -1, len(model.names)) * model.scales
        raw_r = res.r.reshape(n_poses, -1)
        valid = np.repeat(res.valid, dims, axis=1)
        pose_of_row = np.repeat(np.arange(n_poses), raw_r.shape[1])
        n_values = max(int(valid.sum()), 1)
        # The current model's free parameters come first in the joint model's x, in the same places.
        kept = list(np.flatnonzero(current.estimate.identifiable))
        out = []
        for effect, block in zip(pool, model.blocks[len(current.effects):]):
            columns = kept + list(range(model.n_geometric + block.start, model.n_geometric + block.stop))
            chi2 = squared = 0.0
            for k in range(self.options.folds):
                held = self.fold == k
                held_rows = held[pose_of_row]
                step = np.linalg.lstsq(jac_white[~held_rows][:, columns], r_white[~held_rows], rcond=None)[0]
                chi2 += float(((r_white[held_rows] - jac_white[held_rows][:, columns] @ step) ** 2).sum())
                predicted = raw_r[held] - raw_jac[held][:, :, columns] @ step
                squared += float((predicted[valid[held]] ** 2).sum())
            out.append((effect, chi2 / n_values, squared / max(res.valid.sum(), 1)))
        return sorted(out, key=lambda item: item[1])


def paired_p(current: Fitted, candidate: Fitted) -> float:
    """One-sided paired t test over the calibration poses that the candidate's
    mean held-out chi^2 (each pose's held-out residual whitened by the
    reference noise model) is smaller than the current model's. Whitening puts
    poses whose spots the joint noise moves a lot (long beams, grazing
    incidence) on the same footing as the rest, which keeps the differences'
    tails short enough for the t test; it tests the mean, which is what the
    held-out error is (a rank test misses improvements concentrated in part
    of the poses)."""
    difference = current.cv_chi2 - candidate.cv_chi2
    if len(difference) < 3 or not np.any(difference):
        return 1.0
    return float(stats.ttest_1samp(difference, 0.0, alternative="greater").pvalue)


def rms_mm(distances: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(distances ** 2)) * 1e3)


def fit_test_p(current: Fitted, candidate: Fitted) -> float:
    """F test of the chi^2 decrease (nested fits, same reference whitening):
    F = (Δchi^2 / Δk) / (chi^2 / dof) of the candidate; scale-free, so a
    misstated noise level does not matter."""
    extra = candidate.n_free - current.n_free
    decrease = current.chi2 - candidate.chi2
    if extra <= 0 or decrease <= 0:
        return 1.0
    f = (decrease / extra) / (candidate.chi2 / candidate.dof)
    return float(stats.f.sf(f, extra, candidate.dof))


