"""The selection rounds over the effect library and the report of the
chosen effects' parameters.

Besides the statistical rules (engine docstring), a candidate is judged
physically: a sensor-side effect whose fitted value lies outside what its
sensor can do (effects.bounds) by more than its standard error is rejected,
and so is one none of whose parameters can be reported (each is not
identifiable or not separable from another parameter). The screen is the
library's quadratic or, where the held-out error of the folds says it
predicts better, a penalised spline whose penalty that error chose
(screen_fit). Candidates the data cannot tell apart (held-out errors not
significantly different) are reported as the group: the figures use the one
with the lowest BIC, the verdict names none of them as the cause
(ambiguous_verdict).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Sequence

import numpy as np
from scipy import stats

from laser_calib.diagnosis.fitter import Fitter, fit_test_p, paired_p, rms_mm
from laser_calib.diagnosis.options import (EQUIVALENT_P, EXPLAINED, SEPARABLE_CORRELATION, UNDETERMINED,
                                           DiagnoseOptions)
from laser_calib.diagnosis.result import Fitted, Ranked
from laser_calib.effects.base import Effect
from laser_calib.effects.bounds import limit_of
from laser_calib.effects.catalog import same_place
from laser_calib.effects.screen import ScreenShape, Surface
from laser_calib.effects.screen_spline import SURFACES, ScreenSpline

# A parameter this correlated with another free one has no value of its own to
# report, however small its standard error: a slight misfit moves it along the other.
UNREPORTABLE_CORRELATION = 0.999
# Distinct spots a screen spline needs beyond its null space: fewer, and the screen is the quadratic.
MIN_SPLINE_SPOTS = 20


def select(fitter: Fitter, pool: list[Effect], options: DiagnoseOptions
           ) -> tuple[list[Fitted], list[tuple[Ranked, ...]], list[list[str]]]:
    """The selection rounds (module docstring); returns the stages' fits, each
    round's ranking and, per added effect, the passed candidates the data could
    not tell from it."""
    current = fitter.start()
    stages = [current]
    rounds, alternatives = [], []
    pool = [screen_candidate(fitter, c) for c in pool]
    while len(current.effects) < options.max_effects:
        remaining = [c for c in pool if not any(same_place(c, e) or isinstance(c, Surface) and isinstance(e, Surface)
                                                for e in current.effects)]
        if not remaining:
            break
        screened = fitter.screen(current, remaining)
        fits, ranked = [], {}
        for effect, _, _ in screened[:options.shortlist]:
            fitted = candidate_fit(fitter, current, effect, options.alpha)
            p_fit = min(1.0, fit_test_p(current, fitted) * len(remaining))
            p_heldout = paired_p(current, fitted)
            delta_bic = fitted.bic - current.bic
            failed = [text for text, bad in (("fit test", p_fit >= options.alpha),
                                             ("held-out test", p_heldout >= options.alpha),
                                             ("BIC", delta_bic >= 0)) if bad]
            failed += physical_objections(fitted, fitter.base.robot)
            ranked[effect.label] = (rms_mm(fitted.cv), fitted, p_fit, p_heldout, delta_bic,
                                    "passed" if not failed else "rejected: " + ", ".join(failed))
            if not failed:
                fits.append(fitted)
        chosen = None
        if fits:
            best = min(fits, key=lambda f: f.cv_chi2.sum())
            equivalent = [f for f in fits if f is best or paired_p(f, best) >= EQUIVALENT_P]
            # The figures need one model: of a group the data cannot tell apart the one
            # with the lowest BIC, the fewest parameters for the same held-out error.
            chosen = min(equivalent, key=lambda f: f.bic)
            alternatives.append([f.effects[-1].label for f in equivalent if f is not chosen])
        table = []
        for effect, linear_chi2, linear_mse in screened:
            entry = Ranked(effect.label, linear_chi2, math.sqrt(linear_mse) * 1e3)
            if effect.label in ranked:
                rms, fitted, p_fit, p_heldout, delta_bic, outcome = ranked[effect.label]
                entry = replace(entry, label=fitted.effects[-1].label,
                                cv_chi2=float(fitted.cv_chi2.sum() / fitted.n_values), cv_rms_mm=rms,
                                p_fit=p_fit, p_heldout=p_heldout, delta_bic=delta_bic,
                                outcome="added" if fitted is chosen else outcome)
            table.append(entry)
        rounds.append(tuple(table))
        if chosen is None:
            break
        current = chosen
        stages.append(current)
    return stages, rounds, alternatives


def candidate_fit(fitter: Fitter, current: Fitted, effect: Effect, alpha: float) -> Fitted:
    """The current model plus the candidate, fitted from the current fit (the
    candidate's parameters at 0); the screen as the surface its held-out error chooses."""
    if isinstance(effect, ScreenSpline):
        return screen_fit(fitter, current, effect, alpha)
    return extended_fit(fitter, current, effect)


def extended_fit(fitter: Fitter, current: Fitted, effect: Effect) -> Fitted:
    """The current model plus ``effect``, fitted from the current fit (its parameters at 0)."""
    return fitter.fit(current.effects + (effect,),
                      np.concatenate([current.estimate.values, np.zeros(len(effect.params))]))


def screen_candidate(fitter: Fitter, effect: Effect) -> Effect:
    """The pool's screen: the library's quadratic becomes the spline over the
    calibration spots (its null space is that quadratic), so that the screening
    sees any smooth shape; the quadratic where the spots are too few for a spline."""
    if not isinstance(effect, ScreenShape):
        return effect
    spots = fitter.base.samples.spots
    distinct = len(np.unique(spots[~np.isnan(spots).any(axis=-1)], axis=0))
    return ScreenSpline.make(spots, camera=effect.camera) if distinct > MIN_SPLINE_SPOTS else effect


def screen_fit(fitter: Fitter, current: Fitted, spline: ScreenSpline, alpha: float) -> Fitted:
    """The screen: the library's quadratic, or the spline of the penalty order
    (or Matern length) and smoothing the linearised held-out error chooses
    (Fitter.screen over SURFACES and SMOOTHINGS) where its held-out chi^2 over the poses is lower in
    total and significantly lower than the quadratic's by its mean or by its
    ranks (paired_p or ranked_p below alpha / 2: a screen's gain often lies in
    a few poses at the edge of the spots, which the rank test misses, or in
    most poses by a little, which the mean's tails hide): a quadratic screen
    stays the library's effect, with its 5 parameters."""
    robot = fitter.base.robot
    quadratic = extended_fit(fitter, current, ScreenShape(robot.screen.half_y, robot.screen.half_z,
                                                          camera=spline.camera))
    surfaces = [spline.with_order(order, length) for order, length in SURFACES]
    chosen, _, _ = fitter.screen(current, surfaces)[0]
    fitted = extended_fit(fitter, current, chosen)
    significant = min(paired_p(quadratic, fitted), ranked_p(quadratic, fitted)) < alpha / 2
    return fitted if significant and fitted.cv_chi2.sum() < quadratic.cv_chi2.sum() else quadratic


def ranked_p(lower: Fitted, higher: Fitted) -> float:
    """One-sided Wilcoxon signed-rank p over the calibration poses that the
    richer model's held-out chi^2 is smaller. Not the mean (paired_p): a
    surface's held-out error is dominated by the few poses of a fold beyond
    the spots the other folds cover, where every surface extrapolates (at
    grazing beams, by many times the surface's error); the richer surface is
    the one that predicts most poses better."""
    difference = lower.cv_chi2 - higher.cv_chi2
    if np.count_nonzero(difference) < 6:
        return 1.0
    return float(stats.wilcoxon(difference, alternative="greater").pvalue)


def physical_objections(fitted: Fitted, robot) -> list[str]:
    """Why the last effect of a fit is not physical: none of its parameters can
    be reported, or a sensor-side value outside what its sensor can do (effects.bounds)
    by more than its standard error."""
    model, est = fitted.model, fitted.estimate
    effect, block = model.effects[-1], model.blocks[-1]
    start = model.n_geometric + block.start
    notes = [note for note, _, _ in (parameter_entry(fitted, start + k) for k in range(len(effect.params)))]
    if all(note is not None for note in notes):
        return ["no parameter separable (" + notes[0] + ")"]
    limit = limit_of(effect, robot)
    if limit is None:
        return []
    values, stds = est.values[start:start + len(effect.params)], est.std[start:start + len(effect.params)]
    outside = [k for k in range(len(values)) if abs(values[k]) - limit.limit > stds[k]]
    if not outside:
        return []
    k = max(outside, key=lambda k: abs(values[k]) / limit.limit)
    name = effect.params[k] if len(effect.params) > 1 else ""
    return [f"{effect.title}{' ' + name if name else ''} {limit.describe(float(values[k]))}"]


def parameter_entry(fitted: Fitted, i: int) -> tuple[str | None, float | None, float | None]:
    """(note, value, std) of parameter i of a fit: no value and a note saying why
    where it is not identifiable, or not separable from another free parameter
    (correlation above UNREPORTABLE_CORRELATION, or above SEPARABLE_CORRELATION
    with a standard error beyond its scale); else the value and its std."""
    est, model = fitted.estimate, fitted.model
    if not est.identifiable[i]:
        return est.identifiability.merged.get(model.names[i], "not identifiable"), None, None
    cov = est.fit.covariance
    std = float(est.std[i])
    others = np.array([j for j in np.flatnonzero(est.identifiable) if j != i], int)
    if others.size:
        corr = cov[i, others] / np.sqrt(cov[i, i] * np.diag(cov)[others])
        worst = int(np.argmax(np.abs(corr)))
        if abs(corr[worst]) > UNREPORTABLE_CORRELATION or (
                std > model.scales[i] and abs(corr[worst]) > SEPARABLE_CORRELATION):
            return (f"not separable from {model.names[others[worst]]} (correlation {corr[worst]:+.4f}, std "
                    f"{std / model.scales[i]:.3g} x its scale)"), None, None
    return None, float(est.values[i]), std


def parameter_report(fitted: Fitted, alternatives: Sequence[Sequence[str]]) -> tuple[dict, ...]:
    """Per effect: name, where and each parameter's value and std, or, where the
    data cannot separate it from the other parameters, no number and why; the
    candidates that explained the data as well when it was added and, with
    any, ``determined`` false and the group named ("A or B")."""
    model = fitted.model
    out = []
    for effect, block, others in zip(model.effects, model.blocks, alternatives):
        params = []
        for k, name in enumerate(effect.params):
            note, value, std = parameter_entry(fitted, model.n_geometric + block.start + k)
            entry = {"name": name, "value": value, "std": std, "unit": effect.units[k]}
            if note is not None:
                entry["note"] = note
            params.append(entry)
        item = {"name": effect.kind, "where": effect.where, "title": effect.title, "parameters": params,
                "indistinguishable_from": list(others), "determined": not others}
        if others:
            item["group"] = " or ".join([effect.label] + list(others)) + ": the data cannot tell them apart"
        if hasattr(effect, "covariate"):
            item["covariate"] = effect.covariate
        if isinstance(effect, ScreenSpline):
            item["penalty_order"], item["smoothing_m"] = effect.penalty_order, effect.smoothing
            if effect.length is not None:
                item["matern_length"] = effect.length   # box half sizes
            # what the data saw of the screen: beyond it the surface is extrapolated
            item["known_over_m"] = {"y": [effect.centre_y - effect.half_y, effect.centre_y + effect.half_y],
                                    "z": [effect.centre_z - effect.half_z, effect.centre_z + effect.half_z]}
        out.append(item)
    return tuple(out)


def ambiguous_verdict(verdict: str, evidence: str, parameters: Sequence[dict]) -> tuple[str, str]:
    """The verdict once the groups the data cannot tell apart are counted: an
    effect that is one of such a group is not the explanation, so "explained"
    becomes "undetermined"; the evidence names each group and which model the
    figures use."""
    groups = [p for p in parameters if not p["determined"]]
    if not groups:
        return verdict, evidence
    said = " ".join(f"{p['group']} (held-out errors not significantly different); the figures use "
                    f"{p['name']} ({p['where']}), the lowest BIC." for p in groups)
    if verdict == EXPLAINED:
        return UNDETERMINED, (f"{evidence} Undetermined: the residual is explained, but not by one cause: {said}")
    return verdict, f"{evidence} Not one cause: {said}"
