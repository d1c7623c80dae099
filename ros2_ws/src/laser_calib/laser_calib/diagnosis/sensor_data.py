"""What remains after a sensor calibration, and which effect explains it.

Two views of the residuals of a fit (sensors.calibration):

- correlations: each residual component (translation in the sensor frame, m;
  rotation vector, rad) against each covariate (joint readings and their first
  two harmonics, time, the target's position in the sensor frame, extra sample
  columns). A covariate that explains a large share of a component points at
  an effect; a residual that follows none of them looks like noise.
- the diagnosis: the one engine of diagnosis.py (diagnosis.run, its F test,
  paired t test and BIC rules and its verdict) on SensorData: the point or pose
  model as the base, the frames-first identifiability and the rotation weight
  of the sensor calibration (held in every fit), the effect library's joint
  and parameter effects (spot effects are dropped by the engine: no spots)
  and one effect of the sensor, its length scale per axis (SensorScale).

The position-error figures of a selected model (held-out and in-sample, the
metric of the calibration) come from sensors.calibration with the selected
effects composed through ``extend``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar, Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from laser_calib.diagnosis.engine import DiagnoseOptions, Diagnosis, TooFewPoses, minimum_poses_nested, run
from laser_calib.effects import PARAM, Effect, EffectModel, candidates
from laser_calib.io.errors import InputError
from laser_calib.diagnosis.structure import SPOT_LEVEL, Series
from laser_calib.measurement.base import MeasurementModel, NoiseModel, Residuals
from laser_calib.model.robot import Robot
from laser_calib.estimation.sensor_fit import (Extend, HeldOut, SensorFit, SensorFitOptions, calibrate, kfold, make_model,
                          pose_errors, sensor_of)
from laser_calib.estimation.estimate import Estimate, EstimateOptions, estimate_model
from laser_calib.estimation.folds import kfold_labels
from laser_calib.measurement.sensor import SCALE_NAMES, SCALE_SCALE, PointModel, PoseModel
from laser_calib.io.sensor_samples import SensorSamples

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


def to_sensor_frame(model: MeasurementModel, res: Residuals) -> np.ndarray:
    """(P,D,D) map of a pose's residual values to the sensor-frame view: for
    poses the translation from the predicted target frame to the sensor frame
    and the rotation values from m to rad (divided by rotation_length); the
    identity for points."""
    dims = res.r.shape[2]
    out = np.broadcast_to(np.eye(dims), (res.r.shape[0], dims, dims)).copy()
    if dims == 6:
        length = sensor_of(model).rotation_length
        # The pose model's prediction carries the predicted rotation as a scaled rotation vector.
        out[:, :3, :3] = Rotation.from_rotvec(res.predicted[:, 0, 3:] / length).as_matrix()
        out[:, 3:, 3:] /= length
    return out


def sensor_residuals(model: MeasurementModel, x: np.ndarray) -> np.ndarray:
    """(P,D) measured - predicted: the translation in the sensor frame (m), then
    for poses the rotation vector of inv(predicted) · measured (rad); NaN where
    not seen. Works on a sensor model or an extension of one."""
    res = model.residuals(x, False)
    values = np.einsum("pij,pj->pi", to_sensor_frame(model, res), res.r[:, 0])
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
class SensorScale(Effect):
    """The sensor's length scale per axis of its frame (models.py): it reports a
    position p as (1 + s) p per axis. It acts on the base model's scale
    parameters (``param``: their indices, held at 0 in the geometric part), so
    the base must be built with scale=True; 3 dimensionless parameters."""

    param: tuple[int, int, int]

    kind: ClassVar[str] = "sensor_scale"
    family: ClassVar[str] = PARAM
    title: ClassVar[str] = "length scale of the sensor per axis"
    params: ClassVar[tuple[str, ...]] = ("x", "y", "z")
    units: ClassVar[tuple[str, ...]] = ("1", "1", "1")

    @property
    def where(self) -> str:
        return "sensor"

    @property
    def label(self) -> str:
        return "sensor scale"

    @property
    def scales(self) -> np.ndarray:
        return np.full(3, SCALE_SCALE)

    @property
    def typical(self) -> np.ndarray:
        return np.full(3, SCALE_SCALE)

    def basis(self, robot: Robot, samples: SensorSamples) -> np.ndarray:
        """(P,3,3): each scale parameter offset by its own value."""
        return np.broadcast_to(np.eye(3), (len(samples), 3, 3))

    @classmethod
    def from_yaml(cls, robot: Robot, entry: Mapping[str, Any], where: str) -> "SensorScale":
        raise InputError(f"{where}.type", "sensor_scale is the sensor calibration's scale option (calibrate "
                                          "--scale), not an effect of the robot")

    @classmethod
    def of(cls, base: PointModel | PoseModel) -> "SensorScale":
        return cls(param=tuple(base.names.index(n) for n in SCALE_NAMES))


@dataclass(frozen=True)
class SensorData:
    """Point or pose samples as the diagnosis engine sees them (diagnosis.Data).

    rotation_length (m/rad) weighs the pose rotations (from the sensor
    calibration); fixed: the parameters held in every fit (the user's, those
    the frames carry and, when the scale is not a base parameter, the base's
    scale parameters, which SensorScale then moves); scale: the sensor scale
    is estimated in every model (no SensorScale candidate)."""

    robot: Robot
    samples: SensorSamples
    rotation_length: float
    fixed: tuple[str, ...]
    scale: bool = False

    def base(self) -> PointModel | PoseModel:
        return make_model(self.robot, self.samples, self.rotation_length, True)

    def subset(self, index: np.ndarray) -> "SensorData":
        return replace(self, samples=self.samples.subset(index))

    def candidates(self) -> list[Effect]:
        extra = [] if self.scale else [SensorScale.of(self.base())]
        return extra + candidates(self.robot, self.samples)

    def measured_values(self) -> int:
        return (6 if self.samples.kind == "pose" else 3) * int(self.samples.seen.sum())

    def screen(self, options: EstimateOptions) -> Estimate:
        return estimate_model(EffectModel(self.base(), ()), options)

    def without(self, units: np.ndarray) -> "SensorData":
        return replace(self, samples=self.samples.without(units))

    def series(self, model: EffectModel, x: np.ndarray, res: Residuals, noise: NoiseModel
               ) -> tuple[list[Series], list[Series]]:
        """Each residual component in the sensor frame (sensor_residuals:
        translation, mm; rotation, mrad), weighted by its variance under the
        noise model, against the measured target position in the sensor frame
        and its distance; all (P,1)."""
        to_sensor = to_sensor_frame(model, res)
        values = np.einsum("pij,pj->pi", to_sensor, res.r[:, 0])
        g = np.einsum("pij,pjn->pin", to_sensor, res.jac_q[:, 0])
        joint = np.broadcast_to(np.asarray(noise.joint_sigma, float), (g.shape[-1],))
        variance = (noise.sigma ** 2 * np.einsum("pij,pij->pi", to_sensor, to_sensor)
                    + np.einsum("pin,n->pi", g ** 2, joint ** 2))
        valid = res.valid[:, 0]
        responses = [Series(f"residual {name}", values[:, d, None], SPOT_LEVEL, "mm" if d < 3 else "mrad", 1e3,
                            np.where(valid, 1.0 / variance[:, d], 0.0)[:, None])
                     for d, name in enumerate(("x", "y", "z", "rx", "ry", "rz")[:values.shape[1]])]
        position = self.samples.position
        covs = [Series(f"sensor {axis}", position[:, a, None], SPOT_LEVEL, "mm", 1e3) for a, axis in enumerate("xyz")]
        covs.append(Series("distance", np.linalg.norm(position, axis=1)[:, None], SPOT_LEVEL, "mm", 1e3))
        return responses, covs


def sensor_data(robot: Robot, samples: SensorSamples, options: SensorFitOptions) -> SensorData:
    """SensorData with the rotation weight and the frames-first holds of the
    sensor calibration (calibrate) on these samples."""
    fit = calibrate(robot, samples, options)
    held = tuple(options.estimate.fixed) + tuple(fit.absorbed) + (() if options.scale else SCALE_NAMES)
    return SensorData(robot, samples, fit.rotation_length, tuple(dict.fromkeys(held)), options.scale)


def diagnose_options(options: SensorFitOptions, folds: int = 5, seed: int = 0, max_effects: int = 4
                     ) -> DiagnoseOptions:
    """The engine's options from the sensor fit's: method, (given) sigma and robust rule; the
    joint-reading noise is estimated. The engine's nested held-out error is
    left out: nested_heldout measures it in the calibration's metric."""
    return DiagnoseOptions(method=options.estimate.method, spot_sigma=options.estimate.spot_sigma, folds=folds,
                           seed=seed, max_effects=max_effects, nested=False, robust=options.estimate.robust)


def diagnose(robot: Robot, samples: SensorSamples, options: SensorFitOptions,
             engine: DiagnoseOptions = DiagnoseOptions()) -> Diagnosis:
    """The diagnosis engine (diagnosis.run) on point or pose samples. The fits
    carry no priors (the engine's rules compare unpenalised fits)."""
    return run(sensor_data(robot, samples, options), engine)


def with_effects(options: SensorFitOptions, effects: tuple[Effect, ...]
                 ) -> tuple[SensorFitOptions, tuple[Effect, ...]]:
    """The calibration options and the effects to compose through ``extend``
    for a selected model: SensorScale is calibrate()'s own scale option."""
    scale = options.scale or any(isinstance(e, SensorScale) for e in effects)
    return replace(options, scale=scale), tuple(e for e in effects if not isinstance(e, SensorScale))


def extender(robot: Robot, samples: SensorSamples, effects: tuple[Effect, ...], scale: bool,
             within: np.ndarray | None = None) -> Extend | None:
    """The hook composing joint and parameter effects with a sensor model on
    the poses ``within`` (indices into ``samples``, default all). Bases come
    from the whole sequence (approach directions) and are sliced per subset."""
    if not effects:
        return None
    whole = EffectModel(make_model(robot, samples, 1.0, scale), effects)
    within = np.arange(len(samples)) if within is None else np.asarray(within)

    def extend(base, index: np.ndarray) -> MeasurementModel:
        return EffectModel(base, effects, whole.bases.subset(within[index]))
    return extend


def fit_effects(robot: Robot, samples: SensorSamples, options: SensorFitOptions, effects: tuple[Effect, ...],
                within: np.ndarray | None = None) -> SensorFit:
    """The sensor calibration with the selected effects on the poses ``within``."""
    within = np.arange(len(samples)) if within is None else np.asarray(within)
    fit_options, rest = with_effects(options, effects)
    extend = extender(robot, samples, rest, fit_options.scale, within)
    return calibrate(robot, samples.subset(within), fit_options, extend)


def heldout_effects(robot: Robot, samples: SensorSamples, options: SensorFitOptions, effects: tuple[Effect, ...],
                    k: int = 5, seed: int = 0) -> HeldOut:
    """k-fold held-out errors (calibration.kfold) of the model with the effects."""
    fit_options, rest = with_effects(options, effects)
    return kfold(robot, samples, fit_options, k, seed, extender(robot, samples, rest, fit_options.scale))


def nested_heldout(robot: Robot, samples: SensorSamples, options: SensorFitOptions, k: int = 5, seed: int = 0,
                   engine: DiagnoseOptions = DiagnoseOptions()) -> tuple[np.ndarray, tuple[str, ...]]:
    """Held-out position error (P,) of the whole procedure, selection included:
    per outer fold, the diagnosis on the other folds only (its own folds), the
    chosen model fitted there, the fold predicted. Also the model chosen per fold."""
    fold = kfold_labels(len(samples), k, seed + 1)  # an outer split unlike the inner one
    out = np.full(len(samples), np.nan)
    chosen = []
    for f in range(k):
        train, test = np.flatnonzero(fold != f), np.flatnonzero(fold == f)
        effects = diagnose(robot, samples.subset(train), options, replace(engine, nested=False)).final.effects
        fit = fit_effects(robot, samples, options, effects, train)
        fit_options, rest = with_effects(options, effects)
        base = make_model(robot, samples.subset(test), fit.rotation_length, fit_options.scale)
        extend = extender(robot, samples, rest, fit_options.scale, test)
        out[test] = pose_errors(base if extend is None else extend(base, np.arange(len(test))),
                                fit.estimate.values)[0]
        chosen.append(" + ".join(e.label for e in effects) or "geometric")
    return out, tuple(chosen)


def diagnosis_summary(robot: Robot, samples: SensorSamples, options: SensorFitOptions, folds: int, seed: int,
                      source: str) -> dict:
    """`calibrate-poses --diagnose`: the diagnosis engine on the samples (diagnose): its
    selection rounds, verdict and evidence; per stage the k-fold held-out mean
    position error (mm) of the calibration with its effects (chosen on all the
    poses), and the held-out error of the whole procedure, the selection nested
    inside the folds (nested_heldout: the figure the final model is judged by).
    source: the samples' file, named when they are too few."""
    engine = diagnose_options(options, folds, seed)
    try:
        diagnosis = diagnose(robot, samples, options, engine)
        nested, chosen = nested_heldout(robot, samples, options, folds, seed, engine)
    except TooFewPoses as exc:  # counted on the poses it ran on: all of them or a fold's training part
        raise InputError(source, f"{len(samples)} poses, at least {minimum_poses_nested(exc.needed, folds)} needed "
                                 f"for --diagnose (the diagnosis needs {exc.needed}, and its held-out error runs "
                                 f"it again without each of the {folds} folds)") from None
    full = diagnosis.to_json()
    stages = []
    for stage in diagnosis.stages:
        held = heldout_effects(robot, samples, options, stage.fitted.effects, folds, seed)
        stages.append({"model": stage.label, "heldout_mean_mm": float(np.nanmean(held.position)) * 1e3,
                       "bic": stage.fitted.bic})
    return {"stages": stages, "heldout_nested_mean_mm": float(np.nanmean(nested)) * 1e3,
            "nested_choices": list(chosen), "selection": full["selection"], "effects": full["effects"],
            "verdict": diagnosis.verdict, "evidence": diagnosis.evidence, "noise": full["noise"],
            "notes": full["notes"], "joints": full["joints"]}
