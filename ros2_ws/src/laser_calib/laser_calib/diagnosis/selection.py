"""The selection rounds over the effect library and the report of the
chosen effects' parameters."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Sequence

import numpy as np

from laser_calib.diagnosis.fitter import Fitter, fit_test_p, paired_p, rms_mm
from laser_calib.diagnosis.options import EQUIVALENT_P, SEPARABLE_CORRELATION, DiagnoseOptions
from laser_calib.diagnosis.result import Fitted, Ranked
from laser_calib.effects.base import Effect
from laser_calib.effects.catalog import same_place

def select(fitter: Fitter, pool: list[Effect], options: DiagnoseOptions
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
            ranked[effect.label] = (rms_mm(fitted.cv), fitted, p_fit, p_heldout, delta_bic,
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


