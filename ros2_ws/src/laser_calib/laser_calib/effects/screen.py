"""Spot effects (base.SPOT): the screen is not flat, the camera's residual distortion.

Both act on the predicted spot s = (y, z) (m) of the flat-screen model, in
normalised screen coordinates so that every coefficient is a length in metres
(its size at the screen edge). They are applied in physical order: the beam
meets the real surface (ScreenShape), then the camera reports where it sees the
spot (CameraDistortion).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

import numpy as np

from laser_calib.effects.base import SpotEffect, positive_number
from laser_calib.model.robot import Robot

MM = 1e-3
FIXED_POINT_ITERATIONS = 6  # |grad f . t| ~ 1e-3: six iterations reach 1e-18 m


@dataclass(frozen=True)
class ScreenShape(SpotEffect):
    """The screen surface is x = f(y, z), not x = 0:

        f = c_u u + c_v v + c_uu u^2 + c_uv u v + c_vv v^2,   u = y / half_y, v = z / half_z

    (no constant term: a screen offset along x is the same as moving the base,
    which the geometric errors already hold). The beam p + k z meets it where
    p_x + k z_x = f(s): with the flat spot s0 and t = (z_y, z_z) / z_x,

        s = s0 + f(s) t                                                (1)

    solved by fixed-point iteration (exact). Differentiating (1),
    (I - t grad f^T) ds = ds0 + t phi^T dc (+ f dt, neglected: second order,
    f ~ mm times the beam-direction change), so
    d s / d s0 = (I - t g^T)^-1 = I + t g^T / (1 - g.t) and
    d s / d c = t phi^T / (1 - g.t), g = grad f.
    Coefficients in m (the height at the screen edge); scale 1 mm; typical
    truth 1 mm (linear terms) and 2 mm (quadratic terms).
    """

    half_y: float
    half_z: float

    kind: ClassVar[str] = "screen_shape"
    title: ClassVar[str] = "screen not flat"
    params: ClassVar[tuple[str, ...]] = ("u", "v", "uu", "uv", "vv")
    units: ClassVar[tuple[str, ...]] = ("m",) * 5
    order: ClassVar[int] = 0

    @property
    def where(self) -> str:
        return "screen"

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
                   positive_number(where, entry, "half_z", robot.screen.half_z))

    def _terms(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """phi (...,5) and d phi / d s (...,5,2) at spots s (...,2)."""
        u, v = s[..., 0] / self.half_y, s[..., 1] / self.half_z
        zero = np.zeros_like(u)
        phi = np.stack([u, v, u * u, u * v, v * v], axis=-1)
        dphi_du = np.stack([1 + zero, zero, 2 * u, v, zero], axis=-1) / self.half_y
        dphi_dv = np.stack([zero, 1 + zero, zero, u, 2 * v], axis=-1) / self.half_z
        return phi, np.stack([dphi_du, dphi_dv], axis=-1)

    def apply(self, spots, beams, values):
        t = beams[..., 1:] / beams[..., :1]
        s = spots
        for _ in range(FIXED_POINT_ITERATIONS):
            phi, _ = self._terms(s)
            s = spots + (phi @ values)[..., None] * t
        phi, dphi = self._terms(s)
        g = np.einsum("...kd,k->...d", dphi, values)
        denominator = (1.0 - np.einsum("...d,...d->...", g, t))[..., None, None]
        d_spots = np.eye(2) + t[..., :, None] * g[..., None, :] / denominator
        d_values = t[..., :, None] * phi[..., None, :] / denominator
        return s, d_spots, d_values


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

