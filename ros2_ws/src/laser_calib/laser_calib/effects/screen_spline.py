"""The screen of any shape: a penalised thin-plate regression spline, or a Matern surface (Surface).

A screen that is not flat is fitted as the surface x = f(y, z) (effects.screen.Surface:
the beam meets it, the camera sees the spot through the plane's homography)

    f(x) = sum over 1 <= i + j <= ORDER - 1 of c_ij u^i v^j  +  sum_k g_k psi_k(x),   x = (u, v),
    u = (y - centre_y) / half_y,  v = (z - centre_z) / half_z,

over the box the calibration spots cover, minus its value at the centre (a
constant is a screen offset, which the geometric errors hold). The polynomial
is the null space of the thin-plate bending energy of order ORDER (the
integral of the squared third derivatives), so it is fitted unpenalised: at
ORDER 3 it is the quadratic of ScreenShape. The psi_k are the smoothest
eigenfunctions of that energy over knots at the spots (Wood 2003, thin plate
regression splines): with eta(r) = r^4 log r, Z an orthonormal basis of the
knot weights orthogonal to the polynomials of degree < ORDER at the knots (the
thin-plate side conditions, under which the energy of sum_i a_i eta(|x - K_i|)
is a^T E a, E_ij = eta(|K_i - K_j|)) and Z^T E Z = U D U^T, psi_k(x) =
sum_i (Z U)_ik eta(|x - K_i|) plus the polynomial that makes it orthogonal to
the null space at the knots, scaled to RMS 1 there; its energy per unit g_k is
``bending``_k. The penalty is a Gaussian prior on g (effects.base.Effect.prior),

    g_k ~ N(0, rho^2 min(bending) / bending_k),

so rho (``smoothing``, m) is the size the smoothest bend may take, and
rougher modes are held to less; the diagnosis chooses rho by the held-out
error of its folds (diagnosis.fitter.Fitter.screen) and counts the fit's
effective parameters, not its coefficients. A robot file holds the fitted
surface in its knot form (``to_yaml``): the knots, the polynomial and one
weight per knot, a_i = sum_k (Z U)_ik g_k, which evaluates the same surface
without the eigenbasis.

Beyond the spots a thin-plate spline goes on as its polynomial: right for a
sag (a cubic continues), wrong for a bump or a wave of the sheet, where the
quadratic the spots happen to show grows without bound (on the 4-DOF arm's
wave screens, 9 mm off at a test spot 0.37 m beyond the calibration spots,
against 1.8 mm for the true model). The Matern surface (``length`` given,
in box half sizes) replaces eta by the Matern 5/2 covariance
k(r) = (1 + a + a^2 / 3) exp(-a), a = sqrt(5) r / length, over the plane's
null space (ORDER 2): within about a length of the knots it follows the
shape, beyond them it returns to the plane, as kriging does. The same
eigenform and prior hold (k is positive definite; its eigenvalues play the
energies' part); the held-out error chooses among the thin-plate orders and
the Matern lengths (SURFACES) as among the smoothings.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any, ClassVar, Mapping

import numpy as np

from laser_calib.effects.base import Effect
from laser_calib.effects.screen import BoxSurface
from laser_calib.io.errors import InputError
from laser_calib.io.read import finite_number
from laser_calib.model.robot import Robot

ORDERS = (3, 4)     # penalised derivative: the null space is the quadratic (ScreenShape's), or the cubic
# Matern lengths (box half sizes): from a bump a sixth of the spots' range across to a bend over all of it
LENGTHS = (0.3, 0.6, 1.2, 2.4)
MATERN_ORDER = 2    # the Matern surface's null space: the plane (its constant removed)
SURFACES = tuple((order, None) for order in ORDERS) + tuple((MATERN_ORDER, length) for length in LENGTHS)
MAX_KNOTS = 60     # knots spread over the spots (farthest-point subsample)
MODES = 30         # smoothest eigenfunctions kept; rougher ones carry nothing a prior would let through
MODE_FLOOR = 1e-10  # eigenvalues below this fraction of the largest are the eigensolver's rounding
# rho (m) the screening tries (Effect.variants): from a surface barely off its polynomial to bends of
# millimetres, a factor of about 2 apart (the held-out error changes little within that).
SMOOTHINGS = tuple(float(v) * 1e-3 for v in (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0))


def kernel(r2: np.ndarray, order: int, length: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """eta = (-1)^m r^(2m-2) log r of order m in the plane (the sign makes it conditionally
    positive definite) and d eta / d r^2, at squared distances r2 (0 at r = 0); with a
    ``length``, the Matern 5/2 covariance k of that length and d k / d r^2 (module docstring)."""
    if length is not None:
        a = np.sqrt(5.0 * r2) / length
        decay = np.exp(-a)
        return (1 + a + a * a / 3) * decay, -(5.0 / (6 * length ** 2)) * (1 + a) * decay
    positive = r2 > 0
    r2 = np.where(positive, r2, 1.0)
    log, sign = np.log(r2), (-1) ** order
    return (np.where(positive, sign * 0.5 * r2 ** (order - 1) * log, 0.0),
            np.where(positive, sign * 0.5 * r2 ** (order - 2) * ((order - 1) * log + 1), 0.0))


def exponents(order: int) -> tuple[tuple[int, int], ...]:
    """(i, j) of the null space's monomials u^i v^j, degree < order, the constant first."""
    return tuple((n - j, j) for n in range(order) for j in range(n + 1))


def polynomial(x: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
    """The null-space monomials (..., n) at normalised points x (...,2) and their gradients (..., n, 2)."""
    u, v = x[..., 0, None], x[..., 1, None]
    i, j = np.array(exponents(order)).T
    values = u ** i * v ** j
    du = np.where(i > 0, i * u ** np.maximum(i - 1, 0) * v ** j, 0.0)
    dv = np.where(j > 0, j * u ** i * v ** np.maximum(j - 1, 0), 0.0)
    return values, np.stack([du, dv], axis=-1)


def spread_knots(points: np.ndarray, count: int) -> np.ndarray:
    """``count`` of the points (n,2), each the farthest from those already taken (the first point first)."""
    if len(points) <= count:
        return points
    taken = [0]
    distance = np.linalg.norm(points - points[0], axis=1)
    for _ in range(count - 1):
        taken.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(points - points[taken[-1]], axis=1))
    return points[taken]


@dataclass(frozen=True, eq=False)
class ScreenSpline(BoxSurface):
    """A screen of any smooth shape (module docstring). ``penalty_order`` m (the null
    space: polynomials of degree < m); ``length`` the Matern surface's (None:
    thin-plate); ``knots`` (n,2) in the normalised
    coordinates; ``modes`` (n,K) and ``tails`` (len(exponents(m)),K) the knot
    weights and polynomial of each eigenfunction, ``bending`` (K,) their
    energies, ``smoothing`` rho (m); ``modes`` None is the knot form (one
    parameter per knot weight, no prior), as a robot file holds it.
    Coefficients in m; scale 1 mm."""

    kind: ClassVar[str] = "screen_spline"
    title: ClassVar[str] = "screen not flat (smooth surface)"

    penalty_order: int
    knots: np.ndarray
    modes: np.ndarray | None = None
    tails: np.ndarray | None = None
    bending: np.ndarray | None = None
    smoothing: float | None = None
    length: float | None = None

    @classmethod
    def make(cls, spots: np.ndarray, order: int = ORDERS[0],
             camera: tuple[float, float, float] | None = None, length: float | None = None) -> "ScreenSpline":
        """The spline of ``order`` over the box of the measured spots (P,L,2) m (NaN where not
        seen), knots spread over them; no smoothing chosen yet (variants)."""
        seen = spots.reshape(-1, 2)
        seen = seen[~np.isnan(seen).any(axis=1)]
        centre, half = cls.box(spots)
        knot_form = cls(float(centre[0]), float(centre[1]), float(half[0]), float(half[1]), order,
                        spread_knots((seen - centre) / half, MAX_KNOTS), camera=camera)
        return knot_form.with_order(order, length)

    def with_order(self, order: int, length: float | None = None) -> "ScreenSpline":
        """The eigenform of ``order`` (and Matern ``length``) over the same box and knots."""
        null, _ = polynomial(self.knots, order)
        if len(self.knots) <= null.shape[1]:
            raise ValueError(f"a screen spline needs more than {null.shape[1]} distinct spots, got {len(self.knots)}")
        z = np.linalg.qr(null, mode="complete")[0][:, null.shape[1]:]     # (n, n - m) side conditions
        gram, _ = kernel(((self.knots[:, None] - self.knots[None]) ** 2).sum(axis=-1), order, length)
        eigenvalues, vectors = np.linalg.eigh(z.T @ gram @ z)
        # The largest eigenvalues are the smoothest modes: their values (E Z U = Z U D plus a
        # polynomial) are large for their energy (Wood 2003). Those at the eigensolver's rounding of the
        # largest are no modes: with knots nearly coincident (one pose measured again and again) one
        # came out -4e-16 of 1e-6, and its prior sqrt(min / bending) was NaN.
        keep = np.argsort(-eigenvalues)[:MODES]
        keep = keep[eigenvalues[keep] > MODE_FLOOR * eigenvalues[keep[0]]]
        modes = z @ vectors[:, keep]
        values = gram @ modes
        tails = -np.linalg.lstsq(null, values, rcond=None)[0]
        rms = np.sqrt(np.mean((values + null @ tails) ** 2, axis=0))
        return replace(self, penalty_order=order, modes=modes / rms, tails=tails / rms, bending=eigenvalues[keep] / rms ** 2,
                       smoothing=None, length=length)

    def variants(self) -> tuple["ScreenSpline", ...]:
        return tuple(replace(self, smoothing=rho) for rho in SMOOTHINGS)

    @property
    def label(self) -> str:
        if self.length is not None:
            return f"{self.kind} (screen, Matern of length {self.length:g})"
        return f"{self.kind} (screen, penalty order {self.penalty_order})"

    @property
    def params(self) -> tuple[str, ...]:  # type: ignore[override]
        prefix, count = ("w", len(self.knots)) if self.modes is None else ("g", self.modes.shape[1])
        return (tuple(f"c{i}{j}" for i, j in exponents(self.penalty_order)[1:])
                + tuple(f"{prefix}{k + 1}" for k in range(count)))

    @property
    def tag(self) -> str:
        return "spline"

    @property
    def prior(self) -> np.ndarray | None:
        if self.modes is None or self.smoothing is None:
            return None
        modes = self.smoothing * np.sqrt(self.bending.min() / self.bending)
        return np.concatenate([np.full(len(exponents(self.penalty_order)) - 1, np.inf), modes])

    def constants(self) -> dict:
        length = {} if self.length is None else {"length": self.length}
        return {**super().constants(), "penalty_order": self.penalty_order, **length, "knots": self.knots.tolist()}

    def to_yaml(self, values: np.ndarray) -> dict[str, Any]:
        """The knot form: polynomial coefficients and one weight per knot."""
        if self.modes is None:
            return super().to_yaml(values)
        n_poly = len(exponents(self.penalty_order)) - 1
        modes = values[n_poly:]
        coefficients = values[:n_poly] + self.tails[1:] @ modes   # the tails' constants vanish at the centre
        knot_form = replace(self, modes=None, tails=None, bending=None, smoothing=None)
        return Effect.to_yaml(knot_form, np.concatenate([coefficients, self.modes @ modes]))

    @classmethod
    def from_yaml(cls, robot: Robot, entry: Mapping[str, Any], where: str) -> "ScreenSpline":
        length = None if entry.get("length") is None else finite_number(entry["length"], f"{where}.length")
        order, orders = entry.get("penalty_order"), ORDERS if length is None else (MATERN_ORDER,)
        if order not in orders or isinstance(order, bool):
            raise InputError(f"{where}.penalty_order", f"expected one of {', '.join(map(str, orders))}"
                             f"{'' if length is None else ' with a length'}, got {order!r}")
        if length is not None and length <= 0:
            raise InputError(f"{where}.length", f"expected a length above 0 (box half sizes), got {length:g}")
        knots = entry.get("knots")
        if (not isinstance(knots, list) or not knots
                or not all(isinstance(k, list) and len(k) == 2 for k in knots)):
            raise InputError(f"{where}.knots", "expected a list of [u, v] pairs (normalised knot positions)")
        points = np.array([[finite_number(value, f"{where}.knots[{n}]") for value in k] for n, k in enumerate(knots)])
        return cls(*cls.box_from_yaml(robot, entry, where), order, points, length=length, camera=robot.screen.camera)

    def _in_box(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """phi (...,k) and d phi / d x (...,k,2) at normalised points x (...,2), before the centre's value is removed."""
        offset = x[..., None, :] - self.knots                                 # (..., n, 2)
        eta, slope = kernel(np.einsum("...nd,...nd->...n", offset, offset), self.penalty_order, self.length)
        null, d_null = polynomial(x, self.penalty_order)
        d_eta = [2 * slope * offset[..., 0], 2 * slope * offset[..., 1]]      # d eta / du, dv (..., n)
        if self.modes is None:
            weights = eta
        else:
            weights = eta @ self.modes + null @ self.tails
            d_eta = [d @ self.modes + d_null[..., axis] @ self.tails for axis, d in enumerate(d_eta)]
        return (np.concatenate([null[..., 1:], weights], axis=-1),
                np.stack([np.concatenate([d_null[..., 1:, axis], d], axis=-1) for axis, d in enumerate(d_eta)],
                         axis=-1))

    @cached_property
    def _at_centre(self) -> np.ndarray:
        return self._in_box(np.zeros(2))[0]

    def terms(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        phi, d_phi = self._in_box(self.normalised(s))
        return phi - self._at_centre, d_phi / np.array([self.half_y, self.half_z])
