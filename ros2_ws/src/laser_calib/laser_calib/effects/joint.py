"""Joint effects: per-pose offsets dq_i of one joint angle, linear in the
parameters (base.JOINT). The true joint angle is the reading plus dq_i:

    theta_i = q_i + theta0_i + Δtheta_i + dq_i(pose)

Constant parts of dq_i are indistinguishable from Δtheta_i; the identifiability
analysis of the joint fit takes care of that (e.g. the cosine terms of a
periodic error at a joint that moves little).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

import numpy as np

from laser_calib.model.kinematics import forward
from laser_calib.model.robot import Robot
from laser_calib.io.samples import Samples
from laser_calib.effects.base import JointEffect, joint_name, move_directions, positive_number, yaml_joint

MRAD = 1e-3


@dataclass(frozen=True)
class JointScale(JointEffect):
    """Gear-ratio (encoder scale) error: dq_i = s q_i, s dimensionless.

    Scale 1e-3 (0.1 % of the reading, 1 mrad at 1 rad); typical truth 2e-3.
    """

    kind: ClassVar[str] = "joint_scale"
    title: ClassVar[str] = "gear-ratio (joint scale) error"
    params: ClassVar[tuple[str, ...]] = ("scale",)
    units: ClassVar[tuple[str, ...]] = ("1",)

    @property
    def scales(self) -> np.ndarray:
        return np.array([1e-3])

    @property
    def typical(self) -> np.ndarray:
        return np.array([2e-3])

    def basis(self, robot: Robot, samples: Samples) -> np.ndarray:
        return samples.q[:, self.joint:self.joint + 1].copy()


def gravity_torques(robot: Robot, q: np.ndarray) -> np.ndarray:
    """(P,N) static gravity torque about each joint axis, per unit lumped weight (m).

    Mass model: equal point masses at the points where the later joint axes
    meet their D-H frames and at the SLM origin; the masses of link i and of
    the links before it do not load joint i. Gravity is robot.gravity (unit
    vector in frame {0}, default -z). tau_i = u_i . sum_m (p_m - o_i) x g,
    u_i, o_i the axis and a point of joint i, at the readings q (P,N).
    """
    state = forward(robot, q)
    points = np.concatenate([state.joint_origin[:, 1:], state.origin[:, None]], axis=1)  # (P,N,3)
    # Sum over the masses beyond joint i: those at joints i+1..N and the SLM.
    beyond = np.cumsum(points[:, ::-1], axis=1)[:, ::-1]                                 # (P,N,3)
    count = np.arange(robot.n_joints, 0, -1)[None, :, None]
    arm = beyond - count * state.joint_origin
    g = np.asarray(robot.gravity, float)
    return np.einsum("pni,pni->pn", state.joint_axis, np.cross(arm, g))


@dataclass(frozen=True)
class Compliance(JointEffect):
    """Joint compliance under gravity: dq_i = c_i tau_i(q), c_i in rad/m.

    tau_i is the gravity torque of the links beyond joint i per unit lumped
    weight (gravity_torques: equal point masses at the later joints and the
    SLM, gravity robot.gravity). Neither the compliance nor the masses are
    known: c_i = compliance_i x m g is the one gain per joint the data can
    estimate. Torques are taken at the readings with the current geometric
    estimate (EffectModel recomputes the basis: errors of 10 mm / 1 deg change
    tau by several %); their change with the geometric errors is left out of
    the Jacobian (second order: c_i times that change). A positive c_i deflects
    the joint the way gravity pulls it.

    ``torque_span`` (m) is the peak-to-peak range of tau_i over the calibration
    data (fixed when the candidate is made): the scale of c_i is the gain that
    moves the joint by 1 mrad over that range, its typical truth 5 mrad (a
    compact arm needs a larger gain to sag as much as a long one; a smooth sag
    is largely absorbed by the geometric errors, so it must be larger than a
    backlash to show as much).
    """

    torque_span: float

    kind: ClassVar[str] = "compliance"
    title: ClassVar[str] = "joint compliance under gravity"
    params: ClassVar[tuple[str, ...]] = ("gain",)
    units: ClassVar[tuple[str, ...]] = ("rad/m",)
    geometric_basis: ClassVar[bool] = True

    @property
    def scales(self) -> np.ndarray:
        return np.array([MRAD / self.torque_span])

    @property
    def typical(self) -> np.ndarray:
        return np.array([5 * MRAD / self.torque_span])

    def constants(self) -> dict:
        return {**super().constants(), "torque_span": self.torque_span}

    def basis(self, robot: Robot, samples: Samples) -> np.ndarray:
        return gravity_torques(robot, samples.q)[:, self.joint:self.joint + 1]

    @classmethod
    def from_yaml(cls, robot: Robot, entry: Mapping[str, Any], where: str) -> "Compliance":
        joint = yaml_joint(robot, entry, where)
        return cls(joint=joint, torque_span=positive_number(where, entry, "torque_span", 1.0),
                   name=joint_name(robot, joint))

    @classmethod
    def make(cls, robot: Robot, samples: Samples, joint: int) -> "Compliance":
        """The candidate at ``joint`` (0-based) for the calibration samples."""
        return cls(joint=joint, torque_span=float(np.ptp(gravity_torques(robot, samples.q)[:, joint])),
                   name=joint_name(robot, joint))


@dataclass(frozen=True)
class Periodic(JointEffect):
    """Periodic joint error (encoder eccentricity, transmission error), the
    first two harmonics of the reading:

        dq_i = c1 cos q_i + s1 sin q_i + c2 cos 2q_i + s2 sin 2q_i     (rad)

    Scale 1 mrad per coefficient; typical truth 1 mrad (0.057 deg).
    """

    kind: ClassVar[str] = "periodic"
    title: ClassVar[str] = "periodic joint error (1st and 2nd harmonic)"
    params: ClassVar[tuple[str, ...]] = ("c1", "s1", "c2", "s2")
    units: ClassVar[tuple[str, ...]] = ("rad",) * 4

    @property
    def scales(self) -> np.ndarray:
        return np.full(4, MRAD)

    @property
    def typical(self) -> np.ndarray:
        return np.full(4, MRAD)

    def basis(self, robot: Robot, samples: Samples) -> np.ndarray:
        q = samples.q[:, self.joint]
        return np.stack([np.cos(q), np.sin(q), np.cos(2 * q), np.sin(2 * q)], axis=1)


@dataclass(frozen=True)
class Backlash(JointEffect):
    """Backlash: the link lags the motor by b on the side it was driven from,

        dq_i = -b d_i,   d_i = sign of the last move of joint i (base.move_directions)

    b (rad) is half the dead band. Scale 1 mrad; typical truth 2 mrad (0.11 deg).
    """

    kind: ClassVar[str] = "backlash"
    title: ClassVar[str] = "backlash (approach direction)"
    params: ClassVar[tuple[str, ...]] = ("b",)
    units: ClassVar[tuple[str, ...]] = ("rad",)

    @property
    def scales(self) -> np.ndarray:
        return np.array([MRAD])

    @property
    def typical(self) -> np.ndarray:
        return np.array([2 * MRAD])

    def basis(self, robot: Robot, samples: Samples) -> np.ndarray:
        return -move_directions(samples.q)[:, self.joint:self.joint + 1]


JOINT_EFFECTS = (JointScale, Compliance, Periodic, Backlash)
