"""Fits and cross-validation of candidate models on one calibration set."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Sequence

import numpy as np
from scipy import stats

from laser_calib.diagnosis.data import Data
from laser_calib.diagnosis.options import DiagnoseOptions
from laser_calib.diagnosis.result import Fitted
from laser_calib.effects.base import Effect
from laser_calib.effects.effect_model import EffectModel
from laser_calib.estimation.estimate import Estimate, EstimateOptions, estimate_model
from laser_calib.estimation.failures import FitMovedBeams, NoSpotToFit
from laser_calib.estimation.folds import kfold_labels
from laser_calib.estimation.identifiability import TooFewValues
from laser_calib.estimation.problem import pose_blocks, residuals_at
from laser_calib.measurement.base import NoiseModel, count_values, whiten
from laser_calib.measurement.noise_components import noise_components

ESTIMATED_SIGMA = "the diagnosis estimated from the geometric fit's residual"  # no spot sigma given (Fitter.start)
FINAL_SIGMA = "the diagnosis estimated from the final model's residual"  # no spot sigma given (Fitter.at_noise)


def distances(model: EffectModel, x: np.ndarray) -> np.ndarray:
    res = model.residuals(x, False)
    return np.where(res.valid, np.linalg.norm(res.r, axis=-1), np.nan)


def warm_estimate(model: EffectModel, options: EstimateOptions, x0: np.ndarray) -> Estimate:
    """estimate_model from x0, the values of a fit that started at the nominal model (0).
    When x0 leaves no spot, or too few, to fit but the nominal model's beams meet the
    screen at enough and at least twice as many, that fit moved the beams off it:
    FitMovedBeams, not the data's counts (a beam or two grazing the screen's edge can
    differ between honest fits, and then the data's count is the reason)."""
    try:
        return estimate_model(model, options, None, x0)
    except (NoSpotToFit, TooFewValues) as exc:
        values, needed = (exc.n_values, exc.n_free) if isinstance(exc, TooFewValues) else (0, 0)
        nominal = residuals_at(model, np.zeros_like(x0))
        if count_values(nominal) > max(needed, 2 * values):
            raise FitMovedBeams(int(nominal.valid.sum()), values // nominal.r.shape[2], needed) from None
        raise


class Fitter:
    """Fits and cross-validates models on one calibration set, all with
    estimate_model, the same folds and one reference noise model: the noise
    given, with the components not given estimated once from the geometric
    fit (start)."""

    def __init__(self, data: Data, options: DiagnoseOptions, stage: str = "selection"):
        self.base = data.base()
        self.fixed = data.fixed
        self.options = options
        # Plain least squares: the structure the diagnosis looks for shows as large
        # residuals, which the robust rule would weigh down (the effects bench was
        # measured so); gross outliers are the estimate's to reject first.
        self.fit_options = EstimateOptions(method=options.method, spot_sigma=options.spot_sigma,
                                           joint_sigma=options.joint_sigma or 0.0, restarts=options.restarts,
                                           seed=options.seed, fixed=data.fixed, robust=False, noise_checks=False)
        self.fold = kfold_labels(len(data.samples.q), options.folds, options.seed)
        self.reference = NoiseModel(options.spot_sigma or 1.0, options.joint_sigma or 0.0)
        self.merged: dict[str, str] = {}
        self.progress = options.progress
        self.stage = stage  # what the fits are for, on the progress line

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
        # with no spot sigma given, every later fit's warnings would call this estimate given
        source = self.fit_options.spot_sigma_source if self.options.spot_sigma is not None else ESTIMATED_SIGMA
        self.fit_options = replace(self.fit_options, spot_sigma=spot, joint_sigma=joint, spot_sigma_source=source)
        self.reference = NoiseModel(spot, joint)
        return self.fit((), first.values)

    def at_noise(self, fitted: Fitted, spot_sigma: float, joint_sigma: float) -> Fitted:
        """``fitted`` refitted with the noise components not given at their estimate from its own
        residual (verdict.verdict_noise): the final model's values, standard deviations and what it
        holds. The reference noise, estimated from the geometric fit, holds what the effects took out
        since (a strong periodic term: 0.91 mm spot sigma against 0.32 from the final residual), and
        the final stds were as many times too wide. Its scores (chi^2, held-out errors) stay those
        of the reference noise model, as every other stage's."""
        source = self.fit_options.spot_sigma_source if self.options.spot_sigma is not None else FINAL_SIGMA
        options = replace(self.fit_options, spot_sigma=spot_sigma, joint_sigma=joint_sigma, spot_sigma_source=source,
                          restarts=0, noise_checks=self.options.joint_sigma is not None)   # the final fit: a given sigma judged
        return replace(fitted, estimate=warm_estimate(fitted.model, options, fitted.estimate.values))

    def on(self, data: Data, stage: str) -> "Fitter":
        """A Fitter on other poses of the same session (all of them, after a selection on
        part of them) with this one's reference noise model and fixed parameters: no new start."""
        other = Fitter(data, self.options, stage)
        other.fit_options, other.reference, other.merged = self.fit_options, self.reference, dict(self.merged)
        return other

    def estimate(self, effects: tuple[Effect, ...], x0: np.ndarray) -> tuple[EffectModel, Estimate]:
        """The geometric errors plus ``effects`` fitted on all poses from the warm start x0,
        without LM restarts (x0 is a converged fit: the first geometric fit had them)."""
        model = EffectModel(self.base, effects)
        return model, warm_estimate(model, replace(self.fit_options, restarts=0), x0)

    def fit(self, effects: tuple[Effect, ...], x0: np.ndarray) -> Fitted:
        """Fit and cross-validate the geometric errors plus ``effects`` from the
        warm start x0 (estimate). Each fold starts from the full fit's
        minimum (a fold leaves out a fifth of the poses, so its minimum is
        near: LM takes a few steps, not a fit from scratch)."""
        model, est = self.estimate(effects, x0)
        options = replace(self.fit_options, restarts=0)
        label = f"{self.stage}: " + " + ".join(["geometric"] + [e.label for e in effects])
        self.report(1, label)
        chi2, cal, n_values = self.scored(model, est.values)
        cv = np.full(cal.shape, np.nan)
        cv_chi2 = np.zeros(len(cv))
        for k in range(self.options.folds):
            held = self.fold == k
            train = warm_estimate(model.subset(~held), options, est.values)
            cv_chi2[held], cv[held], _ = self.scored(model.subset(held), train.values)
            self.report(k + 2, label)
        return Fitted(effects, model, est, cv, cv_chi2, cal, float(chi2.sum()), n_values,
                      effective_parameters(model, est))

    def report(self, done: int, note: str) -> None:
        """Progress: ``done`` of the folds + 1 fits of one model."""
        if self.progress is not None:
            self.progress(done, self.options.folds + 1, note)

    def scored(self, model: EffectModel, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """Each pose's chi^2 (P,) under the reference noise model and spot distances
        (P,L) in m (NaN where not measured) at x, and the measured values; by
        blocks of poses (the Jacobian, for the joint-noise weights, of all poses
        at once would grow with them)."""
        chi2, dist, n_values = [], [], 0
        for _, block in pose_blocks(model):
            # A fold's fit of a candidate the fold cannot pin down may run off to sizes at
            # which the model overflows: its prediction is infinitely wrong (paired_p
            # rejects it), not a warning on the console.
            with np.errstate(over="ignore", invalid="ignore"):
                res = block.residuals(x, True)
                white = np.einsum("pij,pj->pi", self.reference.whitener(res), res.r.reshape(len(res.r), -1))
                pose_chi2 = (white ** 2).sum(axis=1)
                norm = np.linalg.norm(res.r, axis=-1)
            chi2.append(np.where(np.isfinite(pose_chi2), pose_chi2, np.inf))
            dist.append(np.where(res.valid, np.where(np.isfinite(norm), norm, np.inf), np.nan))
            n_values += count_values(res)
        return np.concatenate(chi2), np.concatenate(dist), n_values

    def screen(self, current: Fitted, pool: Sequence[Effect]) -> list[tuple[Effect, float, float]]:
        """Linearised cross-validation of the current model plus each candidate:
        (effect, held-out chi^2 per measured value, held-out MSE in m^2), best first.

        The candidates are evaluated in joint models at the current fit with
        their parameters at 0; per fold, one least-squares solve in the current
        model's free parameters and the candidate's, on the training poses'
        whitened rows, predicts the held-out poses' rows. The rows are never
        stacked: per fold and block of poses they are folded into the
        triangular factor R of [J | r] (QR), which has J's singular values, so
        the solve on R's columns is the one on J's; the candidates go in
        groups whose effect bases (per pose, the joint models hold them) fit
        in SCREEN_BYTES. A penalised effect is screened at each of its
        penalties (Effect.variants, the prior's rows appended to the solve) and
        the best is returned: its penalty is chosen by this held-out error.
        """
        n_current = len(current.model.names)
        kept = list(np.flatnonzero(current.estimate.identifiable))
        out = []
        for group in screen_groups(current, pool):
            model = EffectModel(self.base, current.effects + tuple(group))
            x = np.concatenate([current.estimate.values, np.zeros(len(model.names) - n_current)])
            white, raw, rows, n_values, n_units = self._factors(model, x)
            # per fold: R of the training rows (all other folds), and the training rows' count
            train = [(np.linalg.qr(np.vstack(white[:k] + white[k + 1:]), mode="r"),
                      rows - rows * int((self.fold == k).sum()) // len(self.fold)) for k in range(len(white))]
            for effect, block in zip(group, model.blocks[len(current.effects):]):
                columns = kept + list(range(model.n_geometric + block.start, model.n_geometric + block.stop))
                scores = []
                for variant in effect.variants():
                    # a prior's rows: x_j / sigma_j in the scaled parameters, toward 0 (the start)
                    prior = np.zeros(len(effect.params)) if variant.prior is None else 1.0 / variant.prior
                    rows = np.zeros((len(columns), len(columns) + 1))
                    rows[len(kept):, len(kept):-1] = np.diag(prior * variant.scales)
                    chi2 = squared = 0.0
                    for k, (factor, train_rows) in enumerate(train):
                        # rcond as lstsq's default on the stacked training rows
                        rcond = np.finfo(float).eps * max(train_rows, len(columns))
                        system = np.vstack([factor[:, columns + [-1]], rows])
                        if not np.isfinite(system).all():   # a shape over spots all in one place: no fit
                            break
                        step = np.linalg.lstsq(system[:, :-1], system[:, -1], rcond=rcond)[0]
                        chi2 += held_sum(white[k], columns, step)
                        squared += held_sum(raw[k], columns, step)
                    else:
                        scores.append((variant, chi2 / max(n_values, 1), squared / max(n_units, 1)))
                if scores:   # else the data give this effect nothing to be fitted on
                    out.append(min(scores, key=lambda item: item[1]))
        return sorted(out, key=lambda item: item[1])

    def _factors(self, model: EffectModel, x: np.ndarray) -> tuple[list, list, int, int, int]:
        """Per fold, R of the whitened [J | r] and of the raw [J | r] (valid values
        only), J in scaled parameters; all rows, measured values and measured units."""
        n = len(model.names)
        white = [np.zeros((0, n + 1)) for _ in range(self.options.folds)]
        raw = [np.zeros((0, n + 1)) for _ in range(self.options.folds)]
        rows = n_values = n_units = 0
        for index, block in pose_blocks(model, SCREEN_POSES):
            res = block.residuals(x, True)
            r_white, jac_white = whiten(res, self.reference.whitener(res))
            n_poses, per_pose = res.r.shape[0], res.r.shape[1] * res.r.shape[2]
            valid = np.repeat(res.valid, res.r.shape[2], axis=1).ravel()
            raw_rows = np.where(valid[:, None], np.hstack([res.jac.reshape(-1, n), res.r.reshape(-1, 1)]), 0.0)
            white_rows = np.hstack([jac_white, r_white[:, None]])
            fold = np.repeat(self.fold[index], per_pose)
            for k in range(self.options.folds):
                white[k] = np.linalg.qr(np.vstack([white[k], white_rows[fold == k]]), mode="r")
                raw[k] = np.linalg.qr(np.vstack([raw[k], raw_rows[fold == k]]), mode="r")
            rows += n_poses * per_pose
            n_values += int(valid.sum())
            n_units += int(res.valid.sum())
        scale = np.append(model.scales, 1.0)
        return [w * scale for w in white], [r * scale for r in raw], rows, n_values, n_units


# Bytes of effect bases a joint model of the screen may hold (EffectModel keeps
# them per pose for all its parameters): at 10,000 poses of the 7-DOF arm every
# candidate fits in one model; at 200,000 they go in groups.
SCREEN_BYTES = 256 * 2 ** 20
SCREEN_POSES = 4096  # poses per block of the screen's joint models (their Jacobians, ~15 MB)


def screen_groups(current: Fitted, pool: Sequence[Effect]) -> list[list[Effect]]:
    """The pool in groups (in order) whose joint model's bases stay within SCREEN_BYTES."""
    model = current.model
    per_parameter = 8 * len(model.samples.q) * (model.samples.q.shape[1] + model.n_geometric)
    room = max(SCREEN_BYTES // per_parameter - model.n_effect_params, 1)
    groups, size = [[]], 0
    for effect in pool:
        if groups[-1] and size + len(effect.params) > room:
            groups.append([])
            size = 0
        groups[-1].append(effect)
        size += len(effect.params)
    return [g for g in groups if g]


def effective_parameters(model: EffectModel, est: Estimate) -> float:
    """The free parameters a fit spends: their count, less what the priors
    (penalised effects) hold, tr((J^T J + Q)^-1 J^T J) = k - sum_j Q_jj cov_jj
    for the diagonal prior precision Q (the effective degrees of freedom of a
    penalised fit)."""
    free = est.identifiable
    prior = model.prior_sigma
    if prior is None:
        return float(free.sum())
    held = free & np.isfinite(prior)
    return float(free.sum() - np.sum(np.diag(est.fit.covariance)[held] / prior[held] ** 2))


def held_sum(factor: np.ndarray, columns: list[int], step: np.ndarray) -> float:
    """||r - J[:, columns] step||^2 of the rows whose factor R of [J | r] is ``factor``."""
    return float(np.sum((factor[:, -1] - factor[:, columns] @ step) ** 2))


def paired_p(current: Fitted, candidate: Fitted) -> float:
    """One-sided paired t test over the calibration poses that the candidate's
    mean held-out chi^2 (each pose's held-out residual whitened by the
    reference noise model) is smaller than the current model's. Whitening puts
    poses whose spots the joint noise moves a lot (long beams, grazing
    incidence) on the same footing as the rest, which keeps the differences'
    tails short enough for the t test; it tests the mean, which is what the
    held-out error is (a rank test misses improvements concentrated in part
    of the poses)."""
    if not np.isfinite(candidate.cv_chi2).all():
        return 1.0  # a fold's fit diverged (Fitter.scored): its held-out error is not smaller
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


