"""The effect block: a physical effect the D-H model lacks, as parameters.

An effect owns k parameters p (k,) and acts in one of three places, its family:

- JOINT: per-pose joint offsets dq_i(p) = B(pose) @ p added to the reading of
  its joint i, B (P,k) a basis of the readings, their order or the geometry.
  Its Jacobian is jac_q[:, :, :, i] @ B, so it works for every sensor model
  that exposes jac_q.
- PARAM: per-pose offsets of one geometric parameter j, Δx_j(p) = B(pose) @ p;
  its Jacobian is jac[..., j] @ B.
- SPOT: a map of the predicted spots on the screen, s' = S(s, beam; p), with
  its Jacobians d s'/d s (P,L,2,2) and d s'/d p (P,L,2,k).

Every block is linear in p for the joint and parameter families (the basis is
fixed by the data), so these are exact; the spot family is exact in value and
its Jacobian neglects only second-order terms (stated where they occur).

Each effect states, per parameter, its unit, a characteristic scale (the size
the damping and the identifiability analysis compare it with, like 10 mm /
1 deg for the geometric errors) and a typical size (the default size of the
simulator's truth form).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.io.samples import Samples
from laser_calib.model.robot import Robot
from laser_calib.io.read import yaml_number

JOINT, PARAM, SPOT = "joint", "param", "spot"
# The YAML 'type' of every concrete effect -> its class, filled as each class is defined.
REGISTRY: dict[str, type["Effect"]] = {}



def positive_number(where: str, entry: Mapping[str, Any], key: str, default: float | None = None) -> float:
    value = yaml_number(where, entry, key, default)
    if value <= 0:
        raise InputError(f"{where}.{key}", "must be positive")
    return value


@dataclass(frozen=True)
class Effect(ABC):
    """One parameter block. Subclasses set the class constants below."""

    kind: ClassVar[str]                 # the YAML 'type' and the family of candidates
    family: ClassVar[str]               # JOINT, PARAM or SPOT
    title: ClassVar[str]                # human-readable name of the physical effect
    params: ClassVar[tuple[str, ...]]   # short parameter names, as in the YAML entry
    units: ClassVar[tuple[str, ...]]
    # True when the basis depends on the geometric errors (recomputed at each evaluation).
    geometric_basis: ClassVar[bool] = False

    def __init_subclass__(cls, register: bool = True, **kwargs):
        # register=False: a truth form of the simulator, never a robot file's effect.
        super().__init_subclass__(**kwargs)
        if "kind" in cls.__dict__ and register:
            REGISTRY[cls.kind] = cls

    @classmethod
    @abstractmethod
    def from_yaml(cls, robot: Robot, entry: Mapping[str, Any], where: str) -> "Effect":
        """The effect of a robot file's ``effects:`` entry (its constants; the
        values are read by the caller from ``params``); InputError naming
        ``where`` and the key on bad input."""

    @property
    @abstractmethod
    def where(self) -> str:
        """Where the effect acts: 'joint 3', 'a2', 'screen', 'camera'."""

    @property
    @abstractmethod
    def scales(self) -> np.ndarray:
        """(k,) characteristic size of each parameter, in its unit."""

    @property
    @abstractmethod
    def typical(self) -> np.ndarray:
        """(k,) default size of each parameter in the simulator's truth form."""

    @property
    def prior(self) -> np.ndarray | None:
        """(k,) standard deviation of a zero-mean Gaussian prior on each parameter
        (inf: none), or None: no prior. A penalised effect (the screen spline)
        has one; every fit of a model with it carries it, and the diagnosis
        counts the fit's effective parameters."""
        return None

    def variants(self) -> tuple["Effect", ...]:
        """The forms the diagnosis screens, keeping the best: the effect itself, or a
        penalised effect at each of its penalties (same parameters, other priors)."""
        return (self,)

    @property
    def tag(self) -> str:
        """Short identifier used in parameter names: 'backlash3', 'screen'."""
        return self.kind

    @property
    def names(self) -> tuple[str, ...]:
        """Full parameter names: tag if one parameter, else tag_param."""
        if len(self.params) == 1:
            return (self.tag,)
        return tuple(f"{self.tag}_{p}" for p in self.params)

    @property
    def label(self) -> str:
        return f"{self.kind} ({self.where})"

    def constants(self) -> dict[str, Any]:
        """What the YAML entry holds besides the parameter values."""
        return {}

    def to_yaml(self, values: np.ndarray) -> dict[str, Any]:
        entry: dict[str, Any] = {"type": self.kind}
        entry.update(self.constants())
        entry.update({p: float(v) for p, v in zip(self.params, values)})
        return entry


@dataclass(frozen=True)
class JointEffect(Effect):
    """An effect on the angle of one joint (0-based index ``joint``; ``name``:
    the robot's own name for it, a URDF joint's, shown beside the number; the
    files keep the number)."""

    family: ClassVar[str] = JOINT
    joint: int
    name: str = field(default="", compare=False, kw_only=True)

    @property
    def where(self) -> str:
        return f"joint {self.joint + 1}" + (f" {self.name}" if self.name else "")

    @property
    def tag(self) -> str:
        return f"{self.kind}{self.joint + 1}"

    def constants(self) -> dict[str, Any]:
        return {"joint": self.joint + 1}

    @classmethod
    def from_yaml(cls, robot: Robot, entry: Mapping[str, Any], where: str) -> "JointEffect":
        joint = yaml_joint(robot, entry, where)
        return cls(joint=joint, name=joint_name(robot, joint))

    @abstractmethod
    def basis(self, robot: Robot, samples: Samples) -> np.ndarray:
        """(P,k): dq_joint = basis @ p, in rad, at the samples' readings and order."""


@dataclass(frozen=True)
class ParamEffect(Effect):
    """An effect on one geometric parameter (index ``param`` in the error vector)."""

    family: ClassVar[str] = PARAM
    param: int

    @abstractmethod
    def basis(self, robot: Robot, samples: Samples) -> np.ndarray:
        """(P,k): offset of the parameter = basis @ p, in its unit."""


@dataclass(frozen=True)
class SpotEffect(Effect):
    """A map of the spots on the screen. ``order`` fixes the physical sequence
    (the beam meets the surface first, then the camera sees the spot)."""

    family: ClassVar[str] = SPOT
    order: ClassVar[int]

    @abstractmethod
    def apply(self, spots: np.ndarray, beams: np.ndarray, values: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """spots (P,L,2) m and unit beams (P,L,3) in {0} (finite everywhere) ->
        (new spots (P,L,2), d new / d spots (P,L,2,2), d new / d values (P,L,2,k))."""


def joint_name(robot: Robot, joint: int) -> str:
    """The name of the 0-based ``joint`` a URDF robot gives it; "" for a D-H robot (its joints are numbered)."""
    return robot.joint_names[joint] if robot.chain is not None else ""


def yaml_joint(robot: Robot, entry: Mapping[str, Any], where: str) -> int:
    """The 0-based joint of an entry's 1-based ``joint`` key."""
    joint = entry.get("joint")
    if isinstance(joint, bool) or not isinstance(joint, int) or not 1 <= joint <= robot.n_joints:
        raise InputError(f"{where}.joint", f"expected a joint number 1..{robot.n_joints}, got {joint!r}")
    return joint - 1


def last_moves(q: np.ndarray) -> np.ndarray:
    """(P,N) rad each joint's move into each row, in row order (conventions.md: before the
    first row the arm is at q = 0)."""
    q = np.atleast_2d(np.asarray(q, float))
    return np.diff(np.vstack([np.zeros((1, q.shape[1])), q]), axis=0)


def move_directions(q: np.ndarray, tolerance: float = 1e-6) -> np.ndarray:
    """(P,N) sign of the last move of each joint before each row, in row order.

    conventions.md: before the first row the arm is at q = 0. A joint that did
    not move (|step| <= tolerance rad) keeps its previous direction (the gears
    stay on the flank they were pushed against); 0 until it first moves.
    """
    q = np.atleast_2d(np.asarray(q, float))
    steps = last_moves(q)
    moved = np.abs(steps) > tolerance
    signs = np.where(moved, np.sign(steps), 0.0)
    out = np.zeros_like(signs)
    current = np.zeros(q.shape[1])
    for p in range(len(q)):
        current = np.where(moved[p], signs[p], current)
        out[p] = current
    return out


def sign_choice(rng: np.random.Generator, k: int) -> np.ndarray:
    """Random signs and magnitudes in [0.5, 1]: a truth that is neither tiny nor
    of one fixed sign (used by every effect's truth form)."""
    return rng.choice([-1.0, 1.0], k) * rng.uniform(0.5, 1.0, k)
