"""A robot chain given by joint placements (URDF), its parameters and their names.

Each joint of the chain, base to tip, is its nominal placement (URDF origin,
a rigid transform from the parent link) followed, for a movable joint, by a
placement error and the motion about / along its unit axis:

    T_j = Origin_j · Trans(x,dx) Trans(y,dy) Trans(z,dz) Rot(x,drx) Rot(y,dry) Rot(z,drz) · Motion(axis, v_j)

with v_j = q_reading + offset_j (revolute: Rot, prismatic: Trans), or for a
coupled joint (URDF mimic) v_j = multiplier · q_source + mimic_offset + offset_j.
Fixed joints are their origin only: fixed frames anywhere in the chain. The 7
parameters of a movable joint, in this order, are named ``<joint>.offset``,
``.x``, ``.y``, ``.z``, ``.rx``, ``.ry``, ``.rz``; their nominal values are
zero and ``values`` holds the current ones (a calibrated chain). Several tips
(a tree): ``tips`` lists, per measured tip, the indices of the joints from the
base to it; a joint shared by two tips has its parameters once.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

REVOLUTE, PRISMATIC, FIXED_JOINT = "revolute", "prismatic", "fixed"
UNLIMITED = 1e3  # rad: the limits of a joint that turns without end (URDF continuous), for checking readings
# The offset first: of an offset and a placement rotation about the same axis
# (which only act as a sum), identifiability keeps the first, the readable one.
PLACEMENT_PARAMS = ("offset", "x", "y", "z", "rx", "ry", "rz")
OFFSET, PLACEMENT = 0, slice(1, 7)  # positions in a joint's block


@dataclass(frozen=True, eq=False)
class ChainJoint:
    """name; kind REVOLUTE / PRISMATIC / FIXED_JOINT; origin (4,4) from the parent
    link; axis (3,) unit; reading: the q column driving it, or for a coupled joint
    the source's column with multiplier and mimic_offset; -1 for a fixed joint;
    lower / upper: limits (rad or m) of a read joint."""

    name: str
    kind: str
    origin: np.ndarray
    axis: np.ndarray
    reading: int = -1
    multiplier: float = 1.0
    mimic_offset: float = 0.0
    coupled: bool = False
    lower: float = -np.pi
    upper: float = np.pi

    @property
    def movable(self) -> bool:
        return self.kind != FIXED_JOINT


@dataclass(frozen=True, eq=False)
class JointChain:
    """joints: every joint on the way from base to any tip, in the parameter
    order; tips: per tip link, the joint indices from the base to it; readings:
    names of the joints whose readings q holds, in q's column order; values (7M,)
    the placement errors and offsets of the M movable joints; urdf: the source
    URDF text (the exporter writes it back with corrected origins); sources:
    read joints off the way that drive a mimic joint on it (reading and limits
    only, no parameters)."""

    joints: tuple[ChainJoint, ...]
    base: str
    tip_links: tuple[str, ...]
    tips: tuple[tuple[int, ...], ...]
    readings: tuple[str, ...]
    values: np.ndarray = field(default=None)
    urdf: str = ""
    sources: tuple[ChainJoint, ...] = ()

    def __post_init__(self):
        if self.values is None:
            object.__setattr__(self, "values", np.zeros(self.n_params))

    @property
    def movable(self) -> tuple[int, ...]:
        """Indices of the movable joints, the order of their parameter blocks."""
        return tuple(i for i, j in enumerate(self.joints) if j.movable)

    @property
    def n_params(self) -> int:
        return len(PLACEMENT_PARAMS) * len(self.movable)

    def block(self, joint: int) -> int:
        """First parameter index of movable joint ``joint`` (an index into joints)."""
        return len(PLACEMENT_PARAMS) * self.movable.index(joint)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(f"{self.joints[i].name}.{p}" for i in self.movable for p in PLACEMENT_PARAMS)

    def kinds(self) -> np.ndarray:
        """'length' or 'angle' per parameter (7M,): the offset of a prismatic joint is a length."""
        out = []
        for i in self.movable:
            offset = "length" if self.joints[i].kind == PRISMATIC else "angle"
            out += [offset] + ["length"] * 3 + ["angle"] * 3
        return np.array(out)

    def prismatic(self) -> np.ndarray:
        """(N,) whether each read joint is prismatic (its reading in m)."""
        by_name = {j.name: j for j in self.joints + self.sources}
        return np.array([by_name[n].kind == PRISMATIC for n in self.readings], bool)

    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        """(N,) lower and upper limits of the read joints."""
        by_name = {j.name: j for j in self.joints + self.sources}
        return (np.array([by_name[n].lower for n in self.readings]),
                np.array([by_name[n].upper for n in self.readings]))

    def with_values(self, values: np.ndarray) -> "JointChain":
        return replace(self, values=np.array(values, dtype=float))
