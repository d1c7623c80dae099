"""The robust rule as `estimate` runs it (robust.robust_fit): the units it leaves out, the
least-squares fit on the rest, and what it says of them. `estimate` runs it again when the
joint-reading noise estimated after it is significant: the rule weighs each unit by the noise
model it is given, and without joint noise it rejected spots on long levers for the scatter
that noise gives them (0.8-1.1 % of clean spots at 0.5 mm spot and 0.1 deg joint noise)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from laser_calib.estimation.identifiability import TooFewValues
from laser_calib.estimation.lm import LmOptions, levenberg_marquardt
from laser_calib.estimation.problem import Fit
from laser_calib.estimation.robust import NO_JOINT_NOISE, ROBUST_RULE, robust_fit
from laser_calib.io.samples import Samples
from laser_calib.measurement.base import MeasurementModel, NoiseModel, Residuals

LISTED = 8  # poses named in one warning line


def model_samples(model: MeasurementModel) -> Samples:
    """The model's samples (effects wrap a base model)."""
    while not hasattr(model, "samples") and hasattr(model, "base"):
        model = model.base
    return model.samples


def listing(model: MeasurementModel, units: list[tuple[int, int]]) -> str:
    """The units (pose index, channel) of the model's samples by pose id (named)."""
    return named(model_samples(model), units)


def named(samples: Samples, units: list[tuple[int, int]]) -> str:
    """The units (pose index, channel) by pose id: a spot's laser always, since a pose has two;
    a point's or pose's unit is its pose; at most LISTED, then how many more."""
    lasers = samples.kind == "spot"
    names = [f"pose {samples.pose[p]}" + (f" laser {c + 1}" if lasers else "") for p, c in units[:LISTED]]
    return ", ".join(names) + (f" and {len(units) - LISTED} more" if len(units) > LISTED else "")


@dataclass(frozen=True)
class Rejection:
    """rejected: (pose index, channel) of the units the rule rejected; removed (P,C) their mask,
    None when none; left_out (P,C): those and the units excluded before it, None when neither; fit:
    its final least-squares fit on the rest, None when none was rejected (the fits after it then start
    where they would without the rule); summary: result.json's "robust"."""

    rejected: list[tuple[int, int]]
    removed: np.ndarray | None
    left_out: np.ndarray | None
    fit: Fit | None
    summary: dict
    warnings: list[str]


def rejection(model: MeasurementModel, noise: NoiseModel, free: np.ndarray, prior_sigma: np.ndarray | None,
              x0: np.ndarray, excluded: np.ndarray | None, at_start: Residuals, lm: LmOptions) -> Rejection:
    """The robust rule from x0 on the units measured there (at_start: the model's residuals at x0)
    and not ``excluded`` (P,C; None: none), its IRLS and final fit by LM whatever the method (the
    EKF's fixed point is the same, in hundreds of iterations). TooFewValues when a rejection would
    leave no residual value (it would make up sigma and stds)."""
    outcome = robust_fit(model, noise, free, prior_sigma, x0,
                         lambda problem, x, start: levenberg_marquardt(problem, x, lm, start), excluded, at_start, lm)
    rejected = [(int(p), int(c)) for p, c in zip(*np.nonzero(outcome.rejected))]
    removed = outcome.rejected if rejected else None
    seen, dims = at_start.valid, at_start.r.shape[2]
    left_out = excluded if removed is None else removed if excluded is None else excluded | removed
    kept = int((seen if left_out is None else seen & ~left_out).sum())
    n_values = (kept + len(rejected)) * dims
    if rejected and kept * dims <= free.sum() and prior_sigma is None:
        raise TooFewValues(kept * dims, int(free.sum()), len(rejected))
    summary = {"rule": ROBUST_RULE, "scale": outcome.scale, "rounds": outcome.rounds,
               "weights_converged": outcome.converged, "rejected": len(rejected), "kept": kept}
    warnings = []
    if rejected:
        warnings.append(f"robust: {len(rejected)} of {kept + len(rejected)} measurements rejected as outliers and not "
                        f"fitted: {listing(model, rejected)}" + ("" if noise.joint_noise else NO_JOINT_NOISE))
    if outcome.overflow:
        warnings.append(f"robust: {outcome.overflow} of {kept} measurements lie beyond the outlier limit: the model "
                        "does not fit the data (an unmodelled effect or wrong nominal model); none rejected")
    if outcome.untestable:
        warnings.append(f"robust: too few values to tell an outlier: without the {outcome.untestable} of {kept} "
                        f"measurements farthest from the fit, {n_values - outcome.untestable * dims} values would "
                        f"be left for {int(free.sum())} parameters (an exact fit); none rejected")
    if not outcome.converged:
        warnings.append(f"robust: the weights did not settle in {outcome.rounds} rounds")
    return Rejection(rejected, removed, left_out, outcome.fit if rejected else None, summary, warnings)
