"""Rotation helpers for the sensor models: quaternions, the log map of SO(3)
and the inverse of its left Jacobian. Stacked over any leading shape (...)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x (...,3,3) with [v]x w = v x w, for v (...,3)."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def quaternion_to_matrix(quaternion: np.ndarray) -> np.ndarray:
    """(...,4) unit quaternions (qw, qx, qy, qz), normalised here, to (...,3,3)."""
    q = np.asarray(quaternion, float)
    flat = q.reshape(-1, 4)
    matrices = Rotation.from_quat(flat[:, [1, 2, 3, 0]]).as_matrix()
    return matrices.reshape(q.shape[:-1] + (3, 3))


def matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    """(...,3,3) to (...,4) (qw, qx, qy, qz) with qw >= 0 (one of the two signs, fixed)."""
    r = np.asarray(rotation, float)
    xyzw = Rotation.from_matrix(r.reshape(-1, 3, 3)).as_quat()
    wxyz = xyzw[:, [3, 0, 1, 2]] * np.where(xyzw[:, 3:4] < 0, -1.0, 1.0)
    return wxyz.reshape(r.shape[:-2] + (4,))


def log_rotation(rotation: np.ndarray) -> np.ndarray:
    """Rotation vector (...,3), rad, of rotations (...,3,3)."""
    r = np.asarray(rotation, float)
    return Rotation.from_matrix(r.reshape(-1, 3, 3)).as_rotvec().reshape(r.shape[:-2] + (3,))


def left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """J_l^-1(phi) (...,3,3): log(exp(d) exp(phi)) = phi + J_l^-1(phi) d + O(d^2).

    J_l^-1 = I - [phi]x / 2 + (1/t^2 - (1 + cos t) / (2 t sin t)) [phi]x^2, t = |phi|;
    the coefficient tends to 1/12 as t -> 0 (series used below 1e-4 rad).
    """
    t = np.linalg.norm(phi, axis=-1)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    coefficient = np.where(small, 1.0 / 12.0 + t ** 2 / 720.0,
                           1.0 / ts ** 2 - (1.0 + np.cos(ts)) / (2.0 * ts * np.sin(ts)))
    k = skew(phi)
    return np.eye(3) - 0.5 * k + coefficient[..., None, None] * (k @ k)
