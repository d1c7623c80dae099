"""The data protocol of the diagnosis engine, and the laser-spot data set."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from laser_calib.diagnosis.structure import Readings, Series, spot_covariates, spot_responses
from laser_calib.effects.base import SPOT, Effect
from laser_calib.effects.catalog import candidates
from laser_calib.effects.effect_model import EffectModel
from laser_calib.estimation.estimate import Estimate, EstimateOptions, estimate
from laser_calib.io.samples import Samples
from laser_calib.measurement.base import NoiseModel, Residuals, RobotModel
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.kinematics import forward
from laser_calib.model.robot import Robot

class Data(Protocol):
    """A calibration data set as the engine sees it (SpotData here,
    sensor_data.SensorData for point and pose sensors).

    robot and samples (readings q (P,N), stamp (P,), extra columns); fixed:
    parameter names of the base model held at their nominal values in every
    fit; base(): the base measurement model on all P poses (its subset(index)
    gives the folds); candidates(): the effects to select from (those the base
    model cannot carry are dropped by the engine); subset(index): the same
    data on the poses ``index``; measured_values(): the
    number of measured values; screen(options): the geometric estimate that
    `estimate` runs on these samples (its refused units: diagnosis.screening);
    without(units): the same data with the units (P,C) not seen; series(): the
    measurement-level responses and covariates of the verdict's structure tests.
    """

    robot: Robot
    samples: Readings
    fixed: tuple[str, ...]

    def base(self) -> RobotModel: ...

    def subset(self, index: np.ndarray) -> "Data": ...

    def candidates(self) -> list[Effect]: ...

    def measured_values(self) -> int: ...

    def screen(self, options: EstimateOptions) -> Estimate: ...

    def without(self, units: np.ndarray) -> "Data": ...

    def series(self, model: EffectModel, x: np.ndarray, res: Residuals, noise: NoiseModel
               ) -> tuple[list[Series], list[Series]]: ...


@dataclass(frozen=True)
class SpotData:
    """Laser spots on the screen (SpotModel): the whole effect library, spot
    effects included; the spot-level series (effects.residuals)."""

    robot: Robot
    samples: Samples
    fixed: tuple[str, ...] = ()

    def base(self) -> SpotModel:
        return SpotModel(self.robot, self.samples)

    def subset(self, index: np.ndarray) -> "SpotData":
        return SpotData(self.robot, self.samples.subset(index), self.fixed)

    def candidates(self) -> list[Effect]:
        return candidates(self.robot, self.samples)

    def measured_values(self) -> int:
        return 2 * int(self.samples.seen.sum())

    def screen(self, options: EstimateOptions) -> Estimate:
        return estimate(self.robot, self.samples, options)

    def without(self, units: np.ndarray) -> "SpotData":
        return SpotData(self.robot, self.samples.without(units), self.fixed)

    def series(self, model: EffectModel, x: np.ndarray, res: Residuals, noise: NoiseModel
               ) -> tuple[list[Series], list[Series]]:
        errors, dq = model.offsets(x)
        q = self.samples.q if dq is None else self.samples.q + dq
        beams = forward(self.robot, q, errors).beams
        return spot_responses(res, noise, beams), spot_covariates(self.samples, res.predicted, beams)


def supports(base: RobotModel, effect: Effect) -> bool:
    """Whether the base model can carry the effect: spot effects need spots."""
    return effect.family != SPOT or base.measures_spots


