"""Diagnosis: find what the geometric model lacks, name it, add it, check the rest.

diagnose(robot, samples, test, spot_sigma, joint_sigma) runs the engine, run(),
on laser spot data (SpotData). run(data, options) works on any data set that
gives a base measurement model, its candidate effects and its measurement-level
covariates (the Data protocol; sensors.analysis.SensorData for point and pose
sensors, which adds the sensor's scale as a candidate); candidates the base
model cannot carry (screen and lens effects without spots) are dropped. It runs:

1. the geometric fit (estimation.estimate_model, as every fit here). Noise
   components not given are estimated from its residual by maximum
   likelihood (noise_components) and the fit repeated with them: this is the
   reference noise model every later fit, test and whitening uses (an effect
   still in the residual inflates it, which only makes the tests cautious).
   Parameters the nominal geometry cannot separate stay fixed in every fit, as
   do those the data set fixes (data.fixed).
2. rounds of selection over the effect library (effects.catalog.candidates:
   each effect at each joint, length/covariate or target where the data can
   show it). A round screens every candidate with the linearised
   cross-validation (one Gauss-Newton solve per fold at the current fit,
   effect parameters starting at 0) and ranks them by held-out chi^2 (each
   held-out pose's residual whitened by the reference noise model); it fits
   the ``shortlist`` best jointly with the geometric errors and the effects
   already in (warm start) and cross-validates them with full fits per fold
   (the same seeded folds for every model). A candidate passes when
     - the fit improves: F test of the chi^2 decrease, F = (Δchi^2/Δk) /
       (chi^2/dof), Bonferroni-adjusted over the round's candidates, p < alpha
       (this carries the multiplicity of picking the best of many), and
     - the held-out error improves: one-sided paired t test over the
       calibration poses of the held-out chi^2 (current model minus
       candidate), p < alpha, and
     - its BIC = M ln(chi^2/M) + k ln M is lower (M measured values, k free
       parameters), and at least one of its parameters is identifiable.
   Of those that pass, the one with the lowest held-out chi^2 is added, unless
   another is not significantly worse (paired p >= 0.05) and has a lower BIC
   (the simpler explanation of the same held-out error; both are reported as
   indistinguishable). Rounds repeat until none passes or ``max_effects`` are in.
3. the verdict (verdict_noise, _evidence): structure tests of the final
   residual against every covariate (effects.residuals, Bonferroni-adjusted),
   weighted by the noise (components not given re-estimated from the final
   residual), and a test of the residual level where the noise is known: a
   chi^2 test when spot and joint sigma are both given, else a lack-of-fit F
   test against the scatter of repeated poses when the data has any, else
   none (and the evidence says so). "explained" when no test is significant
   at alpha, "structure remains" otherwise, with the strongest test as
   evidence.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Protocol, Sequence

import numpy as np
from scipy import stats

from laser_calib import __version__
from laser_calib.io.errors import InputError
from laser_calib.estimation.estimate import Estimate, EstimateOptions, estimate_model
from laser_calib.estimation.folds import kfold_labels
from laser_calib.effects.base import SPOT, Effect
from laser_calib.effects.catalog import candidates, effects_to_yaml, same_place
from laser_calib.effects.effect_model import EffectModel
from laser_calib.diagnosis.noise import noise_components, pure_error
from laser_calib.diagnosis.report import write_report
from laser_calib.diagnosis.structure import (Readings, Series, Test, pose_covariates, pose_responses, spot_covariates,
                                spot_responses, structure_tests)
from laser_calib.model.kinematics import forward
from laser_calib.measurement.base import MeasurementModel, NoiseModel, Residuals, whiten
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.model.robot_file import save_robot
from laser_calib.io.samples import Samples
from laser_calib.report.statistics import summary

EXPLAINED, STRUCTURE = "explained", "structure remains"
MIN_REPEAT_DOF = 8        # repeated-pose scatter with fewer degrees of freedom is not used
EQUIVALENT_P = 0.05       # held-out errors this close are "not significantly different"
SEPARABLE_CORRELATION = 0.99
MIN_TRAINING_RATIO = 3    # measured values per geometric error in a training fold, to select effects


@dataclass(frozen=True)
class DiagnoseOptions:
    """method 'lm' or 'ekf' for every fit; spot_sigma (m) / joint_sigma (rad)
    of the measurements, None when not known; folds of the cross-validation;
    alpha the significance level of every test; max_effects added at most;
    shortlist fitted per round; seed of the fold split and of LM restarts;
    restarts of LM for the geometric fit (estimation.EstimateOptions)."""

    method: str = "lm"
    spot_sigma: float | None = None
    joint_sigma: float | None = None
    folds: int = 5
    alpha: float = 0.01
    max_effects: int = 4
    shortlist: int = 4
    seed: int = 0
    restarts: int = 6

    def __post_init__(self):
        if self.spot_sigma is not None and not (math.isfinite(self.spot_sigma) and self.spot_sigma > 0):
            raise ValueError(f"spot sigma must be a positive number of metres, got {self.spot_sigma}")
        if self.joint_sigma is not None and not (math.isfinite(self.joint_sigma) and self.joint_sigma >= 0):
            raise ValueError(f"joint sigma must be a non-negative number of radians, got {self.joint_sigma}")
        if self.folds < 2:
            raise ValueError(f"cross-validation needs at least 2 folds, got {self.folds}")


@dataclass(frozen=True)
class Fitted:
    """A model fitted on the calibration poses: its estimate, held-out spot
    distances (P,L) in m from the cross-validation (NaN where no held-out
    prediction) and each pose's held-out chi^2 (P,) under the reference noise
    model, calibration distances (P,L), chi^2 under the reference noise model
    and BIC."""

    effects: tuple[Effect, ...]
    model: EffectModel
    estimate: Estimate
    cv: np.ndarray
    cv_chi2: np.ndarray
    cal: np.ndarray
    chi2: float
    n_values: int
    n_free: int

    @property
    def label(self) -> str:
        return " + ".join(["geometric"] + [e.label for e in self.effects])

    @property
    def dof(self) -> int:
        return max(self.n_values - self.n_free, 1)

    @property
    def bic(self) -> float:
        return self.n_values * math.log(max(self.chi2, 1e-300) / self.n_values) + self.n_free * math.log(self.n_values)


@dataclass(frozen=True)
class Ranked:
    """One candidate of a round: linearised held-out chi^2 per measured value
    (the ranking) and RMS (mm); for the shortlisted the fitted held-out chi^2
    per value and RMS (mm), the p of the fit test (Bonferroni-adjusted) and of
    the held-out test, the BIC change and the decision."""

    label: str
    linear_cv_chi2: float
    linear_cv_rms_mm: float
    cv_chi2: float | None = None
    cv_rms_mm: float | None = None
    p_fit: float | None = None
    p_heldout: float | None = None
    delta_bic: float | None = None
    outcome: str = "not shortlisted"


@dataclass(frozen=True)
class Stage:
    label: str
    fitted: Fitted
    test: np.ndarray | None  # (P_test, L) distances in m, NaN where not seen


@dataclass(frozen=True)
class NoiseInfo:
    """The noise the verdict uses (spot sigma m, joint sigma rad, each "given" or
    "estimated"), the degrees of freedom and pooled RMS per coordinate (m) of
    the scatter of repeated poses, and the test of the residual level when there
    is one: its name, statistic, dof and p."""

    spot_sigma: float
    spot_source: str
    joint_sigma: float
    joint_source: str
    repeat_dof: int = 0
    repeat_rms: float = 0.0
    level_test: str | None = None
    level_statistic: float | None = None
    level_dof: tuple[int, ...] | None = None
    level_p: float | None = None


@dataclass(frozen=True)
class Analysis:
    tests: list[Test]
    responses: list[Series]
    covariates: list[Series]


@dataclass(frozen=True)
class Diagnosis:
    robot: Robot
    samples: Readings
    test_samples: Readings | None
    stages: tuple[Stage, ...]
    rounds: tuple[tuple[Ranked, ...], ...]
    noise: NoiseInfo
    before: Analysis
    after: Analysis
    verdict: str
    evidence: str
    parameters: tuple[dict, ...]
    options: DiagnoseOptions
    wall_time: float
    merged: dict[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def final(self) -> Fitted:
        return self.stages[-1].fitted

    def calibrated_robot(self) -> Robot:
        """The robot with the geometric corrections and the ``effects:`` key
        (spot data: the base parameters are the D-H errors)."""
        final = self.final
        geometric, values = final.model.split(final.estimate.values)
        corrected = self.robot.with_errors(geometric)
        extra = {k: v for k, v in self.robot.extra.items() if k != "effects"}
        if final.effects:
            extra["effects"] = effects_to_yaml(final.effects, values)
        return replace(corrected, extra=extra)

    def to_json(self) -> dict:
        return {
            "robot": self.robot.name,
            "stages": [{"model": s.label, "cal": summary(s.fitted.cal, 1e3, "_mm"),
                        "cv": summary(s.fitted.cv, 1e3, "_mm"),
                        "test": None if s.test is None else summary(s.test, 1e3, "_mm"),
                        "parameters": int(s.fitted.estimate.identifiable.sum()),
                        "bic": s.fitted.bic, "spot_sigma_m": s.fitted.estimate.sigma,
                        "chi2": s.fitted.estimate.fit.chi2, "dof": s.fitted.estimate.fit.dof}
                       for s in self.stages],
            "effects": list(self.parameters),
            "not_identifiable": dict(self.merged),
            "verdict": self.verdict,
            "evidence": self.evidence,
            "noise": {"spot_sigma_m": self.noise.spot_sigma, "spot_sigma_source": self.noise.spot_source,
                      "joint_sigma_rad": self.noise.joint_sigma, "joint_sigma_source": self.noise.joint_source,
                      "repeated_pose_dof": self.noise.repeat_dof,
                      "repeated_pose_rms_m": self.noise.repeat_rms, "level_test": self.noise.level_test,
                      "level_statistic": self.noise.level_statistic,
                      "level_dof": None if self.noise.level_dof is None else list(self.noise.level_dof),
                      "level_p": self.noise.level_p},
            "structure": {"before": [_test_json(t) for t in self.before.tests[:10]],
                          "after": [_test_json(t) for t in self.after.tests[:10]]},
            "selection": [[{k: v for k, v in r.__dict__.items()} for r in ranking] for ranking in self.rounds],
            "options": {k: v for k, v in self.options.__dict__.items()},
            "wall_time_s": self.wall_time,
            "notes": list(self.notes),
        }


def _test_json(t: Test) -> dict:
    return {"response": t.response, "covariate": t.covariate, "F": t.f, "dof": list(t.dof), "p": t.p,
            "p_adjusted": t.p_adjusted, "eta2": t.eta2}


class Data(Protocol):
    """A calibration data set as the engine sees it (SpotData here,
    sensors.analysis.SensorData for point and pose sensors).

    robot and samples (readings q (P,N), stamp (P,), extra columns); fixed:
    parameter names of the base model held at their nominal values in every
    fit; base(): the base measurement model on all P poses (its subset(index)
    gives the folds); candidates(): the effects to select from (those the base
    model cannot carry are dropped by the engine); measured_values(): the
    number of measured values; series(): the measurement-level responses and
    covariates of the verdict's structure tests.
    """

    robot: Robot
    samples: Readings
    fixed: tuple[str, ...]

    def base(self) -> MeasurementModel: ...

    def candidates(self) -> list[Effect]: ...

    def measured_values(self) -> int: ...

    def series(self, model: EffectModel, x: np.ndarray, res: Residuals, noise: NoiseModel
               ) -> tuple[list[Series], list[Series]]: ...


@dataclass(frozen=True)
class SpotData:
    """Laser spots on the screen (SpotModel): the whole effect library, spot
    effects included; the spot-level series (effects.residuals)."""

    robot: Robot
    samples: Samples
    fixed: tuple[str, ...] = ()

    def base(self) -> SpotModel:
        return SpotModel(self.robot, self.samples)

    def candidates(self) -> list[Effect]:
        return candidates(self.robot, self.samples)

    def measured_values(self) -> int:
        return 2 * int(self.samples.seen.sum())

    def series(self, model: EffectModel, x: np.ndarray, res: Residuals, noise: NoiseModel
               ) -> tuple[list[Series], list[Series]]:
        errors, dq = model.offsets(x)
        q = self.samples.q if dq is None else self.samples.q + dq
        beams = forward(self.robot, q, errors).beams
        return spot_responses(res, noise, beams), spot_covariates(self.samples, beams)


def supports(base: MeasurementModel, effect: Effect) -> bool:
    """Whether the base model can carry the effect: spot effects need spots."""
    return effect.family != SPOT or isinstance(base, SpotModel)


def _distances(model: EffectModel, x: np.ndarray) -> np.ndarray:
    res = model.residuals(x, False)
    return np.where(res.valid, np.linalg.norm(res.r, axis=-1), np.nan)


class TooFewPoses(InputError):
    """A data limit, not a failure: too few poses to cross-validate (minimum_poses)."""

    def __init__(self, n_poses: int, needed: int):
        super().__init__("samples", f"{n_poses} poses, at least {needed} needed for the diagnosis")
        self.n_poses, self.needed = n_poses, needed


def minimum_poses(n_errors: int, values_per_pose: float, folds: int) -> int:
    """The fewest poses the diagnosis runs on: one per fold (estimation.folds.kfold_labels), and
    the smallest training fold (all poses but the largest fold) holding at least as many
    measured values as there are geometric errors, below which its estimate is refused
    (estimate_model)."""
    n = folds
    while values_per_pose > 0 and (n - math.ceil(n / folds)) * values_per_pose < n_errors:
        n += 1
    return n


class _Fitter:
    """Fits and cross-validates models on one calibration set, all with
    estimate_model, the same folds and one reference noise model: the noise
    given, with the components not given estimated once from the geometric
    fit (start)."""

    def __init__(self, data: Data, options: DiagnoseOptions):
        self.base = data.base()
        self.fixed = data.fixed
        self.options = options
        self.fit_options = EstimateOptions(method=options.method, spot_sigma=options.spot_sigma,
                                           joint_sigma=options.joint_sigma or 0.0, restarts=options.restarts,
                                           seed=options.seed, fixed=data.fixed)
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


def _rms_mm(distances: np.ndarray) -> float:
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


def select(fitter: _Fitter, pool: list[Effect], options: DiagnoseOptions
           ) -> tuple[list[Fitted], list[tuple[Ranked, ...]], list[list[str]]]:
    """The selection rounds (module docstring); returns the stages' fits, each
    round's ranking and, per added effect, the passed candidates the data could
    not tell from it."""
    current = fitter.start()
    stages = [current]
    rounds, alternatives = [], []
    while len(current.effects) < options.max_effects:
        remaining = [c for c in pool if not any(same_place(c, e) for e in current.effects)]
        if not remaining:
            break
        screened = fitter.screen(current, remaining)
        x0 = current.estimate.values
        fits, ranked = [], {}
        for effect, _, _ in screened[:options.shortlist]:
            fitted = fitter.fit(current.effects + (effect,), np.concatenate([x0, np.zeros(len(effect.params))]))
            p_fit = min(1.0, fit_test_p(current, fitted) * len(remaining))
            p_heldout = paired_p(current, fitted)
            delta_bic = fitted.bic - current.bic
            block = fitted.model.blocks[-1]
            identifiable = bool(fitted.estimate.identifiable[fitted.model.n_geometric:][block].any())
            failed = [text for text, bad in (("fit test", p_fit >= options.alpha),
                                             ("held-out test", p_heldout >= options.alpha),
                                             ("BIC", delta_bic >= 0), ("no identifiable parameter", not identifiable))
                      if bad]
            ranked[effect.label] = (_rms_mm(fitted.cv), fitted, p_fit, p_heldout, delta_bic,
                                    "passed" if not failed else "rejected: " + ", ".join(failed))
            if not failed:
                fits.append(fitted)
        chosen = None
        if fits:
            best = min(fits, key=lambda f: f.cv_chi2.sum())
            equivalent = [f for f in fits if f is best or paired_p(f, best) >= EQUIVALENT_P]
            chosen = min(equivalent, key=lambda f: f.bic)
            alternatives.append([f.effects[-1].label for f in equivalent if f is not chosen])
        table = []
        for effect, linear_chi2, linear_mse in screened:
            entry = Ranked(effect.label, linear_chi2, math.sqrt(linear_mse) * 1e3)
            if effect.label in ranked:
                rms, fitted, p_fit, p_heldout, delta_bic, outcome = ranked[effect.label]
                entry = replace(entry, cv_chi2=float(fitted.cv_chi2.sum() / fitted.n_values), cv_rms_mm=rms,
                                p_fit=p_fit, p_heldout=p_heldout, delta_bic=delta_bic,
                                outcome="added" if fitted is chosen else outcome)
            table.append(entry)
        rounds.append(tuple(table))
        if chosen is None:
            break
        current = chosen
        stages.append(current)
    return stages, rounds, alternatives


def verdict_noise(final: Fitted, samples: Readings, options: DiagnoseOptions) -> NoiseInfo:
    """The noise model of the verdict and the test of the residual level.

    Components not given are estimated by maximum likelihood from the final
    residual (noise_components), so the structure tests weight every pose by
    its real noise. The level can then be tested only against what was given
    or measured: a chi^2 test when both components are given, a lack-of-fit F
    test against the scatter of repeated poses (pure error) when there are
    any; otherwise it is not tested.
    """
    est = final.estimate
    res = final.model.residuals(est.values, True)
    m = int(res.valid.sum()) * res.r.shape[2]
    dof = max(m - int(est.identifiable.sum()), 1)
    spot, joint = noise_components(res, math.sqrt(m / dof), options.spot_sigma, options.joint_sigma)
    sources = ("given" if options.spot_sigma is not None else "estimated",
               "given" if options.joint_sigma is not None else "estimated")
    noise = NoiseModel(spot, joint)
    pure, repeat_dof, repeat_rms = pure_error(samples, res, noise)
    if options.spot_sigma is not None and options.joint_sigma is not None:
        r, _ = whiten(res, noise.whitener(res))
        chi2 = float(r @ r)
        return NoiseInfo(spot, sources[0], joint, sources[1], repeat_dof, repeat_rms, "chi^2", chi2, (dof,),
                         float(stats.chi2.sf(chi2, dof)))
    if repeat_dof >= MIN_REPEAT_DOF and dof > repeat_dof:
        # Lack of fit: the whitened residual beyond the pure error of repeated poses.
        r, _ = whiten(res, noise.whitener(res))
        f = ((float(r @ r) - pure) / (dof - repeat_dof)) / (pure / repeat_dof)
        return NoiseInfo(spot, sources[0], joint, sources[1], repeat_dof, repeat_rms, "lack-of-fit F", f,
                         (dof - repeat_dof, repeat_dof), float(stats.f.sf(f, dof - repeat_dof, repeat_dof)))
    return NoiseInfo(spot, sources[0], joint, sources[1], repeat_dof, repeat_rms)


def _analysis(data: Data, fitted: Fitted, noise: NoiseModel) -> Analysis:
    """Structure tests of a fit's residual: the pose-level responses and
    covariates of every measurement model, and the data's measurement-level ones."""
    model, x = fitted.model, fitted.estimate.values
    res = model.residuals(x, True)
    level_resp, level_cov = data.series(model, x, res, noise)
    resp = pose_responses(model.robot, res, noise) + level_resp
    cov = pose_covariates(model.robot, data.samples) + level_cov
    return Analysis(structure_tests(resp, cov), resp, cov)


def parameter_report(fitted: Fitted, alternatives: Sequence[Sequence[str]]) -> tuple[dict, ...]:
    """Per effect: name, where and each parameter's value and std, or, where the
    data cannot separate it from the geometric errors, no number and why; and
    the candidates that explained the data as well when it was added."""
    est, model = fitted.estimate, fitted.model
    cov = est.fit.covariance
    n_geo = model.n_geometric
    out = []
    for effect, block, others in zip(model.effects, model.blocks, alternatives):
        params = []
        for k, name in enumerate(effect.params):
            i = n_geo + block.start + k
            entry = {"name": name, "value": None, "std": None, "unit": effect.units[k]}
            if not est.identifiable[i]:
                entry["note"] = est.identifiability.merged.get(model.names[i], "not identifiable")
            else:
                std = float(est.std[i])
                geo = np.flatnonzero(est.identifiable[:n_geo])
                corr = cov[i, geo] / np.sqrt(cov[i, i] * np.diag(cov)[geo])
                worst = int(np.argmax(np.abs(corr))) if geo.size else -1
                if std > model.scales[i] and worst >= 0 and abs(corr[worst]) > SEPARABLE_CORRELATION:
                    entry["note"] = (f"not separable from {model.names[geo[worst]]} (correlation "
                                     f"{corr[worst]:+.4f}, std {std / model.scales[i]:.3g} x its scale)")
                else:
                    entry["value"], entry["std"] = float(est.values[i]), std
            params.append(entry)
        item = {"name": effect.kind, "where": effect.where, "title": effect.title, "parameters": params,
                "indistinguishable_from": list(others)}
        if hasattr(effect, "covariate"):
            item["covariate"] = effect.covariate
        out.append(item)
    return tuple(out)


def _evidence(after: Analysis, noise: NoiseInfo, alpha: float) -> tuple[str, str]:
    tests = after.tests
    structure = bool(tests) and tests[0].p_adjusted < alpha
    level_fail = noise.level_p is not None and noise.level_p < alpha
    parts = []
    if tests:
        parts.append(("Structure: " if structure else "No covariate explains the residual; strongest: ")
                     + tests[0].sentence() + f", {len(tests)} tests.")
    sources = {"given": "given", "estimated": "estimated from the residual by maximum likelihood"}
    sigma_text = (f"spot sigma {noise.spot_sigma * 1e3:.3g} mm {sources[noise.spot_source]}, joint-reading sigma "
                  f"{np.degrees(noise.joint_sigma):.3g} deg {sources[noise.joint_source]}")
    if noise.level_test == "chi^2":
        parts.append(f"Level: chi^2 = {noise.level_statistic:.1f} on {noise.level_dof[0]} dof (ratio "
                     f"{noise.level_statistic / noise.level_dof[0]:.2f}, p = {noise.level_p:.2g}) with {sigma_text}"
                     + (": the residual exceeds the noise." if level_fail else "."))
    elif noise.level_test is not None:
        parts.append(f"Level: lack-of-fit F = {noise.level_statistic:.3g} on {noise.level_dof[0]}, "
                     f"{noise.level_dof[1]} dof against the scatter of repeated poses ({noise.repeat_rms * 1e3:.3g} "
                     f"mm RMS per coordinate; p = {noise.level_p:.2g})"
                     + (": the residual exceeds the noise" if level_fail else "") + f"; {sigma_text}.")
    else:
        parts.append(f"The residual level is not tested: the noise is not fully given and there are "
                     f"{'too few' if noise.repeat_dof else 'no'} repeated poses ({sigma_text}).")
    return (STRUCTURE if structure or level_fail else EXPLAINED), " ".join(parts)


def write_outputs(diagnosis: Diagnosis, out_dir: str | Path, sources: dict[str, str | None] | None = None) -> dict:
    """diagnosis.json, robot_calibrated.yaml (geometric corrections and the
    ``effects:`` key, docs/effects.md) and report.md with its plots into
    out_dir; returns the JSON dictionary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = diagnosis.to_json()
    result["inputs"] = sources or {}
    (out / "diagnosis.json").write_text(json.dumps(result, indent=2))
    unseparated = [f"{e['name']} ({e['where']}) {p['name']}: {p['note']}" for e in result["effects"]
                   for p in e["parameters"] if p["value"] is None]
    merged = "; ".join(f"{k}: {v}" for k, v in diagnosis.merged.items())
    header = (f"Calibrated by laser_calib {__version__} diagnose from {len(diagnosis.samples)} poses: "
              f"{diagnosis.final.label}. Verdict: {diagnosis.verdict}."
              + (f"\nNot identifiable, held at nominal: {merged}" if merged else "")
              + "".join(f"\nEffect parameter not separable from the geometric errors (the model uses the "
                        f"value, which has no meaning alone): {u}" for u in unseparated))
    save_robot(diagnosis.calibrated_robot(), out / "robot_calibrated.yaml", header=header)
    write_report(diagnosis, result, out)
    return result


def diagnose(robot: Robot, samples: Samples, test: Samples | None = None, spot_sigma: float | None = None,
             joint_sigma: float | None = None, options: DiagnoseOptions | None = None) -> Diagnosis:
    """Diagnose, select and add effects (module docstring). spot_sigma (m) and
    joint_sigma (rad) override those of ``options``. ValueError (InputError) on
    bad input."""
    options = options or DiagnoseOptions()
    options = replace(options, spot_sigma=spot_sigma if spot_sigma is not None else options.spot_sigma,
                      joint_sigma=joint_sigma if joint_sigma is not None else options.joint_sigma)
    for name, s in (("samples", samples), ("test", test)):
        if s is not None and s.n_joints != robot.n_joints:
            raise InputError(name, f"{s.n_joints} joint columns but robot '{robot.name}' has {robot.n_joints} joints")
    missing = [c for c in samples.extra if test is not None and c not in test.extra]
    if missing:
        raise InputError("test", f"no column '{missing[0]}' (the calibration samples have it, and an effect may "
                                 "follow it)")
    notes = []
    if "effects" in robot.extra:
        notes.append("the input robot's effects key was not used: the diagnosis starts from the geometric model")
    return run(SpotData(robot, samples), options, None if test is None else SpotData(robot, test), tuple(notes))


def run(data: Data, options: DiagnoseOptions, test: Data | None = None, notes: tuple[str, ...] = ()) -> Diagnosis:
    """The diagnosis engine (module docstring) on any data set: the geometric
    fit of data.base(), selection over the candidates the base model supports,
    the verdict; test (the same kind of data) predicted at every stage."""
    start = time.perf_counter()
    notes = list(notes)
    n_poses = len(data.samples.q)
    needed = minimum_poses(len(data.base().names) - len(data.fixed), data.measured_values() / max(n_poses, 1),
                           options.folds)
    if n_poses < needed:
        raise TooFewPoses(n_poses, needed)
    fitter = _Fitter(data, options)
    pool = [c for c in data.candidates() if supports(fitter.base, c)]
    training_values = data.measured_values() * (options.folds - 1) / options.folds
    n_errors = len(fitter.base.names) - len(data.fixed)
    needed = MIN_TRAINING_RATIO * n_errors
    if training_values < needed:
        # With a training fold barely determining the geometric errors, held-out
        # errors are dominated by the fold's own ill-conditioning and the selection
        # adds effects on chance (seen: a 0.17 deg 'backlash' on 20 effect-free poses).
        per_pose = data.measured_values() / max(len(data.samples.q), 1)
        notes.append(f"too few poses to select effects: a training fold holds {training_values:.0f} measured "
                     f"values for {n_errors} geometric errors (needs {needed:.0f}, about "
                     f"{math.ceil(needed * options.folds / (options.folds - 1) / max(per_pose, 1e-9))} poses); "
                     "only the geometric model and the residual tests are reported")
        pool = []
    fits, rounds, alternatives = select(fitter, pool, options)

    stages = []
    for fitted in fits:
        test_d = None if test is None else _distances(EffectModel(test.base(), fitted.effects),
                                                      fitted.estimate.values)
        stages.append(Stage(fitted.label, fitted, test_d))
    final = fits[-1]
    noise = verdict_noise(final, data.samples, options)
    noise_model = NoiseModel(noise.spot_sigma, noise.joint_sigma)
    before, after = _analysis(data, fits[0], noise_model), _analysis(data, final, noise_model)
    verdict, evidence = _evidence(after, noise, options.alpha)
    merged = {**fitter.merged, **final.estimate.identifiability.merged}
    return Diagnosis(data.robot, data.samples, None if test is None else test.samples, tuple(stages), tuple(rounds),
                     noise, before, after, verdict, evidence, parameter_report(final, alternatives), options,
                     time.perf_counter() - start, merged, tuple(notes))
