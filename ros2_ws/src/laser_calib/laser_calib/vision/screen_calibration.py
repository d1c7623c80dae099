"""Calibration targets and the camera-to-screen calibration.

Two targets, two kinds of image:

* a ChArUco board (``CharucoSpec``), printed flat and held in front of the
  camera at several positions and orientations: these views fix the camera
  intrinsics and lens distortion (cv2.calibrateCamera). A flat target seen in a
  single pose cannot do that, and the screen is a single pose.
* ArUco fiducials printed on the white border of the screen, in its plane
  (``ScreenLayout``): a view of them with the camera in its final, fixed pose
  fixes the homography from undistorted pixels to screen (y, z) metres.

``calibrate_screen(board_images, screen_images)`` turns both into the
``ScreenCalibration`` the spot detector uses. Images are bgr8 (H, W, 3) or
mono8 (H, W) uint8 arrays, as in sensor_msgs/Image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .camera import ScreenCalibration

# Corner k of an ArUco marker, as (sign of y, sign of z) about its centre. The
# marker is read from the front (x < 0), where image right is -y and image up
# is +z; ArUco lists corners top-left, top-right, bottom-right, bottom-left.
_CORNER_SIGNS = np.array([(1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)])


@dataclass(frozen=True)
class ScreenLayout:
    """The screen and the ArUco fiducials on its border (metres, frame {0}).

    half_y, half_z: half size of the measuring area (conventions.md ``screen``).
    border: half size of the white board that carries the area and the
    fiducials; beyond it is the wall. marker_centres: (y, z) of each marker's
    centre; marker i has id marker_ids[i] of ``dictionary`` and side
    marker_side (black border included). The default puts 8 markers of
    DICT_4X4_50 around the area, outside it, so a laser spot never lands on one.
    """

    half_y: float = 1.0
    half_z: float = 1.0
    border: float = 1.2
    marker_side: float = 0.12
    marker_centres: tuple[tuple[float, float], ...] = (
        (1.09, 1.09), (0.0, 1.09), (-1.09, 1.09), (-1.09, 0.0),
        (-1.09, -1.09), (0.0, -1.09), (1.09, -1.09), (1.09, 0.0))
    marker_ids: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7)
    dictionary: int = cv2.aruco.DICT_4X4_50

    def marker_corners(self) -> np.ndarray:
        """(n_markers, 4, 2): screen (y, z) of each marker's corners, in ArUco order."""
        centres = np.asarray(self.marker_centres, dtype=float)
        return centres[:, None, :] + 0.5 * self.marker_side * _CORNER_SIGNS[None]


@dataclass(frozen=True)
class CharucoSpec:
    """A ChArUco board: squares_x by squares_y squares of side ``square`` (m),
    markers of side ``marker`` (m) from ``dictionary`` (DICT_5X5_100 by default,
    so that its markers can never be taken for the screen's fiducials).
    Default: 10 x 7 squares of 80 mm, an 0.8 m x 0.56 m board (A1 paper).
    """

    squares_x: int = 10
    squares_y: int = 7
    square: float = 0.08
    marker: float = 0.06
    dictionary: int = cv2.aruco.DICT_5X5_100

    def board(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(self.dictionary)
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square, self.marker, dictionary)


def _gray(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image


def detect_fiducials(image: np.ndarray, layout: ScreenLayout = ScreenLayout()) -> tuple[np.ndarray, np.ndarray]:
    """Corners of the layout's fiducials found in one image.

    Returns (pixels (M,2) distorted image pixels, screen_yz (M,2) metres), four
    rows per marker found, in the order of layout.marker_ids.
    """
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(layout.dictionary), parameters)
    corners, ids, _ = detector.detectMarkers(_gray(image))
    found = {} if ids is None else {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners)}
    screen = layout.marker_corners()
    pixels, known = [], []
    for k, marker_id in enumerate(layout.marker_ids):
        if marker_id in found:
            pixels.append(found[marker_id])
            known.append(screen[k])
    if not pixels:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(pixels).astype(float), np.concatenate(known)


def _board_points(images: Sequence[np.ndarray], spec: CharucoSpec) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Object (N,3) and image (N,2) points of the ChArUco corners in each usable view."""
    board = spec.board()
    detector = cv2.aruco.CharucoDetector(board)
    object_points, image_points = [], []
    for image in images:
        corners, ids, _, _ = detector.detectBoard(_gray(image))
        # A view with few corners, or all of them on one line, says nothing about the focal length.
        if ids is None or len(ids) < 8 or board.checkCharucoCornersCollinear(ids):
            continue
        obj, img = board.matchImagePoints(corners, ids)
        object_points.append(obj.reshape(-1, 3).astype(np.float32))
        image_points.append(img.reshape(-1, 2).astype(np.float32))
    return object_points, image_points


def calibrate_screen(board_images: Sequence[np.ndarray], screen_images: Sequence[np.ndarray],
                     board: CharucoSpec = CharucoSpec(), layout: ScreenLayout = ScreenLayout()
                     ) -> ScreenCalibration:
    """Intrinsics, distortion and the pixel-to-screen homography from two sets of images.

    board_images: views of the ChArUco ``board`` held at different positions and
    orientations, covering the image out to its corners (at least 4 usable
    views; 10 to 20 tilted up to ~40 degrees are typical). screen_images: one or
    more views of the screen's fiducials (``layout``) from the camera's final
    pose; corners are averaged over them, which beats down detection noise
    (at least 4 markers must be found). All images have the same size.
    Raises ValueError if either set is not enough.
    """
    if not board_images or not screen_images:
        raise ValueError("need both ChArUco board images and screen fiducial images")
    height, width = board_images[0].shape[:2]
    object_points, image_points = _board_points(board_images, board)
    if len(object_points) < 4:
        raise ValueError(f"only {len(object_points)} usable ChArUco views, need at least 4")
    _, K, dist, _, _ = cv2.calibrateCamera(object_points, image_points, (width, height), None, None)

    per_image = [detect_fiducials(image, layout) for image in screen_images]
    sums: dict[tuple[float, float], tuple[np.ndarray, int]] = {}
    for pixels, known in per_image:
        for pixel, point in zip(pixels, known):
            total, count = sums.get(tuple(point), (np.zeros(2), 0))
            sums[tuple(point)] = (total + pixel, count + 1)
    if len(sums) < 16:
        raise ValueError(f"found {len(sums) // 4} screen fiducials, need at least 4")
    known = np.array(list(sums))
    pixels = np.array([total / count for total, count in sums.values()])
    undistorted = cv2.undistortPoints(pixels.reshape(-1, 1, 2), K, dist, P=K,
                                      criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12))
    homography, _ = cv2.findHomography(undistorted.reshape(-1, 2), known, 0)
    return ScreenCalibration(width, height, K, dist.ravel()[:5], homography / homography[2, 2])
