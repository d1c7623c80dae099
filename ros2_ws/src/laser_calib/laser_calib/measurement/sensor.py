"""Point and pose measurement models (MeasurementModel protocol, measurement.py).

Both close the loop of chain.py and compose the twists of the target frame
(relative to the sensor, in sensor coordinates) with a small measurement block,
as the spot model composes Jac_1 with Jac_2:

- PointModel (laser tracker, motion-capture marker): the marker at the target
  origin, in the sensor frame. C = 1 channel, D = 3 values (m). Its block is
  the marker's motion, v (the target origin's twist already carries it there).
- PoseModel (a camera observing a target): the relative transform
  E = inv(predicted) · measured as (translation, rotation vector), both in the
  predicted target frame (the metric of industrial_calibration). D = 6. Moving
  the predicted target by (v; w) in sensor coordinates changes them by
      dt_E = -R^T (v + w x (t_meas - t)),   dphi_E = -J_l^-1(phi_E) R^T w,
  so the block (d predicted = -d residual) is [R^T (v + w x (t_meas - t));
  J_l^-1 R^T w]. The rotation values are multiplied by ``rotation_length``
  (m/rad) so that one noise sigma (m) serves all six: an angle error of
  sigma / rotation_length rad weighs like a position error of sigma.

With ``scale=True`` the sensor's length scale per axis is estimated too
(names scale_x, scale_y, scale_z, dimensionless): the sensor reports a
position p as (1 + s) * p per axis of its frame (a tracker's scale error, a
camera's depth scale from its focal length); orientations are unaffected. A
scale common to all axes is only observable when the arm has a known length
the frames do not absorb.

Residuals are measured - predicted in the sense of the estimators:
r(x + dx) = r(x) - jac dx. Parameters (chain.py): robot errors, then the
sensor, base and target frames; PointModel drops the target's rotations, which
a point cannot see. ``evaluate(params, dq)`` takes per-pose parameters (P,n)
and joint offsets (P,N) as SpotModel.evaluate does, for effect models.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from laser_calib.model.kinematics import joint_jacobian
from laser_calib.measurement.base import ANGLE_SCALE, LENGTH_SCALE, Residuals, robot_scales
from laser_calib.model.robot import Robot
from laser_calib.measurement.chain import chain_names, target_in_sensor
from laser_calib.measurement.frames import FRAME_PARAMS, frame_list, robot_frames
from laser_calib.measurement.rotations import left_jacobian_inverse, log_rotation, quaternion_to_matrix
from laser_calib.io.sensor_samples import SensorSamples

FRAME_SCALES = np.where(np.arange(6) < 3, LENGTH_SCALE, ANGLE_SCALE)
SCALE_NAMES = ("scale_x", "scale_y", "scale_z")
SCALE_SCALE = 1e-3  # characteristic size of a scale error: 0.1 % (1 mm at 1 m)


class _SensorModel:
    """What both sensor models share: the robot, its frame guesses, the samples
    and the map from the model's parameters into the full chain vector
    (each model a measurement.RobotModel)."""

    measures_spots: ClassVar[bool] = False

    def __init__(self, robot: Robot, samples: SensorSamples, kind: str, scale: bool):
        if samples.n_joints != robot.n_joints:
            raise ValueError(f"samples have {samples.n_joints} joints, robot {robot.n_joints}")
        if samples.kind != kind:
            raise ValueError(f"{kind} model needs {kind} samples, got {samples.kind} samples")
        self.robot = robot
        self.samples = samples
        self.frames = robot_frames(robot)
        self.tips = _tips(robot, samples)
        full = chain_names(robot)
        targets = frame_list(robot)[2:]
        drop = {f"{t}_{p}" for t in targets for p in FRAME_PARAMS[3:]} if kind == "point" else set()
        self.index = np.array([i for i, name in enumerate(full) if name not in drop])
        self.scale = scale
        self.names = tuple(full[i] for i in self.index) + (SCALE_NAMES if scale else ())
        chain_scales = np.concatenate([robot_scales(robot), np.tile(FRAME_SCALES, len(frame_list(robot)))])[self.index]
        self.scales = np.concatenate([chain_scales, np.full(3 if scale else 0, SCALE_SCALE)])
        self.n_full = len(full)

    def residuals(self, x: np.ndarray, jacobian: bool = True) -> Residuals:
        return self.evaluate(x, None, jacobian)

    def subset(self, index) -> "_SensorModel":
        """The same model (weights, scale option) on the poses ``index``."""
        return self._with(self.samples.subset(index))

    def _state(self, params: np.ndarray, dq: np.ndarray | None, jacobian: bool):
        """The chain's target state, and (1 + s) per pose and sensor axis (P,3)."""
        params = np.asarray(params, float)
        n_chain = len(self.index)
        full = np.zeros(params.shape[:-1] + (self.n_full,))
        full[..., self.index] = params[..., :n_chain]
        q = self.samples.q if dq is None else self.samples.q + dq
        stretch = np.broadcast_to(1.0 + params[..., n_chain:] if self.scale else np.ones(3), (len(q), 3))
        return target_in_sensor(self.robot, self.frames, q, full, jacobian, self.tips), stretch

    def _scale_columns(self, jac: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """Append the scale columns (P,D,3) to the chain Jacobian (P,D,n_chain) if estimated."""
        return np.concatenate([jac, columns], axis=-1) if self.scale else jac

    def _finish(self, r: np.ndarray, jac: np.ndarray | None, predicted: np.ndarray) -> Residuals:
        """Zero invalid rows; shapes (P,1,D), (P,1,D,n); jac_q from the joint columns."""
        valid = (self.samples.seen & np.isfinite(r).all(axis=1))[:, None]
        r = np.where(valid[..., None], np.nan_to_num(r[:, None]), 0.0)
        jac_q = None
        if jac is not None:
            jac = np.where(valid[..., None, None], jac[:, None], 0.0)
            jac_q = joint_jacobian(self.robot, jac)
        return Residuals(r, valid, jac, jac_q, predicted[:, None])


def _tips(robot: Robot, samples: SensorSamples) -> np.ndarray | None:
    """(P,) the tip each pose measures: the samples' ``tip`` column (0, 1, ... in
    the order of the robot's tips), required for a tree and refused without one."""
    n_tips = 1 if robot.chain is None else len(robot.chain.tips)
    if "tip" not in samples.extra:
        if n_tips > 1:
            raise ValueError(f"samples need a 'tip' column (0..{n_tips - 1}): the robot has {n_tips} tips")
        return None
    tips = samples.extra["tip"]
    if not np.isin(tips, np.arange(n_tips)).all():
        bad = int(np.flatnonzero(~np.isin(tips, np.arange(n_tips)))[0])
        raise ValueError(f"pose {int(samples.pose[bad])}: tip {tips[bad]:g} is not one of 0..{n_tips - 1}")
    return tips.astype(int)


class PointModel(_SensorModel):
    """A marker at the target origin measured in the sensor frame (P,1,3), m."""

    def __init__(self, robot: Robot, samples: SensorSamples, scale: bool = False):
        super().__init__(robot, samples, "point", scale)

    def _with(self, samples: SensorSamples) -> "PointModel":
        return PointModel(self.robot, samples, self.scale)

    def evaluate(self, params: np.ndarray, dq: np.ndarray | None, jacobian: bool = True) -> Residuals:
        """params (n,) or (P,n); dq (P,N) rad added to the readings, or None."""
        state, stretch = self._state(params, dq, jacobian)
        predicted = stretch * state.position
        jac = None
        if state.twists is not None:
            chain = stretch[:, :, None] * state.twists[:, :3][..., self.index]
            jac = self._scale_columns(chain, state.position[:, :, None] * np.eye(3))
        return self._finish(self.samples.position - predicted, jac, predicted)


class PoseModel(_SensorModel):
    """A target pose measured in the sensor frame: residual (P,1,6) as
    translation (m) and rotation vector x rotation_length (m/rad)."""

    def __init__(self, robot: Robot, samples: SensorSamples, rotation_length: float = 1.0, scale: bool = False):
        super().__init__(robot, samples, "pose", scale)
        if not (np.isfinite(rotation_length) and rotation_length > 0):
            raise ValueError(f"rotation_length must be a positive number of m/rad, got {rotation_length}")
        self.rotation_length = float(rotation_length)
        self.measured_rotation = quaternion_to_matrix(np.nan_to_num(samples.quaternion, nan=1.0))

    def _with(self, samples: SensorSamples) -> "PoseModel":
        return PoseModel(self.robot, samples, self.rotation_length, self.scale)

    def evaluate(self, params: np.ndarray, dq: np.ndarray | None, jacobian: bool = True) -> Residuals:
        """params (n,) or (P,n); dq (P,N) rad added to the readings, or None."""
        state, stretch = self._state(params, dq, jacobian)
        to_target = state.rotation.transpose(0, 2, 1)
        position = stretch * state.position                                  # as the sensor reports it
        offset = self.samples.position - position                            # t_meas - t, sensor frame
        phi = log_rotation(to_target @ self.measured_rotation)               # rotation of E
        r = np.concatenate([np.einsum("pij,pj->pi", to_target, offset), phi * self.rotation_length], axis=1)
        predicted = np.concatenate([position, log_rotation(state.rotation) * self.rotation_length], axis=1)
        jac = None
        if state.twists is not None:
            v, w = state.twists[:, :3][..., self.index], state.twists[:, 3:][..., self.index]
            at_measured = stretch[:, :, None] * v + np.cross(w, np.nan_to_num(offset)[:, :, None], axis=1)
            rot = left_jacobian_inverse(phi) @ to_target @ w
            chain = np.concatenate([to_target @ at_measured, rot * self.rotation_length], axis=1)
            scale = to_target * state.position[:, None, :]                   # column a: R^T e_a t_a
            jac = self._scale_columns(chain, np.concatenate([scale, np.zeros_like(scale)], axis=1))
        return self._finish(r, jac, predicted)
