"""What remains after a sensor calibration, and which effect explains it.

Two views of the residuals of a fit (sensors.calibration):

- correlations: each residual component (translation in the sensor frame, m;
  rotation vector, rad) against each covariate (joint readings and their first
  two harmonics, time, the target's position in the sensor frame, extra sample
  columns). A covariate that explains a large share of a component points at
  an effect; a residual that follows none of them looks like noise.
- candidates: each effect added to the model in turn, judged by the k-fold
  held-out position error (the same folds for all). Forward selection adds
  the candidate with the lowest held-out mean while it lowers that mean by at
  least ``min_gain`` (relative) and a one-sided paired Wilcoxon signed-rank
  test over the poses' held-out errors gives p < ``alpha``, so an effect is
  only claimed when it predicts poses the fit did not see, consistently.

Candidates are the sensor's own scale per axis (models.py) and the effect
library's joint and parameter effects (gear ratio, periodic error, backlash,
drift of a length with a covariate), composed with the sensor model through
jac_q / jac (effects.model.EffectModel). Spot effects (screen, camera lens) do
not apply to point or pose sensors.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import stats
from scipy.spatial.transform import Rotation

from ..effects import SPOT, Effect, EffectModel, candidates
from ..measurement import MeasurementModel
from ..model import Robot
from .calibration import (Extend, SensorFitOptions, calibrate, fold_labels, kfold, make_model, pose_errors,
                          sensor_of)
from .samples import SensorSamples

SCALE = "sensor scale"


def covariates(samples: SensorSamples) -> dict[str, np.ndarray]:
    """(P,) covariates: q_i, cos/sin of q_i and 2 q_i, time (s from the first
    pose), the measured target position in the sensor frame and its distance
    (m), and the extra sample columns."""
    out: dict[str, np.ndarray] = {}
    for i in range(samples.n_joints):
        q = samples.q[:, i]
        out[f"q{i + 1}"] = q
        for k in (1, 2):
            out[f"cos {k}q{i + 1}"], out[f"sin {k}q{i + 1}"] = np.cos(k * q), np.sin(k * q)
    out["time"] = samples.stamp - samples.stamp[0]
    for a, axis in enumerate("xyz"):
        out[f"sensor {axis}"] = samples.position[:, a]
    out["distance"] = np.linalg.norm(samples.position, axis=1)
    out.update(samples.extra)
    return out


def sensor_residuals(model: MeasurementModel, x: np.ndarray) -> np.ndarray:
    """(P,D) measured - predicted: the translation in the sensor frame (m), then
    for poses the rotation vector of inv(predicted) · measured (rad); NaN where
    not seen. Works on a sensor model or an extension of one."""
    res = model.residuals(x, False)
    values = res.r[:, 0].copy()
    if values.shape[1] == 6:
        length = sensor_of(model).rotation_length
        # The pose model's prediction carries the predicted rotation as a scaled rotation vector.
        rotation = Rotation.from_rotvec(res.predicted[:, 0, 3:] / length).as_matrix()
        values[:, :3] = np.einsum("pij,pj->pi", rotation, values[:, :3])   # target frame -> sensor frame
        values[:, 3:] /= length
    return np.where(res.valid[:, 0, None], values, np.nan)


@dataclass(frozen=True)
class Correlations:
    """r (C,D): correlation of each covariate (names, C) with each residual
    component (components, D); explained (C,): the share of the total residual
    variance a linear fit on that covariate removes, summed over the
    translation components."""

    names: tuple[str, ...]
    components: tuple[str, ...]
    r: np.ndarray
    explained: np.ndarray


def correlations(residuals: np.ndarray, covs: dict[str, np.ndarray]) -> Correlations:
    """Correlations of residuals (P,D) (sensor_residuals) with covariates (P,) each,
    over the seen poses; covariates constant there are left out."""
    seen = np.isfinite(residuals).all(axis=1)
    res = residuals[seen] - residuals[seen].mean(axis=0)
    names = tuple(n for n, c in covs.items() if np.ptp(c[seen]) > 0)
    values = np.column_stack([covs[n][seen] for n in names])
    values = values - values.mean(axis=0)
    r = (values.T @ res) / np.outer(np.linalg.norm(values, axis=0), np.linalg.norm(res, axis=0))
    translation = res[:, :3]
    total = (translation ** 2).sum()
    explained = np.array([((values[:, c] @ translation) ** 2).sum() / (values[:, c] @ values[:, c]) / total
                          for c in range(len(names))])
    components = ("x", "y", "z", "rx", "ry", "rz")[:residuals.shape[1]]
    return Correlations(names, components, r, explained)


@dataclass(frozen=True)
class Candidate:
    """A model variant: the sensor scale on or off and a list of effects."""

    scale: bool
    effects: tuple[Effect, ...]

    @property
    def label(self) -> str:
        parts = ([SCALE] if self.scale else []) + [e.label for e in self.effects]
        return " + ".join(parts) or "geometric (D-H + frames)"

    @property
    def n_params(self) -> int:
        return 3 * self.scale + sum(len(e.params) for e in self.effects)


@dataclass(frozen=True)
class Scored:
    """A candidate's k-fold held-out position error per pose (P,) and the
    in-sample mean (m); p: the paired test against the model it extends."""

    candidate: Candidate
    heldout: np.ndarray
    insample_mean: float
    p: float = float("nan")

    @property
    def heldout_mean(self) -> float:
        return float(np.nanmean(self.heldout))


def library_effects(robot: Robot, samples: SensorSamples) -> list[Effect]:
    """The effect library's joint and parameter candidates for these samples."""
    # Bases recomputed at the geometric errors (compliance) take the whole base
    # vector as D-H errors in EffectModel.joint_basis; left out until it slices them.
    return [e for e in candidates(robot, samples) if e.family != SPOT and not getattr(e, "geometric_basis", False)]


def extender(robot: Robot, samples: SensorSamples, candidate: Candidate,
             within: np.ndarray | None = None) -> Extend | None:
    """The hook composing the candidate's effects with a sensor model on the
    poses ``within`` (indices into ``samples``, default all). Bases come from
    the whole sequence (approach directions) and are sliced per subset."""
    if not candidate.effects:
        return None
    whole = EffectModel(make_model(robot, samples, 1.0, candidate.scale), candidate.effects)
    within = np.arange(len(samples)) if within is None else np.asarray(within)

    def extend(base, index: np.ndarray) -> MeasurementModel:
        return EffectModel(base, candidate.effects, whole.bases.subset(within[index]))
    return extend


def score(robot: Robot, samples: SensorSamples, options: SensorFitOptions, candidate: Candidate,
          k: int, seed: int, against: Scored | None = None, within: np.ndarray | None = None) -> Scored:
    """Held-out and in-sample errors of one candidate on the poses ``within``
    (default all); p of the paired test "candidate better than ``against``"."""
    within = np.arange(len(samples)) if within is None else np.asarray(within)
    options = replace(options, scale=candidate.scale)
    extend = extender(robot, samples, candidate, within)
    part = samples.subset(within)
    held = kfold(robot, part, options, k, seed, extend).position
    fit = calibrate(robot, part, options, extend)
    position, _ = pose_errors(fit.model, fit.estimate.values)
    p = float("nan")
    if against is not None:
        both = np.isfinite(held) & np.isfinite(against.heldout)
        p = float(stats.wilcoxon(against.heldout[both], held[both], alternative="greater").pvalue)
    return Scored(candidate, held, float(np.nanmean(position)), p)


@dataclass(frozen=True)
class Selection:
    """rounds: every candidate scored in each round of forward selection
    (round 0: the geometric model alone); chosen: the selected model."""

    rounds: tuple[tuple[Scored, ...], ...]
    chosen: Scored


def select(robot: Robot, samples: SensorSamples, options: SensorFitOptions, k: int = 5, seed: int = 0,
           min_gain: float = 0.03, alpha: float = 0.01, max_rounds: int = 4,
           within: np.ndarray | None = None) -> Selection:
    """Forward selection of effects by held-out error (module docstring), on
    the poses ``within`` (default all)."""
    effects = library_effects(robot, samples)
    current = score(robot, samples, options, Candidate(False, ()), k, seed, within=within)
    rounds = [(current,)]
    for _ in range(max_rounds):
        base = current.candidate
        trials = [Candidate(True, base.effects)] if not base.scale else []
        trials += [Candidate(base.scale, base.effects + (e,)) for e in effects if e not in base.effects]
        scored = tuple(sorted((score(robot, samples, options, c, k, seed, current, within) for c in trials),
                              key=lambda s: s.heldout_mean))
        rounds.append(scored)
        if (not scored or scored[0].heldout_mean > current.heldout_mean * (1.0 - min_gain)
                or not scored[0].p < alpha):
            break
        current = scored[0]
    return Selection(tuple(rounds), current)


def nested_heldout(robot: Robot, samples: SensorSamples, options: SensorFitOptions, k: int = 5, seed: int = 0,
                   **selection) -> tuple[np.ndarray, tuple[str, ...]]:
    """Held-out position error (P,) of the whole procedure, selection included:
    per outer fold, select() on the other folds only (its own inner k-fold),
    fit the chosen model there, predict the fold. Also the model chosen per fold."""
    fold = fold_labels(len(samples), k, seed + 1)  # an outer split unlike the inner one
    out = np.full(len(samples), np.nan)
    chosen = []
    for f in range(k):
        train, test = np.flatnonzero(fold != f), np.flatnonzero(fold == f)
        candidate = select(robot, samples, options, k, seed, within=train, **selection).chosen.candidate
        fit_options = replace(options, scale=candidate.scale)
        fit = calibrate(robot, samples.subset(train), fit_options, extender(robot, samples, candidate, train))
        base = make_model(robot, samples.subset(test), fit.rotation_length, candidate.scale)
        extend = extender(robot, samples, candidate, test)
        out[test] = pose_errors(base if extend is None else extend(base, np.arange(len(test))),
                                fit.estimate.values)[0]
        chosen.append(candidate.label)
    return out, tuple(chosen)
