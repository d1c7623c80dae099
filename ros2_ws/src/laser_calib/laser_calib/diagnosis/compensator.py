"""The learned compensator: the detector's regression, kept as a last stage.

After the physical effects, what remains may still follow the inputs
smoothly (detector.py). The detector's regression refitted on all calibration
poses gives, per pose, a joint-angle offset f_j(z) of each joint and a twist,
length and offset change of each link, from the pose's inputs z (readings, move directions
and sizes, stamp, extra columns). It is kept only when the detector's held-out gain is
significant (the test that decides it held each pose out), it never replaces
a physical effect (the report lists it apart, with its gain) and it acts
through the kinematics, so it applies to any pose and any measurement model:

    compensator = load_compensator("compensator.json")
    spots = compensator.predict(EffectModel(SpotModel(robot, samples), effects))   # (P,2,2)

with robot the nominal robot of the diagnosis and effects those of its
robot_calibrated.yaml (effects_from_robot): the file holds the geometric
errors and effect values refitted together with the compensation
(compensation.backfit, which also chose its basis), and the errors that fit held
at nominal, which a calibration applying it holds too (report.calibration.calibrate).

File (JSON, compensator.json of a diagnosis, version 3): inputs, targets
(theta_j are joint offsets, alpha_j, d_j and a_j offsets of the link's
parameters), the basis (standardisation, knots, pairs, size, and ``tensor``: a
pair as the products of its splines; versions 1 and 2, from before it, hold
the product of the readings), the model it completes (``model``: names, values and
``held``, absent from files written before it), the coefficients
``coef`` (m', b) of the directions used, in SI units (rad for theta_j and
alpha_j, m for d_j and a_j; version 1 files, from before the length
directions, hold only angles under ``coef_rad`` and still load); load it with
load_compensator(path), which checks the whole file when it reads it (every
key's type, shape and finite numbers: one InputError naming the file and key,
never an error deep in a fit). The moves (directions and sizes) are taken from the row order of
the samples it is applied to (from q = 0), as in the calibration. Applied to a
robot or model it was not made for (a target that is not the robot's, other
parameter names), it raises InputError saying what differs.
"""

from __future__ import annotations

import json
import math
import re
import reprlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from laser_calib.diagnosis.detector import LINK_DIRECTIONS, MIN_SPREAD, Basis, Detection, OffsetRegression, input_table
from laser_calib.effects.effect_model import EffectModel, Fixed
from laser_calib.io.errors import InputError
from laser_calib.model.robot import Robot

VERSION = 3
READABLE = (1, 2, 3)  # version 1: angle targets only, coefficients under "coef_rad"; 3: the key tensor
TARGET = re.compile(rf"(theta|{'|'.join(LINK_DIRECTIONS)})[1-9][0-9]*")  # detector.directions' names
JOINT_READING = re.compile(r"q[1-9][0-9]*")  # input_table's name of a joint reading


@dataclass(frozen=True)
class Compensator:
    """inputs (d,) names; targets (m,) parameter names; used (m,) the targets
    the regression has; coef (m', b) per basis function (rad or m, the target's unit); heldout_gain the
    detector's held-out gain of the regression (fraction of the whitened
    residual sum of squares); names and values (n,) of the model it completes
    (its geometric errors and effect parameters refitted with the compensation);
    source the file it was read from, which its errors name; held the errors its
    fit held at nominal (not determined by the data: applied without holding them,
    its offsets make such a pair barely separable, and the fit moves along it)."""

    inputs: tuple[str, ...]
    targets: tuple[str, ...]
    used: np.ndarray
    basis: Basis
    coef: np.ndarray
    heldout_gain: float
    names: tuple[str, ...] = ()
    values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    source: str = "compensator"
    held: tuple[str, ...] = ()   # of names, held at nominal in its fit: applied, it is held again

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
        self.check_targets(robot)
        names, z = input_table(q, stamp, dict(extra))
        missing = [k for k, n in enumerate(self.inputs) if n not in names]
        if missing:
            raise InputError(f"{self.source}: inputs[{missing[0]}]", f"'{self.inputs[missing[0]]}' is not a column "
                                                                     "of the samples (the compensator follows it)")
        values = self.values_at(z[:, [names.index(n) for n in self.inputs]])
        dq = np.zeros_like(np.asarray(q, float))
        errors = np.zeros((len(q), robot.n_params))
        for k, name in enumerate(self.targets):
            if name.startswith("theta"):
                dq[:, int(name[5:]) - 1] += values[:, k]
            else:
                errors[:, robot.param_names.index(name)] += values[:, k]
        return dq, errors

    def values_at(self, z: np.ndarray) -> np.ndarray:
        """Every target's offset (P,m) at inputs z (P,d); InputError naming the file where the
        standardised inputs or the offsets overflow (numbers of the file far beyond the inputs':
        scikit-learn would refuse the infinite inputs, the fit the NaN offsets, neither naming it)."""
        values = np.zeros((len(z), len(self.targets)))
        with np.errstate(all="ignore"):  # numpy's warnings would be lines beside the error
            finite = np.isfinite((z - self.basis.mean) / self.basis.std).all()
            if finite:
                values[:, self.used] = self.basis(z) @ self.coef.T
        if not (finite and np.isfinite(values).all()):
            raise InputError(self.source, "its offsets overflow at these poses (mean, std or coef far beyond the "
                                          "inputs' range)")
        return values

    def check_targets(self, robot: Robot) -> None:
        """InputError at the first target that is not a parameter of ``robot`` (a joint offset
        theta_j of one of its joints, or one of its parameter names), before any offset is indexed."""
        for k, name in enumerate(self.targets):
            if not _is_target_of(name, robot):
                raise InputError(f"{self.source}: targets[{k}]", f"'{name}' is not a parameter of robot "
                                                                 f"'{robot.name}' (joints 1..{robot.n_joints})")

    def check_model(self, model: EffectModel) -> None:
        """InputError naming the file when ``model`` is not the one the compensator was made for
        (its values are that model's): the parameter counts and the names only one of them has."""
        this = tuple(model.names)
        if this != self.names:
            raise InputError(self.source, f"made for a {len(self.names)}-parameter model, not this "
                                          f"{len(this)}-parameter one of robot '{model.robot.name}' "
                                          f"({_difference(self.names, this)})")

    def apply(self, model: EffectModel) -> EffectModel:
        """The model with the compensation's offsets on its poses (InputError when it is
        not the model the compensator was made for, check_model)."""
        self.check_model(model)
        samples = model.samples
        dq, errors = self.offsets(model.robot, samples.q, samples.stamp, samples.extra)
        padded = np.zeros((len(dq), model.n_geometric))
        padded[:, :errors.shape[1]] = errors  # sensor models append their frames after the D-H errors
        return EffectModel(model.base, model.effects, model.bases, Fixed(dq, padded))

    def predict(self, model: EffectModel) -> np.ndarray:
        """The compensated prediction (P,C,D) of ``model``'s poses (the model of
        the diagnosis, on any samples) at the compensator's own values."""
        return self.apply(model).residuals(self.values, False).predicted

    def to_json(self) -> dict:
        return {"version": VERSION, "inputs": list(self.inputs), "targets": list(self.targets),
                "used": self.used.tolist(), "mean": self.basis.mean.tolist(), "std": self.basis.std.tolist(),
                "knots": self.basis.knots.tolist(), "pairs": self.basis.pairs.tolist(), "size": self.basis.size,
                "tensor": self.basis.tensor,
                "coef": self.coef.tolist(), "heldout_gain": self.heldout_gain,
                "model": {"names": list(self.names), "values": self.values.tolist(), "held": list(self.held)}}

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=1))


def load_compensator(path: str | Path) -> Compensator:
    """A compensator file (module docstring), checked whole when it is read: each problem is
    one InputError naming the file and key (a damaged or hand-edited file would otherwise
    fail deep in a fit, in numpy's or scikit-learn's words, or not at all)."""
    source = str(path)
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError, RecursionError) as error:
        raise InputError(source, f"not a compensator file ({error})") from None
    if not isinstance(data, dict):
        raise InputError(source, f"not a compensator file (expected a JSON object, not {reprlib.repr(data)})")
    file = _Fields(source, data)
    version = file["version"]
    if isinstance(version, bool) or version not in READABLE:
        raise file.error("version", f"{reprlib.repr(version)}, expected one of {', '.join(map(str, READABLE))}")
    inputs = _inputs(file)
    targets = _targets(file)
    basis = _basis(file, inputs, version)
    used = _flags(file["used"], file.where("used"), len(targets))
    key = "coef_rad" if version == 1 else "coef"
    coef = _array(file[key], file.where(key), ((int(used.sum()), "one row per used target"),
                                               (basis.width, "one per basis function")))
    names, values, held = _model(file)
    gain = _number(file["heldout_gain"], file.where("heldout_gain"))
    if not 0 < gain <= 1:  # a share of the residual sum of squares, kept only when above 0
        raise file.error("heldout_gain", f"{gain:g}, expected above 0 and at most 1 (a share of the residual)")
    return Compensator(inputs, targets, used, basis, coef, gain, names, values, source, held)


@dataclass(frozen=True)
class _Fields:
    """A JSON object of a compensator file, its keys prefixed (``model.``) in the errors that name them."""

    source: str
    data: dict
    prefix: str = ""

    def where(self, key: str) -> str:
        return f"{self.source}: {self.prefix}{key}"

    def error(self, key: str, problem: str) -> InputError:
        return InputError(self.where(key), problem)

    def __getitem__(self, key: str) -> object:
        if key not in self.data:
            raise InputError(self.source, f"no key '{self.prefix}{key}' (every compensator file has it)")
        return self.data[key]


def _inputs(file: _Fields) -> tuple[str, ...]:
    """The input names: at least one (the basis has a column per input)."""
    inputs = _names(file["inputs"], file.where("inputs"))
    if not inputs:
        raise file.error("inputs", "empty (a compensator follows at least one input)")
    return inputs


def _targets(file: _Fields) -> tuple[str, ...]:
    """The target names, each a direction the detector fits (offsets() reads its joint from the name)."""
    targets = _names(file["targets"], file.where("targets"))
    for k, name in enumerate(targets):
        if not TARGET.fullmatch(name):
            raise file.error(f"targets[{k}]", f"{name!r} is not a target (theta_j, "
                                              f"{', '.join(f'{kind}_j' for kind in LINK_DIRECTIONS)}; j = 1, 2, ...)")
    return targets


def _basis(file: _Fields, inputs: tuple[str, ...], version: int) -> Basis:
    """The basis: standardisation and knots per input, pairs of joint readings, size and (version 3)
    tensor, such that Basis evaluates it (a positive spread, increasing knots, pairs of existing columns)."""
    per_input = ((len(inputs), "one per input"),)
    mean = _array(file["mean"], file.where("mean"), per_input)
    std = _array(file["std"], file.where("std"), per_input)
    small = np.flatnonzero(std <= MIN_SPREAD)
    if len(small):
        raise file.error(f"std[{small[0]}]", f"{std[small[0]]:g}, expected above {MIN_SPREAD:g} (it divides "
                                             f"input {inputs[small[0]]})")
    knots = _array(file["knots"], file.where("knots"), ((None, "one row per knot"),) + per_input)
    if len(knots) < 2:
        raise file.error("knots", f"{_count(len(knots), 'row')}, expected at least 2 (a spline's first and last "
                                  "knot)")
    rows, columns = np.nonzero(np.diff(knots, axis=0) <= 0)
    if len(rows):
        r, c = rows[0] + 1, columns[0]
        raise file.error(f"knots[{r}][{c}]", f"{knots[r, c]:g} is not above knots[{r - 1}][{c}] = {knots[r - 1, c]:g} "
                                             f"(the knots of input {inputs[c]} increase)")
    size = _number(file["size"], file.where("size"))
    if size <= 0:
        raise file.error("size", f"{size:g}, expected above 0 (it divides the features)")
    tensor = file["tensor"] if version >= 3 else False
    if not isinstance(tensor, bool):
        raise file.error("tensor", f"expected true or false, not {reprlib.repr(tensor)}")
    return Basis(mean, std, knots, _pairs(file["pairs"], file.where("pairs"), inputs), size, tensor)


def _model(file: _Fields) -> tuple[tuple[str, ...], np.ndarray, tuple[str, ...]]:
    """The names and values of the model the compensator completes (predict's values), and the
    names its fit held (none in a file from before the key)."""
    model = file["model"]
    if not isinstance(model, dict):
        raise file.error("model", f"expected an object with names and values, not {reprlib.repr(model)}")
    fields = _Fields(file.source, model, "model.")
    names = _names(fields["names"], fields.where("names"))
    values = _array(fields["values"], fields.where("values"), ((len(names), "one per name of model.names"),))
    held = _names(model.get("held", []), fields.where("held"))
    unknown = [name for name in held if name not in names]
    if unknown:
        raise fields.error("held", f"'{unknown[0]}' is not one of model.names")
    return names, values, held


def _names(value: object, where: str) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(name, str) for name in value):
        raise InputError(where, f"expected a list of names, not {reprlib.repr(value)}")
    return tuple(value)


def _flags(value: object, where: str, length: int) -> np.ndarray:
    """used: a true/false per target (a boolean mask: numbers would index instead)."""
    if not isinstance(value, list) or not all(isinstance(flag, bool) for flag in value):
        raise InputError(where, f"expected a list of true/false (one per target), not {reprlib.repr(value)}")
    if len(value) != length:
        raise InputError(where, f"{_count(len(value), 'value')}, expected {length} (one per target)")
    return np.array(value, bool).reshape(length)


def _pairs(value: object, where: str, inputs: tuple[str, ...]) -> np.ndarray:
    """(np, 2) the pairs [i, j]: indices of joint-reading inputs, the columns Basis multiplies."""
    readings = [k for k, name in enumerate(inputs) if JOINT_READING.fullmatch(name)]
    if not isinstance(value, list):
        raise InputError(where, f"expected a list of [i, j] pairs, not {reprlib.repr(value)}")
    for p, pair in enumerate(value):
        if not (isinstance(pair, list) and len(pair) == 2):
            raise InputError(f"{where}[{p}]", f"expected a pair [i, j] of input indices, not {reprlib.repr(pair)}")
        for side, k in enumerate(pair):
            if isinstance(k, bool) or not isinstance(k, int) or k not in readings:
                named = ", ".join(f"{i} ({inputs[i]})" for i in readings) or "none"
                raise InputError(f"{where}[{p}][{side}]", f"{reprlib.repr(k)} is not the index of a joint reading "
                                                          f"among the inputs ({named})")
    return np.array(value, int).reshape(-1, 2)


def _array(value: object, where: str, shape: tuple[tuple[int | None, str], ...]) -> np.ndarray:
    """value, nested lists of finite numbers of ``shape`` (per axis its length, None for any,
    and what it counts), as floats; InputError at the first element (where[i][j]) that is not."""
    if not shape:
        return np.array(_number(value, where))
    (length, counts), inner = shape[0], shape[1:]
    if not isinstance(value, list):
        raise InputError(where, f"expected a list ({counts}), not {reprlib.repr(value)}")
    if length is not None and len(value) != length:
        raise InputError(where, f"{_count(len(value), 'row' if inner else 'value')}, expected {length} ({counts})")
    items = [_array(item, f"{where}[{k}]", inner) for k, item in enumerate(value)]
    return np.array(items, float).reshape(len(value), *(n for n, _ in inner))


def _number(value: object, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(where, f"not a number ({reprlib.repr(value)})")
    try:
        number = float(value)
    except OverflowError:  # a JSON integer beyond float's range
        number = math.inf
    if not math.isfinite(number):
        raise InputError(where, f"not a finite number ({reprlib.repr(value)})")
    return number


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def _is_target_of(name: str, robot: Robot) -> bool:
    """theta_j offsets the reading of joint j (offsets' dq); the other targets are parameter names."""
    if name.startswith("theta"):
        return int(name[5:]) <= robot.n_joints
    return name in robot.param_names


def _difference(made: tuple[str, ...], this: tuple[str, ...]) -> str:
    """The parameter names only one of two models has (a few each), or that their order differs."""
    def few(names: list[str]) -> str:
        return ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")

    only_this, only_made = [n for n in this if n not in made], [n for n in made if n not in this]
    said = ([f"only this one has {few(only_this)}"] if only_this else []) + (
        [f"only that one has {few(only_made)}"] if only_made else [])
    return "; ".join(said) or "the same names in another order"
