"""The effect library: every candidate for a data set, and the robot file's
``effects:`` key (docs/effects.md), read and written with validation."""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.io.samples import Samples
from laser_calib.effects.base import REGISTRY, Effect, joint_name, move_directions, yaml_number
from laser_calib.effects.drift import STAMP, Drift, length_params
from laser_calib.effects.joint import JOINT_EFFECTS, Backlash, Compliance, gravity_torques
from laser_calib.effects.effect_model import EffectModel
from laser_calib.effects.screen import CameraDistortion, ScreenShape

KINDS = REGISTRY  # every effect class registers its YAML type when defined (effects.base.Effect)
MIN_MOTION = 1e-6  # rad, m or covariate unit: below this a basis is constant over the data


def screen_shape(robot: Robot) -> ScreenShape:
    return ScreenShape(half_y=robot.screen.half_y, half_z=robot.screen.half_z, camera=robot.screen.camera)


def camera_distortion(robot: Robot) -> CameraDistortion:
    return CameraDistortion(radius=max(robot.screen.half_y, robot.screen.half_z))


def covariate_names(samples: Samples) -> list[str]:
    """Columns a drift may follow: the stamp and every extra column that varies."""
    names = [STAMP] + list(samples.extra)
    values = {STAMP: samples.stamp, **samples.extra}
    return [name for name in names if len(values[name]) and np.ptp(values[name]) > MIN_MOTION]


def candidates(robot: Robot, samples: Samples) -> list[Effect]:
    """Each library effect at each joint, length and covariate where the data
    can show it: a joint that moves, a gravity torque that changes, approach
    directions that differ, a covariate that varies."""
    out: list[Effect] = []
    torques = gravity_torques(robot, samples.q)
    directions = move_directions(samples.q)
    for i in range(robot.n_joints):
        if np.ptp(samples.q[:, i]) <= MIN_MOTION:
            continue
        for cls in JOINT_EFFECTS:
            if cls is Compliance:
                if np.ptp(torques[:, i]) > MIN_MOTION:
                    out.append(Compliance(joint=i, torque_span=float(np.ptp(torques[:, i])), name=joint_name(robot, i)))
            elif cls is not Backlash or np.ptp(directions[:, i]) > 0:
                out.append(cls(joint=i, name=joint_name(robot, i)))
    names = robot.param_names
    for covariate in covariate_names(samples):
        out += [Drift.make(robot, samples, names[j], covariate) for j in length_params(robot)]
    out += [screen_shape(robot), camera_distortion(robot)]
    return out


def same_place(a: Effect, b: Effect) -> bool:
    """Two blocks of the same kind acting at the same place (never both in a model)."""
    return a.kind == b.kind and a.where == b.where and getattr(a, "covariate", None) == getattr(b, "covariate", None)


def effects_to_yaml(effects: Sequence[Effect], values: Sequence[np.ndarray]) -> list[dict[str, Any]]:
    return [e.to_yaml(v) for e, v in zip(effects, values)]


def _effect(robot: Robot, entry: Mapping[str, Any], where: str) -> Effect:
    kind = entry.get("type")
    if kind not in REGISTRY:
        raise InputError(f"{where}.type", f"expected one of {', '.join(REGISTRY)}, got {kind!r}")
    return REGISTRY[kind].from_yaml(robot, entry, where)


def effects_from_robot(robot: Robot, source: str = "<robot>") -> tuple[list[Effect], list[np.ndarray]]:
    """The effects of a robot file's ``effects:`` key (empty if absent) and their values."""
    entries = robot.extra.get("effects", [])
    if not isinstance(entries, list):
        raise InputError(f"{source}: effects", f"expected a list, got {type(entries).__name__}")
    effects, values = [], []
    for n, entry in enumerate(entries):
        where = f"{source}: effects[{n}]"
        if not isinstance(entry, Mapping):
            raise InputError(where, f"expected a mapping, got {type(entry).__name__}")
        effect = _effect(robot, entry, where)
        if any(same_place(effect, other) for other in effects):
            raise InputError(where, f"{effect.label} appears twice")
        effects.append(effect)
        values.append(np.array([yaml_number(where, entry, p) for p in effect.params]))
    return effects, values


def calibrated_model(robot: Robot, samples: Samples, source: str = "<robot>") -> tuple[EffectModel, np.ndarray]:
    """The model of a calibrated robot file (D-H values corrected, ``effects:``
    key) on ``samples``, and its parameter vector x (geometric errors 0: they
    are in the D-H values)."""
    effects, values = effects_from_robot(robot, source)
    model = EffectModel(SpotModel(robot, samples), effects)
    return model, np.concatenate([np.zeros(robot.n_params), *values])
