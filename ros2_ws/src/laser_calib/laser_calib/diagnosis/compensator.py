"""The learned compensator: the detector's regression, kept as a last stage.

After the physical effects, what remains may still follow the inputs
smoothly (detector.py). The detector's regression refitted on all calibration
poses gives, per pose, a joint-angle offset f_j(z) of each joint and a twist,
length and offset change of each link, from the pose's inputs z (readings, move directions,
stamp, extra columns). It is kept only when the detector's held-out gain is
significant (the test that decides it held each pose out), it never replaces
a physical effect (the report lists it apart, with its gain) and it acts
through the kinematics, so it applies to any pose and any measurement model:

    compensator = load_compensator("compensator.json")
    spots = compensator.predict(EffectModel(SpotModel(robot, samples), effects))   # (P,2,2)

with robot the nominal robot of the diagnosis and effects those of its
robot_calibrated.yaml (effects_from_robot): the file holds the geometric
errors and effect values refitted together with the compensation (backfit).

File (JSON, compensator.json of a diagnosis, version 2): inputs, targets
(theta_j are joint offsets, alpha_j, d_j and a_j offsets of the link's
parameters), the basis (standardisation, knots, pairs, size), the coefficients
``coef`` (m', b) of the directions used, in SI units (rad for theta_j and
alpha_j, m for d_j and a_j; version 1 files, from before the length
directions, hold only angles under ``coef_rad`` and still load); load it with
load_compensator(path). The move directions are taken from the row order of
the samples it is applied to (from q = 0), as in the calibration.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Mapping

import numpy as np

from sklearn.base import clone

from laser_calib.diagnosis.detector import Basis, Detection, OffsetRegression, design, input_table
from laser_calib.estimation.estimate import EstimateOptions, estimate_model
from laser_calib.measurement.base import NoiseModel
from laser_calib.effects.effect_model import EffectModel, Fixed
from laser_calib.io.errors import InputError
from laser_calib.model.robot import Robot

VERSION = 2
READABLE = (1, 2)  # version 1: angle targets only, coefficients under "coef_rad"
BACKFIT = 3  # rounds of model refit / regression refit


@dataclass(frozen=True)
class Compensator:
    """inputs (d,) names; targets (m,) parameter names; used (m,) the targets
    the regression has; coef (m', b) per basis function (rad or m, the target's unit); heldout_gain the
    detector's held-out gain of the regression (fraction of the whitened
    residual sum of squares); names and values (n,) of the model it completes
    (its geometric errors and effect parameters refitted with the compensation)."""

    inputs: tuple[str, ...]
    targets: tuple[str, ...]
    used: np.ndarray
    basis: Basis
    coef: np.ndarray
    heldout_gain: float
    names: tuple[str, ...] = ()
    values: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @classmethod
    def of(cls, regression: OffsetRegression, detection: Detection, names: tuple[str, ...], values: np.ndarray
           ) -> "Compensator":
        full = regression.coefficients(len(detection.targets))
        used = np.any(full != 0, axis=1)
        return cls(detection.inputs, detection.targets, used, regression.basis, full[used], detection.gain,
                   tuple(names), np.asarray(values, float))

    def offsets(self, robot: Robot, q: np.ndarray, stamp: np.ndarray, extra: Mapping[str, np.ndarray]
                ) -> tuple[np.ndarray, np.ndarray]:
        """Joint offsets dq (P,N) rad and geometric-parameter offsets (P,n) of
        the poses with readings q (P,N), stamps (P,) and extra columns."""
        names, z = input_table(q, stamp, dict(extra))
        missing = [n for n in self.inputs if n not in names]
        if missing:
            raise InputError("samples", f"no column '{missing[0]}' (the compensator follows it)")
        z = z[:, [names.index(n) for n in self.inputs]]
        values = np.zeros((len(q), len(self.targets)))
        values[:, self.used] = self.basis(z) @ self.coef.T
        dq = np.zeros_like(np.asarray(q, float))
        errors = np.zeros((len(q), robot.n_params))
        for k, name in enumerate(self.targets):
            if name.startswith("theta"):
                dq[:, int(name[5:]) - 1] += values[:, k]
            else:
                errors[:, robot.param_names.index(name)] += values[:, k]
        return dq, errors

    def apply(self, model: EffectModel) -> EffectModel:
        """The model with the compensation's offsets on its poses."""
        samples = model.samples
        dq, errors = self.offsets(model.robot, samples.q, samples.stamp, samples.extra)
        padded = np.zeros((len(dq), model.n_geometric))
        padded[:, :errors.shape[1]] = errors  # sensor models append their frames after the D-H errors
        return EffectModel(model.base, model.effects, model.bases, Fixed(dq, padded))

    def predict(self, model: EffectModel) -> np.ndarray:
        """The compensated prediction (P,C,D) of ``model``'s poses (the model of
        the diagnosis, on any samples) at the compensator's own values."""
        if tuple(model.names) != self.names:
            raise InputError("compensator", f"made for the model {', '.join(self.names[-3:])}..., not "
                                            f"{', '.join(model.names[-3:])}...")
        return self.apply(model).residuals(self.values, False).predicted

    def to_json(self) -> dict:
        return {"version": VERSION, "inputs": list(self.inputs), "targets": list(self.targets),
                "used": self.used.tolist(), "mean": self.basis.mean.tolist(), "std": self.basis.std.tolist(),
                "knots": self.basis.knots.tolist(), "pairs": self.basis.pairs.tolist(), "size": self.basis.size,
                "coef": self.coef.tolist(), "heldout_gain": self.heldout_gain,
                "model": {"names": list(self.names), "values": self.values.tolist()}}

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=1))


def backfit(detection: Detection, model: EffectModel, x: np.ndarray, options: EstimateOptions,
            noise: NoiseModel) -> Compensator:
    """The compensator and the model's values fitted together by backfitting:
    the model refitted with the compensation's offsets fixed, the regression
    refitted to the residual the model alone leaves, BACKFIT times (the
    geometric errors had absorbed part of what the compensation now carries)."""
    regression = detection.regression
    names, z = input_table(model.samples.q, model.samples.stamp, dict(model.samples.extra))
    z = z[:, [names.index(n) for n in detection.inputs]]
    compensator = Compensator.of(regression, detection, model.names, x)
    for _ in range(BACKFIT):
        x = estimate_model(compensator.apply(model), replace(options, restarts=0), None, x).values
        X, y, _, _ = design(model.names, model.residuals(x, True), noise, z)
        regression = clone(regression).fit(X, y.ravel())
        compensator = Compensator.of(regression, detection, model.names, x)
    return replace(compensator, values=estimate_model(compensator.apply(model), replace(options, restarts=0), None,
                                                      x).values)


def load_compensator(path: str | Path) -> Compensator:
    """A compensator file (module docstring); InputError naming the file and key on bad input."""
    try:
        data = json.loads(Path(path).read_text())
        version = data.get("version")
        if version not in READABLE:
            raise InputError(str(path), f"compensator version {version!r}, expected one of "
                                        f"{', '.join(map(str, READABLE))}")
        key = "coef_rad" if version == 1 else "coef"
        basis = Basis(np.array(data["mean"], float), np.array(data["std"], float), np.array(data["knots"], float),
                      np.array(data["pairs"], int).reshape(-1, 2), float(data["size"]))
        coef = np.array(data[key], float)
        used = np.array(data["used"], bool)
        compensator = Compensator(tuple(data["inputs"]), tuple(data["targets"]), used, basis, coef,
                                  float(data["heldout_gain"]), tuple(data["model"]["names"]),
                                  np.array(data["model"]["values"], float))
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise InputError(str(path), f"not a compensator file ({error})") from None
    if coef.shape != (int(used.sum()), basis(np.zeros((1, len(compensator.inputs)))).shape[1]):
        raise InputError(f"{path}: {key}", f"shape {coef.shape} does not match the inputs and targets")
    return compensator
