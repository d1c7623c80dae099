"""The camera that watches the screen, and the calibration that maps its pixels to the screen.

Frames (conventions.md): the screen is the plane x = 0 of frame {0}; a screen
point (y, z) in metres is the 3-D point (0, y, z). The arm, and the camera, stand
on the x < 0 side. Camera frame as in OpenCV and ROS optical frames: x right,
y down, z forward. Pixels are (u, v) = (column, row) with the centre of the
top-left pixel at (0, 0), as in OpenCV.

Distortion is OpenCV's (k1, k2, p1, p2, k3), which is also the order of ROS
CameraInfo ``D`` for the ``plumb_bob`` model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from laser_calib.io.errors import InputError
from laser_calib.io.read import load_yaml, read_text


def _frozen_array(value: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    """A read-only float copy of ``value`` with the given shape (frozen dataclasses hold these)."""
    array = np.array(value, dtype=float)
    if array.size != math.prod(shape):
        raise ValueError(f"{name} must have {math.prod(shape)} values, shape {shape}; got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} is not finite")
    array = array.reshape(shape)
    array.flags.writeable = False
    return array


# eq=False: the fields are arrays, so instances compare and hash by identity
# (render.py caches per-camera pixel maps on that).
@dataclass(frozen=True, eq=False)
class CameraModel:
    """A pinhole camera with lens distortion looking at the screen.

    width, height: image size in pixels. K (3,3): intrinsics in pixels.
    dist (5,): (k1, k2, p1, p2, k3). rvec (3,), tvec (3,): pose of the screen
    frame {0} in the camera frame (X_cam = R(rvec) X_0 + tvec, metres), as
    returned by cv2.solvePnP.
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray

    def __post_init__(self) -> None:
        for name, shape in (("K", (3, 3)), ("dist", (5,)), ("rvec", (3,)), ("tvec", (3,))):
            object.__setattr__(self, name, _frozen_array(getattr(self, name), shape, name))

    @property
    def rotation(self) -> np.ndarray:
        """R (3,3): screen frame {0} to camera frame."""
        return cv2.Rodrigues(self.rvec)[0]

    @property
    def position(self) -> np.ndarray:
        """Camera centre in frame {0}, metres, shape (3,)."""
        return -self.rotation.T @ self.tvec

    def project(self, points_yz: np.ndarray) -> np.ndarray:
        """Pixels (M,2) of screen points (y, z) (M,2) in metres, with lens distortion."""
        points_yz = np.asarray(points_yz, dtype=float).reshape(-1, 2)
        points = np.column_stack([np.zeros(len(points_yz)), points_yz])
        pixels, _ = cv2.projectPoints(points, self.rvec, self.tvec, self.K, self.dist)
        return pixels.reshape(-1, 2)

    def screen_to_pixel_homography(self) -> np.ndarray:
        """H (3,3): screen (y, z, 1) to undistorted pixel (u, v, 1), up to scale.

        A point (0, y, z) lands on K (R[:,1] y + R[:,2] z + t): a homography of (y, z, 1).
        """
        r = self.rotation
        return self.K @ np.column_stack([r[:, 1], r[:, 2], self.tvec])

    def ideal_calibration(self) -> "ScreenCalibration":
        """The exact calibration of this camera (what calibrate_screen estimates)."""
        h = np.linalg.inv(self.screen_to_pixel_homography())
        return ScreenCalibration(self.width, self.height, self.K, self.dist, h / h[2, 2])


def look_at(position: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0)
            ) -> tuple[np.ndarray, np.ndarray]:
    """(rvec, tvec) of frame {0} in a camera at ``position`` looking at ``target`` (both (3,), m).

    The image's 'up' (-y of the camera) leans towards ``up``.
    """
    forward = np.asarray(target, float) - np.asarray(position, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.vstack([right, down, forward])  # rows: camera axes in frame {0}
    rvec = cv2.Rodrigues(rotation)[0].ravel()
    return rvec, -rotation @ np.asarray(position, float)


def default_camera() -> CameraModel:
    """The stationary camera of the paper's set-up (our numbers; the paper gives none).

    1280 x 1024 px at (-2.45, -0.3, 0.55) m, i.e. 2.45 m in front of the screen,
    above and to the side of its centre so that it looks over the arm (which
    stands ~0.5 m in front of the screen), 12 degrees off the screen normal. It
    aims at (0, -0.05, 0.08) so that the screen and its fiducial border
    (|y|, |z| <= 1.15 m) are centred with ~50 px to spare. Focal length 1030 px
    (a 5.5 mm lens on 5.3 um pixels); the barrel distortion k1 = -0.12 of such a
    wide lens moves the image corners by ~50 px. Pixel footprint on the screen:
    2.2 to 3.1 mm (2.5 mm at the centre).
    """
    rvec, tvec = look_at(np.array([-2.45, -0.3, 0.55]), np.array([0.0, -0.05, 0.08]))
    K = np.array([[1030.0, 0.0, 645.2], [0.0, 1030.0, 508.7], [0.0, 0.0, 1.0]])
    dist = np.array([-0.12, 0.05, 4e-4, -3e-4, 0.0])
    return CameraModel(1280, 1024, K, dist, rvec, tvec)


@dataclass(frozen=True, eq=False)
class ScreenCalibration:
    """What the spot detector needs to turn pixels into screen metres.

    width, height: image size in pixels the calibration is valid for.
    K (3,3), dist (5,): intrinsics and distortion (k1, k2, p1, p2, k3).
    homography (3,3): undistorted pixel (u, v, 1) to screen (y, z, 1) in metres,
    normalised so that homography[2,2] = 1.
    reprojection_rms_px: how well K and dist fit the views they were fitted to (cv2.calibrateCamera's
    RMS), px; nan when not known (not kept in the file).
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    homography: np.ndarray
    reprojection_rms_px: float = float("nan")

    def __post_init__(self) -> None:
        for name, shape in (("K", (3, 3)), ("dist", (5,)), ("homography", (3, 3))):
            object.__setattr__(self, name, _frozen_array(getattr(self, name), shape, name))
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width} x {self.height}")
        # a singular map sends every pixel to one point: spots that look measured, all wrong
        K, h = self.K, self.homography
        if not (K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == 0 and np.array_equal(K[2], [0.0, 0.0, 1.0])):
            raise ValueError(f"camera_matrix is no camera's intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with "
                             f"fx, fy > 0: got {K.tolist()}")
        if not abs(np.linalg.det(h)) > 1e-12 * np.prod(np.linalg.norm(h, axis=1)):
            raise ValueError("homography is singular: it maps the image onto a line or a point, not the screen")

    @property
    def centre(self) -> np.ndarray:
        """The camera's centre (3,) in frame {0}, m: the homography's inverse is
        K [R_y R_z t] up to scale (CameraModel.screen_to_pixel_homography), so
        with M = K^-1 homography^-1 scaled to unit columns (the sign that puts
        the screen in front of the camera), R_x = R_y x R_z and C = -R^T t. A
        screen that is not flat needs it (the robot file's screen.camera)."""
        m = np.linalg.solve(self.K, np.linalg.inv(self.homography))
        m = m / np.sqrt(np.linalg.norm(m[:, 0]) * np.linalg.norm(m[:, 1]))
        if m[2, 2] < 0:  # the screen's origin in front of the camera
            m = -m
        rotation = np.column_stack([np.cross(m[:, 0], m[:, 1]), m[:, 0], m[:, 1]])
        return -rotation.T @ m[:, 2]

    def distortion_difference_px(self, dist: np.ndarray) -> float:
        """The largest distance, px, between where this calibration's distortion and ``dist`` (k1 k2 p1 p2
        k3, a driver's CameraInfo D) undistort the image's border (a 9 x 9 grid's edge points): how far
        apart the two lens models put a spot at the image's edge. The detector uses its calibration's;
        a driver whose D differs (a lens changed, refocused) says the calibration is stale."""
        edge = np.linspace(0.0, 1.0, 9)
        border = np.array([(u, v) for u in edge for v in edge if u in (0.0, 1.0) or v in (0.0, 1.0)])
        pixels = (border * [self.width - 1, self.height - 1]).reshape(-1, 1, 2)
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        mine, theirs = (cv2.undistortPoints(pixels, self.K, np.asarray(d, float), P=self.K, criteria=criteria)
                        for d in (self.dist, dist))
        return float(np.max(np.linalg.norm(mine - theirs, axis=-1)))

    def pixels_to_screen(self, pixels: np.ndarray) -> np.ndarray:
        """Screen (y, z) in metres (M,2) of distorted image pixels (M,2)."""
        pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if len(pixels) == 0:
            return np.zeros((0, 2))
        # OpenCV's default of 5 iterations leaves 1e-4 px here, more with stronger distortion.
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        undistorted = cv2.undistortPoints(pixels, self.K, self.dist, P=self.K, criteria=criteria)
        return cv2.perspectiveTransform(undistorted, self.homography).reshape(-1, 2)


def calibration_to_dict(calibration: ScreenCalibration) -> dict[str, Any]:
    return {
        "image_width": int(calibration.width),
        "image_height": int(calibration.height),
        "camera_matrix": calibration.K.tolist(),
        "distortion": calibration.dist.tolist(),
        "homography": calibration.homography.tolist(),
    }


def calibration_from_dict(data: Any, source: str = "<calibration>") -> ScreenCalibration:
    if not isinstance(data, dict):
        raise InputError(source, f"expected a mapping, got {type(data).__name__}")
    for key in ("image_width", "image_height", "camera_matrix", "distortion", "homography"):
        if key not in data:
            raise InputError(source, f"missing key '{key}'")
    for key in ("image_width", "image_height"):
        if isinstance(data[key], bool) or not isinstance(data[key], int):
            raise InputError(f"{source}.{key}", f"expected an integer, got {data[key]!r}")
    try:
        return ScreenCalibration(data["image_width"], data["image_height"], data["camera_matrix"],
                                 data["distortion"], data["homography"])
    except (ValueError, TypeError) as error:
        raise InputError(source, str(error)) from None


_HEADER = ("# Screen calibration (laser_calib.vision): camera intrinsics, distortion (k1 k2 p1 p2 k3,\n"
           "# ROS plumb_bob) and the homography from undistorted pixel (u, v, 1) to screen (y, z, 1), m.\n")


def save_calibration(calibration: ScreenCalibration, path: str | Path) -> None:
    text = yaml.safe_dump(calibration_to_dict(calibration), sort_keys=False, default_flow_style=None)
    Path(path).write_text(_HEADER + text)


def load_calibration(path: str | Path) -> ScreenCalibration:
    path = Path(path)
    text = read_text(path)  # UTF-8 or one line naming the file
    # one line naming the file and line (yaml's own message is a multi-line dump of '<unicode string>')
    return calibration_from_dict(load_yaml(text, str(path)), str(path))
