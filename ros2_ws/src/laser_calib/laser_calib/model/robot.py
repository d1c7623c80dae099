"""Robot description and the geometric parameter vector (conventions.md).

The parameter vector of a robot holds its nominal D-H values in the order of
the error vector, so that a corrected model is simply ``nominal + errors``:

    [a_1, d_1, alpha_1, theta0_1, ..., a_N, d_N, alpha_N, theta0_N,
     slm_a, slm_d, slm_alpha, slm_beta, slm_theta]           shape (4N+5,)

and the errors are [Δa_1, Δd_1, Δα_1, Δθ_1, ..., Δx_s, Δz_s, Δrx_s, Δry_s, Δrz_s].
A robot without lasers needs no SLM (slm None): its vector ends with the links.
A robot given by joint placements (URDF, ``chain``) has the chain's 7 values
per movable joint (joint_chain.py) in place of the D-H block, then the SLM's 5
if it carries lasers: a measurement kind brings only its own parameters.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Mapping

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.io.read import length_units
from laser_calib.model.joint_chain import UNLIMITED, JointChain

PAPER = "paper"        # T_i = Trans(x,a) Trans(z,d) Rot(x,alpha) Rot(z,theta)
STANDARD = "standard"  # T_i = Trans(z,d) Rot(z,theta) Trans(x,a) Rot(x,alpha)
CONVENTIONS = (PAPER, STANDARD)

# Units check: no arm has a link over 100 m, no fixed angle over 4 pi rad; such a
# value is a length in mm or an angle in degrees.
MAX_LENGTH = 100.0
MAX_ANGLE = 4 * np.pi
# Revolute joint limits: UR's joints turn +-2 pi, the widest catalogue wrists +-455 deg (Yaskawa's
# T axis; FANUC's J6 +-450, ABB's axis 6 +-400), 7.9 rad. Beyond 3 pi (540 deg) a limit is in
# degrees (+-30 typed for +-30 deg); a joint that turns without end is a URDF continuous joint.
LIMIT_ANGLE = 3 * np.pi
# Prismatic joint limits: an arm's prismatic joints are lifts, torsos and fingers (PR2's torso
# 0.31 m, the Panda's fingers 0.04 m) or a floor track carrying it, a few metres. Beyond 20 m a
# limit is taken for cm or mm (50 typed for 50 cm), which MAX_LENGTH let through as metres; the
# price is that a track longer than 20 m is refused too.
LIMIT_TRAVEL = 20.0
# The laser module sits on the last link's flange, a few cm off it (paper: 5 cm): an offset
# of a metre is no module on a flange, and MAX_LENGTH would let -30 (mm) through as 30 m.
MAX_SLM_OFFSET = 1.0


def plausible_length(where: str, value: float, bound: float = MAX_LENGTH, what: str = "") -> float:
    """``value`` (m), or one line saying it looks like millimetres (or centimetres):
    the one units rule for every length a robot file, a URDF or a frame guess holds.
    ``what``: the quantity whose own bound ``bound`` is, named with it in the line."""
    if abs(value) > bound:
        quantity = f"{what} (over {bound:g} m)" if what else "length"
        raise InputError(where, f"{value:g} m is not a plausible {quantity}: lengths are in metres "
                                f"(this looks like {length_units(value, bound)})")
    return value


def plausible_angle(where: str, value: float, bound: float = MAX_ANGLE) -> float:
    """``value`` (rad), or one line saying it looks like degrees: the one units
    rule for every angle and revolute joint limit of a robot file or a URDF."""
    if abs(value) > bound:
        raise InputError(where, f"{value:g} rad is not a plausible angle: angles are in radians "
                                "(this looks like degrees)")
    return value


LINK_PARAMS = ("a", "d", "alpha", "theta")
SLM_PARAMS = ("slm_x", "slm_z", "slm_rx", "slm_ry", "slm_rz")


@dataclass(frozen=True)
class Joint:
    """One D-H link; a prismatic joint's reading adds to d instead of theta
    (min / max then in m)."""

    a: float
    d: float
    alpha: float
    theta0: float
    min: float
    max: float
    prismatic: bool = False


@dataclass(frozen=True)
class Slm:
    a: float
    d: float
    alpha: float
    theta: float
    beta: float = 0.0


@dataclass(frozen=True)
class Laser:
    gamma: float
    beta: float = 0.0


@dataclass(frozen=True)
class Screen:
    """The screen x = 0 of frame {0}: its half sizes (m) and, when known, the
    centre (x, y, z) of the camera that watches it (m, in {0}; x != 0), which a
    screen that is not flat needs (effects.screen: the camera sees a spot off
    the plane displaced along its line of sight)."""

    half_y: float = 1.0
    half_z: float = 1.0
    camera: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class Robot:
    """joints: the D-H links (empty for a chain of joint placements, ``chain``)."""

    name: str
    joints: tuple[Joint, ...]
    slm: Slm | None
    lasers: tuple[Laser, ...]
    screen: Screen = Screen()
    gravity: tuple[float, float, float] = (0.0, 0.0, -1.0)
    convention: str = PAPER
    # Keys this module does not interpret (effects, frames): kept verbatim on write.
    extra: Mapping[str, Any] = field(default_factory=dict)
    chain: JointChain | None = None

    @property
    def n_joints(self) -> int:
        """Number of joint readings (columns of q)."""
        return len(self.joints) if self.chain is None else len(self.chain.readings)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Names of the readings, q's columns: a URDF's joint names, else q1..qN."""
        return tuple(f"q{i + 1}" for i in range(self.n_joints)) if self.chain is None else self.chain.readings

    @property
    def n_link_params(self) -> int:
        """Size of the arm's block: 4N for D-H, 7 per movable joint for a chain."""
        return 4 * self.n_joints if self.chain is None else self.chain.n_params

    @property
    def n_params(self) -> int:
        return self.n_link_params + (len(SLM_PARAMS) if self.slm is not None else 0)

    @property
    def param_names(self) -> tuple[str, ...]:
        links = self.chain.names if self.chain is not None else param_names(self.n_joints)[:4 * self.n_joints]
        return links + (SLM_PARAMS if self.slm is not None else ())

    def param_kinds(self) -> np.ndarray:
        """'length' or 'angle' per parameter (n_params,)."""
        links = self.chain.kinds() if self.chain is not None else param_kinds(self.n_joints)[:4 * self.n_joints]
        slm = param_kinds(0) if self.slm is not None else np.array([], str)
        return np.concatenate([links, slm])

    @property
    def prismatic(self) -> np.ndarray:
        """(N,) whether each read joint is prismatic: its reading in m, not rad."""
        return np.array([j.prismatic for j in self.joints], bool) if self.chain is None else self.chain.prismatic()

    @property
    def q_min(self) -> np.ndarray:
        return np.array([j.min for j in self.joints]) if self.chain is None else self.chain.limits()[0]

    @property
    def q_max(self) -> np.ndarray:
        return np.array([j.max for j in self.joints]) if self.chain is None else self.chain.limits()[1]

    def pose_range(self) -> tuple[np.ndarray, np.ndarray]:
        """(N,) lower and upper bounds that poses are drawn from (planning, simulation, the
        truth check): the joint limits, and one turn [-pi, pi] for a joint that turns without
        end, every angle it can take. Drawn from its stand-in limits (+-UNLIMITED), a session
        commanded such a joint hundreds of turns from zero, which a real arm's cables do not survive."""
        low, high = self.q_min.copy(), self.q_max.copy()
        endless = (low <= -UNLIMITED) & (high >= UNLIMITED)
        low[endless], high[endless] = -np.pi, np.pi
        return low, high

    def vector(self) -> np.ndarray:
        """Nominal parameter vector, shape (n_params,)."""
        if self.chain is not None:
            links = list(self.chain.values)
        else:
            links = [v for j in self.joints for v in (j.a, j.d, j.alpha, j.theta0)]
        s = self.slm
        return np.array(links + ([s.a, s.d, s.alpha, s.beta, s.theta] if s is not None else []))

    def with_vector(self, params: np.ndarray) -> "Robot":
        """The same robot with its parameter values replaced by ``params`` (n_params,)."""
        params = np.asarray(params, dtype=float)
        if params.shape != (self.n_params,):
            raise ValueError(f"parameter vector has shape {params.shape}, expected ({self.n_params},)")
        n = self.n_link_params
        slm = None if self.slm is None else Slm(*params[n:n + 3], theta=params[n + 4], beta=params[n + 3])
        if self.chain is not None:
            return replace(self, chain=self.chain.with_values(params[:n]), slm=slm)
        joints = tuple(
            replace(j, a=params[4 * i], d=params[4 * i + 1], alpha=params[4 * i + 2], theta0=params[4 * i + 3])
            for i, j in enumerate(self.joints)
        )
        return replace(self, joints=joints, slm=slm)

    def with_errors(self, errors: np.ndarray) -> "Robot":
        """The corrected robot: nominal values plus the geometric errors (4N+5,)."""
        return self.with_vector(self.vector() + np.asarray(errors, dtype=float))

    def laser_angles(self) -> np.ndarray:
        """(L, 2) array of (gamma, beta) per laser."""
        return np.array([(laser.gamma, laser.beta) for laser in self.lasers], dtype=float)


def param_names(n_joints: int) -> tuple[str, ...]:
    names = [f"{p}{i + 1}" for i in range(n_joints) for p in LINK_PARAMS]
    return tuple(names) + SLM_PARAMS


def param_kinds(n_joints: int) -> np.ndarray:
    """'length' or 'angle' per error, shape (4N+5,): selects units and tolerances."""
    link = ["length", "length", "angle", "angle"] * n_joints
    return np.array(link + ["length", "length", "angle", "angle", "angle"])
