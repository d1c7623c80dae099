"""EffectModel: the geometric spot model plus effect blocks, as one
MeasurementModel (measurement/base.py), so LM, the EKF, the identifiability analysis
and estimate_model run on it unchanged.

x = [geometric errors (4N+5), block of effect 1, block of effect 2, ...]

With p the effect parameters (K,), per pose:

    dq      = Bq @ p            joint effects,     Bq (P,N,K)
    errors  = x_geo + Bp @ p    parameter effects, Bp (P,4N+5,K)
    s       = SpotModel.evaluate(errors, dq)       the flat-screen spots
    s'      = S_m(...S_1(s))    spot effects, in physical order

and the Jacobian columns of p are  jac_q @ Bq + jac @ Bp  (chain rule through
the readings and the parameters) plus the spot effects' own columns; every
Jacobian is carried through the spot maps by their d s'/d s. The bases depend
on the whole sequence of the data (approach directions), so subsets for
cross-validation slice them instead of recomputing. Bases that depend on the
geometry (compliance: gravity torques) are recomputed at the current
geometric errors; their change with those errors is second order and left
out of the Jacobian.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar, Sequence

import numpy as np

from laser_calib.model.kinematics import forward
from laser_calib.measurement.base import Residuals, RobotModel
from laser_calib.effects.base import JOINT, PARAM, SPOT, Effect


@dataclass(frozen=True)
class Fixed:
    """Offsets with no parameter (a learned compensator's, diagnosis.compensator):
    joint offsets dq (P,N) rad and geometric-parameter offsets (P,n)."""

    dq: np.ndarray
    errors: np.ndarray

    def subset(self, index) -> "Fixed":
        return Fixed(self.dq[index], self.errors[index])


@dataclass(frozen=True)
class Bases:
    """Precomputed joint and parameter bases, None where no effect of that family."""

    joint: np.ndarray | None   # (P,N,K)
    param: np.ndarray | None   # (P,n,K)

    def subset(self, index) -> "Bases":
        return Bases(None if self.joint is None else self.joint[index],
                     None if self.param is None else self.param[index])


class EffectModel:
    """A robot measurement model with effects. names/scales: the geometric ones, then each
    effect's; ``blocks`` maps each effect to its slice of x.

    ``base`` is any measurement.RobotModel (spot, point, pose); spot effects
    need one that measures spots. An EffectModel is itself a RobotModel's
    MeasurementModel part (names, scales, residuals, subset).
    """

    measures_spots: ClassVar[bool] = False  # set per instance from the base

    def __init__(self, base: RobotModel, effects: Sequence[Effect] = (), bases: Bases | None = None,
                 fixed: Fixed | None = None):
        if any(e.family == SPOT for e in effects) and not base.measures_spots:
            raise ValueError("spot effects (screen shape, camera distortion) need the laser spot model")
        self.base = base
        self.measures_spots = base.measures_spots
        self.robot = base.robot
        self.samples = base.samples
        self.effects = tuple(effects)
        self.n_geometric = len(base.names)
        self.names = tuple(base.names) + tuple(name for e in self.effects for name in e.names)
        self.scales = np.concatenate([base.scales] + [e.scales for e in self.effects])
        self.blocks: list[slice] = []
        start = 0
        for effect in self.effects:
            self.blocks.append(slice(start, start + len(effect.params)))
            start += len(effect.params)
        self.n_effect_params = start
        self.bases = self._bases() if bases is None else bases
        self.fixed = fixed
        self._spot = sorted((e.order, i) for i, e in enumerate(self.effects) if e.family == SPOT)
        self._geometric = [i for i, e in enumerate(self.effects) if e.family == JOINT and e.geometric_basis]

    def _bases(self) -> Bases:
        n_poses, n_joints = self.samples.q.shape
        joint = param = None
        for effect, block in zip(self.effects, self.blocks):
            if effect.family == JOINT:
                if joint is None:
                    joint = np.zeros((n_poses, n_joints, self.n_effect_params))
                joint[:, effect.joint, block] = effect.basis(self.robot, self.samples)
            elif effect.family == PARAM:
                if param is None:
                    param = np.zeros((n_poses, self.n_geometric, self.n_effect_params))
                param[:, effect.param, block] = effect.basis(self.robot, self.samples)
        return Bases(joint, param)

    def subset(self, index) -> "EffectModel":
        """The model on the poses ``index`` (mask or indices), bases sliced."""
        return EffectModel(self.base.subset(index), self.effects, self.bases.subset(index),
                           None if self.fixed is None else self.fixed.subset(index))

    @property
    def prior_sigma(self) -> np.ndarray | None:
        """(n,) the effects' priors (Effect.prior; inf where none), None when no effect has one."""
        priors = [e.prior for e in self.effects]
        if all(p is None for p in priors):
            return None
        return np.concatenate([np.full(self.n_geometric, np.inf)]
                              + [np.full(len(e.params), np.inf) if p is None else p for e, p in zip(self.effects, priors)])

    def split(self, x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
        """Geometric errors (n,) and each effect's values."""
        x = np.asarray(x, float)
        p = x[self.n_geometric:]
        return x[:self.n_geometric], [p[b] for b in self.blocks]

    def offsets(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Per-pose errors (n,) or (P,n) and joint offsets dq (P,N) or None at x."""
        x = np.asarray(x, float)
        geometric, p = x[:self.n_geometric], x[self.n_geometric:]
        joint_basis = self.joint_basis(geometric)
        return self._with_fixed(geometric if self.bases.param is None else geometric + self.bases.param @ p,
                                None if joint_basis is None else joint_basis @ p)

    def _with_fixed(self, errors: np.ndarray, dq: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
        if self.fixed is None:
            return errors, dq
        return errors + self.fixed.errors, self.fixed.dq if dq is None else dq + self.fixed.dq

    def joint_basis(self, geometric: np.ndarray) -> np.ndarray | None:
        """Bq (P,N,K) at the geometric errors (n,)."""
        if not self._geometric:
            return self.bases.joint
        basis = self.bases.joint.copy()
        corrected = self.robot.with_errors(geometric[:self.robot.n_params])  # sensor models append frames
        for i in self._geometric:
            effect = self.effects[i]
            basis[:, effect.joint, self.blocks[i]] = effect.basis(corrected, self.samples)
        return basis

    def residuals(self, x: np.ndarray, jacobian: bool = True) -> Residuals:
        x = np.asarray(x, float)
        geometric, p = x[:self.n_geometric], x[self.n_geometric:]
        joint_basis = self.joint_basis(geometric)
        errors, dq = self._with_fixed(geometric if self.bases.param is None else geometric + self.bases.param @ p,
                                      None if joint_basis is None else joint_basis @ p)
        res = self.base.evaluate(errors, dq, jacobian)
        spot_columns: dict[int, np.ndarray] = {}
        if self._spot:
            res, spot_columns = self._spot_maps(res, errors, dq, p, jacobian)
        if not jacobian:
            return res
        columns = np.zeros(res.jac.shape[:-1] + (self.n_effect_params,))
        if joint_basis is not None:
            columns += np.einsum("pcdn,pnk->pcdk", res.jac_q, joint_basis)
        if self.bases.param is not None:
            columns += np.einsum("pcdn,pnk->pcdk", res.jac, self.bases.param)
        for i, cols in spot_columns.items():
            columns[..., self.blocks[i]] = cols
        jac = np.concatenate([res.jac, columns], axis=-1)
        jac = np.where(res.valid[..., None, None], jac, 0.0)
        return replace(res, jac=jac)

    def _spot_maps(self, res: Residuals, errors, dq, p, jacobian: bool):
        q = self.samples.q if dq is None else self.samples.q + dq
        beams = forward(self.robot, q, errors).beams
        valid = res.valid
        # Invalid spots carry NaN/inf; keep the maps finite there (they are masked out).
        spots = np.where(valid[..., None], res.predicted, 0.0)
        beams = np.where(valid[..., None], beams, np.array([1.0, 0.0, 0.0]))
        jac, jac_q = res.jac, res.jac_q
        columns: dict[int, np.ndarray] = {}
        for _, i in self._spot:
            spots, d_spots, d_values = self.effects[i].apply(spots, beams, p[self.blocks[i]])
            if jacobian:
                jac = d_spots @ jac
                jac_q = d_spots @ jac_q
                columns = {j: d_spots @ c for j, c in columns.items()}
                columns[i] = d_values
        predicted = np.where(valid[..., None], spots, res.predicted)
        r = np.where(valid[..., None], np.nan_to_num(self.samples.spots - predicted), 0.0)
        if jacobian:
            columns = {i: np.where(valid[..., None, None], c, 0.0) for i, c in columns.items()}
        return replace(res, r=r, predicted=predicted, jac=jac, jac_q=jac_q), columns
