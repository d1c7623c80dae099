"""Spot effects (base.SPOT): the screen is not flat (Surface: the quadratic, a
Legendre series; effects.screen_spline: a smooth surface of any shape), the
camera's residual distortion.

Both act on the predicted spot s = (y, z) (m) of the flat-screen model, in
normalised screen coordinates so that every coefficient is a length in metres
(its size at the screen edge). They are applied in physical order: the beam
meets the real surface and the camera sees it there through the screen's
homography (Surface), then the camera's lens displaces what it reports
(CameraDistortion).
"""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np
from numpy.polynomial import legendre
from scipy.spatial import Delaunay, QhullError

from laser_calib.effects.base import SpotEffect, positive_number, yaml_number
from laser_calib.io.errors import InputError
from laser_calib.model.robot import Robot

MM = 1e-3
# Newton's method on (1) converges quadratically from the flat spot (|grad f . t| ~ 1e-3 for a gentle
# screen seen head-on, 0.1 for a bumpy one at a grazing beam, |t| up to 10 on the paper's 7-DOF arm).
NEWTON_TOLERANCE = 1e-13  # m
NEWTON_ITERATIONS = 20
MAX_DEGREE = 8  # 44 coefficients: beyond this a screen is not smooth at the scale of the poses


@dataclass(frozen=True)
class Surface(SpotEffect):
    """A screen surface x = f(y, z) = phi(y, z) . c, linear in its coefficients c
    (no constant term: a screen offset along x is the same as moving the base,
    which the geometric errors already hold), seen by a camera at ``camera``
    (its centre in {0}, m; None: far away along the screen normal).

    The beam p + k z meets the surface where p_x + k z_x = f(s): with the flat
    spot s0 and t = (z_y, z_z) / z_x,

        s = s0 + f(s) t                                                (1)

    solved by Newton's method (to 1e-13 m). The camera's screen calibration
    (a homography) maps what it sees onto the plane x = 0: a point (f, s) off
    the plane lands where the camera's line of sight through it meets the
    plane, with C the camera centre,

        r = s - f(s) tau,   tau = (s - C_yz) / (f(s) - C_x)            (2)

    so the reported spot depends on the beam's direction (t) and on the
    camera's viewpoint (tau), not on s alone; a camera 2.5 m in front of the
    screen sees a third of the beam's displacement on the paper's arms
    (|t| ~ 1, |tau| ~ 0.3). Without a camera, r = s (tau = 0).
    Differentiating (1), (I - t g^T) ds = ds0 + t phi^T dc (+ f dt, neglected:
    second order, f ~ mm times the beam-direction change), g = grad f, so
    d s / d s0 = (I - t g^T)^-1 and d s / d c = t phi^T / (1 - g.t); and (2),
    with kappa = -C_x / (f - C_x), d r / d s = kappa (I - tau g^T) and
    d r / d c (s held) = -kappa tau phi^T.
    """

    camera: tuple[float, float, float] | None = field(default=None, kw_only=True)
    order: ClassVar[int] = 0

    @property
    def where(self) -> str:
        return "screen"

    @abstractmethod
    def terms(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """phi (...,k) and d phi / d s (...,k,2) at spots s (...,2) m."""

    def apply(self, spots, beams, values):
        t = beams[..., 1:] / beams[..., :1]
        s = spots
        for _ in range(NEWTON_ITERATIONS):
            phi, dphi = self.terms(s)
            g = values @ dphi                                            # grad f (...,2)
            denominator = (1.0 - np.sum(g * t, axis=-1))[..., None, None]
            # Newton on (1): s - s0 - f(s) t = 0, its Jacobian I - t g^T inverted (Sherman-Morrison)
            miss = s - spots - (phi @ values)[..., None] * t
            step = miss + t * np.sum(g * miss, axis=-1)[..., None] / denominator[..., 0]
            s = s - step
            if not np.abs(step).max(initial=0.0) > NEWTON_TOLERANCE:
                break   # phi, g at s + step: the same to 1e-13 m
        d_spots = np.eye(2) + t[..., :, None] * g[..., None, :] / denominator
        d_values = t[..., :, None] * phi[..., None, :] / denominator
        if self.camera is None:
            return s, d_spots, d_values
        centre = np.asarray(self.camera)
        f = (phi @ values)[..., None]
        tau = (s - centre[1:]) / (f - centre[0])
        kappa = (-centre[0] / (f - centre[0]))[..., None]
        seen = kappa * (np.eye(2) - tau[..., :, None] * g[..., None, :])   # d r / d s
        return (s - f * tau, seen @ d_spots,
                seen @ d_values - kappa * tau[..., :, None] * phi[..., None, :])


@dataclass(frozen=True)
class ScreenShape(Surface):
    """The screen surface (Surface) is the quadratic

        f = c_u u + c_v v + c_uu u^2 + c_uv u v + c_vv v^2,   u = y / half_y, v = z / half_z.

    Coefficients in m (the height at the screen edge); scale 1 mm; typical
    truth 1 mm (linear terms) and 2 mm (quadratic terms).
    """

    half_y: float
    half_z: float

    kind: ClassVar[str] = "screen_shape"
    title: ClassVar[str] = "screen not flat"
    params: ClassVar[tuple[str, ...]] = ("u", "v", "uu", "uv", "vv")
    units: ClassVar[tuple[str, ...]] = ("m",) * 5

    @property
    def tag(self) -> str:
        return "screen"

    @property
    def scales(self) -> np.ndarray:
        return np.full(5, MM)

    @property
    def typical(self) -> np.ndarray:
        return np.array([1.0, 1.0, 2.0, 2.0, 2.0]) * MM

    def constants(self) -> dict:
        return {"half_y": self.half_y, "half_z": self.half_z}

    @classmethod
    def from_yaml(cls, robot: Robot, entry: Mapping[str, Any], where: str) -> "ScreenShape":
        return cls(positive_number(where, entry, "half_y", robot.screen.half_y),
                   positive_number(where, entry, "half_z", robot.screen.half_z), camera=robot.screen.camera)

    def terms(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v = s[..., 0] / self.half_y, s[..., 1] / self.half_z
        zero = np.zeros_like(u)
        phi = np.stack([u, v, u * u, u * v, v * v], axis=-1)
        dphi_du = np.stack([1 + zero, zero, 2 * u, v, zero], axis=-1) / self.half_y
        dphi_dv = np.stack([zero, 1 + zero, zero, u, 2 * v], axis=-1) / self.half_z
        return phi, np.stack([dphi_du, dphi_dv], axis=-1)


def surface_terms(degree: int) -> tuple[tuple[int, int], ...]:
    """The (i, j) of P_i(u) P_j(v) of total order 1..degree, by order then i descending."""
    return tuple((n - j, j) for n in range(1, degree + 1) for j in range(n + 1))


def extrapolation_note(surfaces: list[str], calibration: np.ndarray, test: np.ndarray) -> str | None:
    """Where the test spots leave what the calibration saw of the screen: the
    fitted surfaces (labels) are only known over the convex hull of the
    calibration's measured spots (P,L,2, NaN where not seen), so a test spot
    (Q,L,2) beyond it is predicted by extrapolation; None when every test spot
    is inside (or no surface is fitted)."""
    measured = test[np.isfinite(test).all(axis=-1)]                       # (M,2)
    try:
        inside = Delaunay(calibration[np.isfinite(calibration).all(axis=-1)]).find_simplex(measured) >= 0
    except QhullError:  # the calibration spots span no area: the surface is known nowhere across the screen
        inside = np.zeros(len(measured), bool)
    outside = int((~inside).sum())
    if not surfaces or not outside:
        return None
    return (f"{outside} of {len(measured)} test spots lie outside the convex hull of the calibration spots: there "
            f"{', '.join(surfaces)} is extrapolated: their test errors say how far it holds beyond the spots it "
            "was fitted on, not how well it fits them")


@dataclass(frozen=True)
class BoxSurface(Surface):
    """A surface over the box the calibration spots cover (``box``: the
    centre and half sizes of their range), in u = (y - centre_y) / half_y,
    v = (z - centre_z) / half_z: a polynomial over the whole screen would be
    fitted on part of its domain, and its folds would extrapolate. Its
    coefficients are lengths in m; scale and typical size 1 mm."""

    centre_y: float
    centre_z: float
    half_y: float
    half_z: float

    @staticmethod
    def box(spots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre (2,) and half sizes (2,) m of the range of the measured spots (P,L,2) (NaN where not seen)."""
        low, high = np.nanmin(spots, axis=(0, 1)), np.nanmax(spots, axis=(0, 1))
        return (low + high) / 2, np.maximum((high - low) / 2, MM)

    @staticmethod
    def box_from_yaml(robot: Robot, entry: Mapping[str, Any], where: str) -> tuple[float, float, float, float]:
        return (yaml_number(where, entry, "centre_y", 0.0), yaml_number(where, entry, "centre_z", 0.0),
                positive_number(where, entry, "half_y", robot.screen.half_y),
                positive_number(where, entry, "half_z", robot.screen.half_z))

    def normalised(self, s: np.ndarray) -> np.ndarray:
        """(u, v) (...,2) of spots s (...,2) m."""
        return (s - np.array([self.centre_y, self.centre_z])) / np.array([self.half_y, self.half_z])

    @property
    def units(self) -> tuple[str, ...]:  # type: ignore[override]
        return ("m",) * len(self.params)

    @property
    def scales(self) -> np.ndarray:
        return np.full(len(self.params), MM)

    @property
    def typical(self) -> np.ndarray:
        return np.full(len(self.params), MM)

    def constants(self) -> dict:
        return {"centre_y": self.centre_y, "centre_z": self.centre_z, "half_y": self.half_y, "half_z": self.half_z}


@dataclass(frozen=True)
class ScreenSurface(BoxSurface):
    """A smooth screen surface (BoxSurface): the 2-D Legendre series

        f = sum over 1 <= i + j <= degree of c_ij (P_i(u) P_j(v) - P_i(0) P_j(0)),

    P_n the Legendre polynomials, nearly orthogonal over the box, so the
    coefficients are nearly uncorrelated and each is about the size of its
    term at the edge of the data (|P_n(1)| = 1). Each term is 0 at the
    centre: a constant is a screen offset, held by the geometric errors.
    Earlier diagnoses chose its degree and wrote it; robot files that hold it
    are read. The diagnosis now fits a screen of any shape as
    effects.screen_spline.ScreenSpline (a polynomial of degree 4 or more
    extrapolates wildly beyond the spots). Degree 2 spans what ScreenShape does.
    """

    kind: ClassVar[str] = "screen_surface"
    title: ClassVar[str] = "screen not flat (smooth surface)"

    degree: int

    @classmethod
    def make(cls, spots: np.ndarray, degree: int) -> "ScreenSurface":
        """The surface of ``degree`` over the range of the measured spots (P,L,2) m (NaN where not seen)."""
        centre, half = cls.box(spots)
        return cls(float(centre[0]), float(centre[1]), float(half[0]), float(half[1]), degree)

    @property
    def params(self) -> tuple[str, ...]:  # type: ignore[override]
        return tuple(f"c{i}{j}" for i, j in surface_terms(self.degree))

    @property
    def tag(self) -> str:
        return "surface"

    @property
    def label(self) -> str:
        return f"{self.kind} (screen, degree {self.degree})"

    def constants(self) -> dict:
        return {**super().constants(), "degree": self.degree}

    @classmethod
    def from_yaml(cls, robot: Robot, entry: Mapping[str, Any], where: str) -> "ScreenSurface":
        degree = entry.get("degree")
        if isinstance(degree, bool) or not isinstance(degree, int) or not 1 <= degree <= MAX_DEGREE:
            raise InputError(f"{where}.degree", f"expected a whole number 1..{MAX_DEGREE}, got {degree!r}")
        return cls(*cls.box_from_yaml(robot, entry, where), degree, camera=robot.screen.camera)

    def terms(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v = np.moveaxis(self.normalised(s), -1, 0)
        derivative = legendre.legder(np.eye(self.degree + 1))   # (degree, degree + 1): column n is P_n'
        pu, pv = legendre.legvander(u, self.degree), legendre.legvander(v, self.degree)   # (..., degree + 1)
        du = legendre.legvander(u, self.degree - 1) @ derivative
        dv = legendre.legvander(v, self.degree - 1) @ derivative
        index = surface_terms(self.degree)
        i, j = np.array([t[0] for t in index]), np.array([t[1] for t in index])
        at_centre = legendre.legval(0.0, np.eye(self.degree + 1))   # (degree + 1,) P_n(0)
        phi = pu[..., i] * pv[..., j] - at_centre[i] * at_centre[j]
        dphi = np.stack([du[..., i] * pv[..., j] / self.half_y, pu[..., i] * dv[..., j] / self.half_z], axis=-1)
        return phi, dphi


@dataclass(frozen=True)
class CameraDistortion(SpotEffect):
    """Residual lens distortion in screen coordinates (Brown-Conrady, centred on
    the screen origin), u = y / R, v = z / R, r^2 = u^2 + v^2, R = ``radius``:

        dy = k1 u r^2 + k2 u r^4 + 2 p1 u v + p2 (r^2 + 2 u^2)
        dz = k1 v r^2 + k2 v r^4 + p1 (r^2 + 2 v^2) + 2 p2 u v

    k1, k2 radial, p1, p2 tangential, all in m (the displacement at r = 1).
    The affine part (scale, shear, offset of the screen coordinates) is left to
    the geometric errors and the screen calibration. Scale 1 mm; typical truth
    1 mm (k1), 0.3 mm (k2), 0.5 mm (p1, p2).
    """

    radius: float

    kind: ClassVar[str] = "camera_distortion"
    title: ClassVar[str] = "residual camera distortion"
    params: ClassVar[tuple[str, ...]] = ("k1", "k2", "p1", "p2")
    units: ClassVar[tuple[str, ...]] = ("m",) * 4
    order: ClassVar[int] = 1

    @property
    def where(self) -> str:
        return "camera"

    @property
    def tag(self) -> str:
        return "distortion"

    @property
    def scales(self) -> np.ndarray:
        return np.full(4, MM)

    @property
    def typical(self) -> np.ndarray:
        return np.array([2.0, 0.5, 1.0, 1.0]) * MM

    def constants(self) -> dict:
        return {"radius": self.radius}

    @classmethod
    def from_yaml(cls, robot: Robot, entry: Mapping[str, Any], where: str) -> "CameraDistortion":
        return cls(positive_number(where, entry, "radius", max(robot.screen.half_y, robot.screen.half_z)))

    def apply(self, spots, beams, values):
        k1, k2, p1, p2 = values
        u, v = spots[..., 0] / self.radius, spots[..., 1] / self.radius
        r2 = u * u + v * v
        uv = u * v
        # d (dy, dz) / d (k1, k2, p1, p2)
        d_values = np.stack([np.stack([u * r2, u * r2 * r2, 2 * uv, r2 + 2 * u * u], axis=-1),
                             np.stack([v * r2, v * r2 * r2, r2 + 2 * v * v, 2 * uv], axis=-1)], axis=-2)
        shift = d_values @ values
        dy_du = k1 * (r2 + 2 * u * u) + k2 * (r2 * r2 + 4 * u * u * r2) + 2 * p1 * v + 6 * p2 * u
        dy_dv = 2 * k1 * uv + 4 * k2 * uv * r2 + 2 * p1 * u + 2 * p2 * v
        dz_du = 2 * k1 * uv + 4 * k2 * uv * r2 + 2 * p1 * u + 2 * p2 * v
        dz_dv = k1 * (r2 + 2 * v * v) + k2 * (r2 * r2 + 4 * v * v * r2) + 6 * p1 * v + 2 * p2 * u
        gradient = np.stack([np.stack([dy_du, dy_dv], axis=-1), np.stack([dz_du, dz_dv], axis=-1)], axis=-2)
        return spots + shift, np.eye(2) + gradient / self.radius, d_values

