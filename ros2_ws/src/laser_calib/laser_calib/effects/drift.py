"""Drift of a link length with time or temperature (base.PARAM).

    Δx_j(pose) = rate (c(pose) - reference)

x_j a length of the geometric model (a_i, d_i, slm_x or slm_z), c the stamp (s)
or an extra column of the samples (e.g. temperature_c), reference the mean of c
over the calibration poses (so Δx_j of the geometric fit is the length at the
reference and the rate does not leak into it). rate is in m per unit of c.
Its characteristic scale is 1 mm over the calibration spread of c (the
peak-to-peak range), its typical truth 3 mm over that spread.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.model.robot import Robot
from laser_calib.io.samples import Samples
from laser_calib.effects.base import ParamEffect, positive_number, yaml_number

STAMP = "stamp"


def covariate_values(samples: Samples, name: str) -> np.ndarray:
    """(P,) the stamp or an extra column; one line naming the column if absent."""
    if name == STAMP:
        return samples.stamp
    if name not in samples.extra:
        raise InputError("samples", f"no column '{name}' (an effect in the model drifts with it)")
    return samples.extra[name]


def length_params(robot: Robot) -> np.ndarray:
    """Indices of the length errors in the geometric parameter vector (D-H or joint placements)."""
    return np.flatnonzero(robot.param_kinds() == "length")


@dataclass(frozen=True)
class Drift(ParamEffect):
    """Linear drift of geometric length ``param`` with covariate ``covariate``.

    ``reference`` and ``spread`` are fixed from the calibration data when the
    candidate is made and kept in the robot file, so a test set is predicted
    with the calibration's reference.
    """

    covariate: str
    reference: float
    spread: float
    param_name: str

    kind: ClassVar[str] = "drift"
    title: ClassVar[str] = "drift of a link length"
    params: ClassVar[tuple[str, ...]] = ("rate",)

    @property
    def units(self) -> tuple[str, ...]:  # type: ignore[override]
        return ("m/s",) if self.covariate == STAMP else (f"m per unit of {self.covariate}",)

    @property
    def where(self) -> str:
        return self.param_name

    @property
    def tag(self) -> str:
        return f"drift_{self.param_name}_{self.covariate}"

    @property
    def label(self) -> str:
        return f"drift ({self.param_name} with {self.covariate})"

    @property
    def scales(self) -> np.ndarray:
        return np.array([1e-3 / self.spread])

    @property
    def typical(self) -> np.ndarray:
        return np.array([3e-3 / self.spread])

    def constants(self) -> dict:
        return {"parameter": self.param_name, "covariate": self.covariate, "reference": self.reference,
                "spread": self.spread}

    def basis(self, robot: Robot, samples: Samples) -> np.ndarray:
        return (covariate_values(samples, self.covariate) - self.reference)[:, None]

    @classmethod
    def from_yaml(cls, robot: Robot, entry: Mapping[str, Any], where: str) -> "Drift":
        names = robot.param_names
        lengths = [names[j] for j in length_params(robot)]
        name = entry.get("parameter")
        if name not in lengths:
            raise InputError(f"{where}.parameter", f"expected a length ({', '.join(lengths)}), got {name!r}")
        covariate = entry.get("covariate")
        if not isinstance(covariate, str) or not covariate:
            raise InputError(f"{where}.covariate", f"expected a column name, got {covariate!r}")
        spread = positive_number(where, entry, "spread")
        return cls(param=names.index(name), covariate=covariate, reference=yaml_number(where, entry, "reference"),
                   spread=spread, param_name=name)

    @classmethod
    def make(cls, robot: Robot, samples: Samples, param_name: str, covariate: str) -> "Drift":
        """The candidate for one length and one covariate of the calibration samples."""
        values = covariate_values(samples, covariate)
        spread = float(np.ptp(values)) if len(values) else 0.0
        names = robot.param_names
        return cls(param=names.index(param_name), covariate=covariate, reference=float(np.mean(values)),
                   spread=spread if spread > 0 else 1.0, param_name=param_name)
