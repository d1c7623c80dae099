"""The paper's measurement: the two laser spots on the screen plane x = 0 of frame {0}."""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from laser_calib.io.samples import Samples
from laser_calib.measurement.base import Residuals, robot_scales
from laser_calib.model.kinematics import joint_jacobian, predict
from laser_calib.model.robot import Robot


class SpotModel:
    """The paper's model: spots of the two lasers from the geometric errors
    (a measurement.RobotModel)."""

    measures_spots: ClassVar[bool] = True

    def __init__(self, robot: Robot, samples: Samples):
        if samples.n_joints != robot.n_joints:
            raise ValueError(f"samples have {samples.n_joints} joints, robot {robot.n_joints}")
        self.robot = robot
        self.samples = samples
        self.names = robot.param_names
        self.scales = robot_scales(robot)
        self._last: tuple | None = None

    def residuals(self, x: np.ndarray, jacobian: bool = True) -> Residuals:
        return self.evaluate(x, None, jacobian)

    def subset(self, index) -> "SpotModel":
        """The model on the poses ``index`` (mask, indices or slice)."""
        return SpotModel(self.robot, self.samples.subset(index))

    def evaluate(self, errors: np.ndarray, dq: np.ndarray | None, jacobian: bool = True) -> Residuals:
        """Residuals with errors (n,) or per pose (P,n), and joint offsets dq (P,N)
        added to the readings (effects use this: the Jacobians then hold at the
        offset pose, and jac_q is d predicted / d q there)."""
        # Estimators often ask twice for the same point (identifiability, then the fit's start).
        key = (np.asarray(errors).tobytes(), None if dq is None else dq.tobytes(), jacobian)
        if self._last is not None and self._last[0] == key:
            return self._last[1]
        q = self.samples.q if dq is None else self.samples.q + dq
        prediction = predict(self.robot, q, errors, jacobian=jacobian)
        res = spot_residuals(self.samples, prediction.spots, prediction.k, prediction.jacobian,
                             self.robot, jacobian)
        self._last = (key, res)
        return res


def spot_residuals(samples: Samples, predicted: np.ndarray, k: np.ndarray, jac: np.ndarray | None,
                   robot: Robot, jacobian: bool) -> Residuals:
    """Residuals of measured spots; a spot counts where it was seen and the
    predicted beam meets the screen plane in front of the laser (k > 0).
    jac (P,2,2,n), predict's own array, is zeroed in place where a spot does not count."""
    valid = samples.seen & np.isfinite(predicted).all(axis=-1) & (k > 0)
    r = np.where(valid[..., None], np.nan_to_num(samples.spots - predicted), 0.0)
    jac_q = None
    if jacobian:
        jac[~valid] = 0.0  # predict's own array: only the invalid rows are written
        if not np.isfinite(jac.sum()):  # rare: one sum (a NaN or inf anywhere makes it so) for nan_to_num's passes
            jac = np.nan_to_num(jac)
        jac_q = joint_jacobian(robot, jac)
    return Residuals(r, valid, jac, jac_q, predicted)
