"""Measurement models, the shape every one has: what the estimators fit.

A measurement model turns a parameter vector x (n,) into residuals
``measured - predicted`` over P poses, C channels per pose (the two lasers) and
D values per channel (spot y, z), with the Jacobians the estimators need.
The geometric spot model is the paper's; effects and other sensors add models
of the same shape, so every estimator, the identifiability analysis and the
diagnosis run on all of them unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import numpy as np

from laser_calib.model.robot import Robot

# Characteristic sizes of one error: the paper's simulated error (10 mm, 1 deg).
# They scale the parameters for damping and rank decisions and are the default
# manufacturing tolerance of --prior.
LENGTH_SCALE = 0.010
ANGLE_SCALE = np.deg2rad(1.0)


@dataclass(frozen=True)
class Residuals:
    """r (P,C,D) measured - predicted, 0 where invalid; valid (P,C);
    jac (P,C,D,n) d predicted / d x; jac_q (P,C,D,N) d predicted / d q_i."""

    r: np.ndarray
    valid: np.ndarray
    jac: np.ndarray | None
    jac_q: np.ndarray | None
    predicted: np.ndarray


class MeasurementModel(Protocol):
    """What the estimators fit: named parameters and their residuals."""

    names: tuple[str, ...]
    scales: np.ndarray  # (n,) characteristic size of each parameter, in its unit

    def residuals(self, x: np.ndarray, jacobian: bool = True) -> Residuals: ...


class RobotModel(MeasurementModel, Protocol):
    """A measurement model of a robot's readings: what effects
    (effects.EffectModel) and the diagnosis build on.

    robot and samples (readings q (P,N), stamp (P,), extra columns, in
    measurement order); evaluate(params, dq, jacobian): the residuals with the
    model's parameters (n,) or per pose (P,n) and joint offsets dq (P,N) or
    None added to the readings, jac_q (P,C,D,N) filled whenever jacobian is
    True; subset(index): the same model on the poses ``index`` (mask or
    indices); measures_spots: the residuals are laser spots on the screen
    (only then can spot effects, screen shape and lens, act on them).
    """

    robot: Robot
    samples: Any
    measures_spots: ClassVar[bool]

    def evaluate(self, params: np.ndarray, dq: np.ndarray | None, jacobian: bool = True) -> Residuals: ...

    def subset(self, index) -> "RobotModel": ...


def robot_scales(robot) -> np.ndarray:
    """(n_params,) characteristic sizes of a robot's parameters (D-H or joint placements)."""
    return np.where(robot.param_kinds() == "length", LENGTH_SCALE, ANGLE_SCALE)


@dataclass(frozen=True)
class NoiseModel:
    """Measurement noise: sigma (m) per measured value, and joint-reading noise
    joint_sigma (rad, scalar or (N,)) propagated through the joint Jacobian, so a
    pose's two spots are correlated as the joint disturbance makes them."""

    sigma: float
    joint_sigma: float | np.ndarray = 0.0

    @property
    def joint_noise(self) -> bool:
        """Some joint-reading noise: a joint sigma above 0."""
        return bool(np.any(np.asarray(self.joint_sigma) > 0))

    def for_poses(self, index: slice) -> "NoiseModel":
        """The noise model of a block of poses (solvers go by blocks); the same for
        every pose here, per pose where a subclass weighs them (robust.WeightedNoise)."""
        return self

    def whitener(self, residuals: Residuals) -> np.ndarray:
        """(P,CD,CD) inverse Cholesky factors of each pose's covariance.

        Invalid values get unit variance and no correlation; their residual and
        Jacobian rows are zero, so they contribute nothing after whitening.
        """
        r = residuals.r
        n_poses, channels, dims = r.shape
        m = channels * dims
        mask = np.repeat(residuals.valid, dims, axis=1)  # (P, CD)
        if not (self.joint_noise and residuals.jac_q is not None):
            # diagonal: 1 / sigma on the measured values, 1 elsewhere (as the Cholesky
            # factor of the covariance below and its inverse give it, bit for bit)
            out = np.zeros((n_poses, m, m))
            np.einsum("pii->pi", out)[...] = np.where(mask, 1.0 / np.sqrt(self.sigma ** 2), 1.0)
            return out
        cov = np.broadcast_to(np.eye(m) * self.sigma ** 2, (n_poses, m, m)).copy()
        jq = residuals.jac_q.reshape(n_poses, m, -1) * mask[..., None]
        joint_sigma = np.broadcast_to(np.asarray(self.joint_sigma, dtype=float), (jq.shape[-1],))
        cov += np.einsum("pin,n,pjn->pij", jq, joint_sigma ** 2, jq)
        cov[~mask] = 0.0
        cov.transpose(0, 2, 1)[~mask] = 0.0
        idx = np.nonzero(~mask)
        cov[idx[0], idx[1], idx[1]] = 1.0
        chol = np.linalg.cholesky(cov)
        return np.linalg.inv(chol)


def whiten(residuals: Residuals, whitener: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Stacked whitened residuals (M,) and Jacobian (M,n), M = P*C*D."""
    n_poses = residuals.r.shape[0]
    diagonal = np.einsum("pii->pi", whitener)                                # (P,CD)
    if np.count_nonzero(whitener) == np.count_nonzero(diagonal):
        # values not correlated (no joint noise): a scale per row, the same numbers as the product
        r = (diagonal * residuals.r.reshape(n_poses, -1)).ravel()
        jac = None
        if residuals.jac is not None:
            flat = residuals.jac.reshape(n_poses, -1, residuals.jac.shape[-1])
            jac = (flat * diagonal[..., None]).reshape(-1, flat.shape[-1])
        return r, jac
    r = (whitener @ residuals.r.reshape(n_poses, -1, 1)).ravel()
    jac = None
    if residuals.jac is not None:
        flat = residuals.jac.reshape(n_poses, -1, residuals.jac.shape[-1])
        jac = (whitener @ flat).reshape(-1, flat.shape[-1])
    return r, jac


def count_values(residuals: Residuals) -> int:
    return int(residuals.valid.sum()) * residuals.r.shape[2]
