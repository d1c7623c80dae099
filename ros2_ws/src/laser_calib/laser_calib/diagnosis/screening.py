"""Gross outliers out before the diagnosis: what the estimate refuses, no model here fits.

The diagnosis fits plain least squares (a structure shows as large residuals,
which a robust loss would weigh down), so one wrong spot (a reflection
detected 15 cm off) would otherwise drive every fit, inflate the estimated
joint-reading noise to degrees and hide all structure behind it, while the
verdict still read "explained". The geometric estimate that `estimate` runs
(its robust rule, estimation/robust.py, and its refusal of physically
impossible spots) judges every measured unit once, on all calibration poses;
the units it refuses are left out of every fit, fold and test of the
diagnosis, and listed in its notes. The geometric model cannot tell a gross
outlier from the far end of an effect it lacks (a gear-ratio error at the
widest joint angles), so the refused units are judged again by the final
model's residual, with the same limit: those it fits within it are taken back
and the diagnosis is run again with them (screened_again). Without the
refused units the kept data may not show that effect at all (a curved
screen's sag, large only at the corners the refused spots lie in, was not
selected, and its test error stayed 3.2 times the true model's), so those the
final model leaves out are judged by the effects selected on every unit
too. The samples file keeps every value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import chdtri

from laser_calib.diagnosis.data import Data
from laser_calib.diagnosis.options import DiagnoseOptions
from laser_calib.diagnosis.result import Fitted, NoiseInfo
from laser_calib.effects.effect_model import EffectModel
from laser_calib.estimation.estimate import LISTED, EstimateOptions
from laser_calib.estimation.failures import first_failure
from laser_calib.estimation.robust import FAMILY_FALSE_REJECTION, NO_JOINT_NOISE, distances_at
from laser_calib.measurement.base import NoiseModel


@dataclass(frozen=True)
class Refused:
    """The units (P,C) the geometric estimate rejected as gross outliers and those it
    refused as physically impossible; taken back: those the final model fits."""

    rejected: np.ndarray
    impossible: np.ndarray
    taken_back: np.ndarray | None = None
    effects: str = ""  # the final model that took them back

    @property
    def units(self) -> np.ndarray:
        out = self.rejected | self.impossible
        return out if self.taken_back is None else out & ~self.taken_back

    def note(self, data: Data, options: DiagnoseOptions) -> list[str]:
        count = int(self.units.sum())
        parts = [f"{int(units.sum())} {what} ({named(data, units)})" for what, units in (
            ("rejected as gross outliers by its robust rule", self.rejected & self.units),
            ("physically impossible (outside the screen, or the beam misses it far)", self.impossible & self.units))
                 if units.any()]
        out = [f"{count} measurement{'s' * (count > 1)} left out of every fit and test of the diagnosis, as the "
               f"geometric calibration leaves them out: {'; '.join(parts)}"
               + (NO_JOINT_NOISE if self.rejected.any() and not options.joint_sigma else "")] if count else []
        if self.taken_back is not None and self.taken_back.any():
            out.append(f"{int(self.taken_back.sum())} measurements the geometric calibration refused are fitted by "
                       f"{self.effects} within its limit and were kept: the far end of an effect, not outliers "
                       f"({named(data, self.taken_back)})")
        return out


def screened(data: Data, options: DiagnoseOptions) -> tuple[Data, Refused | None]:
    """``data`` without the units the geometric estimate refuses, and what it refused (None
    when nothing, options.robust is off, or that estimate is itself no calibration: its
    judgement of outliers is then none)."""
    if not options.robust:
        return data, None
    estimate = data.screen(EstimateOptions(method=options.method, spot_sigma=options.spot_sigma,
                                           joint_sigma=options.joint_sigma or 0.0, restarts=options.restarts,
                                           seed=options.seed, fixed=data.fixed, robust=True))
    if first_failure(estimate.warnings) or not (estimate.rejected or estimate.impossible):
        return data, None
    shape = data.samples.seen.reshape(len(data.samples.q), -1).shape      # (P,C)
    rejected, impossible = np.zeros(shape, bool), np.zeros(shape, bool)
    for p, c in estimate.rejected:
        rejected[p, c] = True
    for p, c, _ in estimate.impossible:
        impossible[p, c] = True
    refused = Refused(rejected, impossible)
    return data.without(refused.units), refused


def screened_again(data: Data, final: Fitted, verdict_noise: NoiseInfo, refused: Refused) -> Refused | None:
    """``refused`` with the units a final model with effects fits taken back: each unit's
    squared whitened distance under the verdict's noise model, against the robust rule's
    limit chi^2_D(1 - 0.01 / N) at the scale of the kept units (at least 1); None when the
    final model has no effect (the geometric model judged them already) or takes none back."""
    if not final.effects:
        return None
    back = fitted(data, final, verdict_noise, refused)
    if not back.any():
        return None
    return Refused(refused.rejected, refused.impossible, back, final.label)


def fitted(data: Data, final: Fitted, verdict_noise: NoiseInfo, refused: Refused) -> np.ndarray:
    """(P,C) the refused units that ``final`` fits within the robust rule's limit (screened_again)."""
    noise = NoiseModel(verdict_noise.spot_sigma, verdict_noise.joint_sigma)
    d2, valid, dims = distances_at(EffectModel(data.base(), final.effects), noise, final.estimate.values)
    refused_units = refused.rejected | refused.impossible
    kept = valid & ~refused_units
    scale2 = float(d2[kept].mean() / dims) if kept.any() else 1.0
    return refused_units & within_limit(d2, valid, dims, scale2)


def within_limit(d2: np.ndarray, valid: np.ndarray, dims: int, scale2: float) -> np.ndarray:
    """(P,C) the valid units whose squared whitened distance d2 (P,C) of ``dims`` values, at the
    scale ``scale2`` (at least 1), is within the robust rule's limit chi^2_D(1 - 0.01 / N), N the
    valid units: what a model fits (screened_again), or a test unit is tested on (prediction.py)."""
    limit = chdtri(dims, FAMILY_FALSE_REJECTION / max(int(valid.sum()), 1))
    return valid & (d2 / max(scale2, 1.0) <= limit)


def misfits(data: Data, final: Fitted, verdict_noise: NoiseInfo, refused: Refused) -> int:
    """How many units the geometric calibration rejected as gross outliers stay left out and
    are beyond the limit of ``final`` too, under the verdict's noise model. Not those within
    it: without a joint-reading sigma given, the geometric calibration's rule takes the joint
    noise's share of a long lever's spot for an outlier (NO_JOINT_NOISE), which the
    verdict's noise model holds."""
    return int((refused.rejected & refused.units & ~fitted(data, final, verdict_noise, refused)).sum())


def taken_back_by_either(first: Refused | None, second: Refused | None) -> Refused | None:
    """The units either judgement (screened_again) took back, and the models that fitted them."""
    if first is None or second is None:
        return first or second
    effects = first.effects if first.effects == second.effects else f"{first.effects} or {second.effects}"
    return Refused(first.rejected, first.impossible, first.taken_back | second.taken_back, effects)


def named(data: Data, units: np.ndarray) -> str:
    """'pose 9 laser 1, ...' of the units (P,C) (a point or pose sensor's unit is its pose), at most LISTED."""
    lasers = data.samples.spots is not None
    pairs = list(zip(*np.nonzero(units)))
    names = [f"pose {data.samples.pose[p]}" + (f" laser {c + 1}" if lasers else "") for p, c in pairs[:LISTED]]
    return ", ".join(names) + (f" and {len(pairs) - LISTED} more" if len(pairs) > LISTED else "")
