"""Calibration targets and the camera-to-screen calibration.

Two targets, two kinds of image:

* a ChArUco board (``CharucoSpec``), printed flat and held in front of the
  camera at several positions and orientations: these views fix the camera
  intrinsics and lens distortion (cv2.calibrateCamera). A flat target seen in a
  single pose cannot do that, and the screen is a single pose.
* ArUco fiducials printed on the white border of the screen, in its plane
  (``ScreenLayout``): views of them with the camera in its final, fixed pose
  fix the homography from undistorted pixels to screen (y, z) metres, and
  help the intrinsics where the distortion is largest, at the image's edge.

Take both in good light: corners are located to ~0.1 px at best (the Bayer
mosaic sets that), and the dim light of the laser measurements adds noise.

``calibrate_screen(board_images, screen_images)`` turns both into the
``ScreenCalibration`` the spot detector uses. Images are bgr8 (H, W, 3) or
mono8 (H, W) uint8 arrays, as in sensor_msgs/Image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from laser_calib.vision.camera import ScreenCalibration

# Corner k of an ArUco marker, as (sign of y, sign of z) about its centre. The
# marker is read from the front (x < 0), where image right is -y and image up
# is +z; ArUco lists corners top-left, top-right, bottom-right, bottom-left.
_CORNER_SIGNS = np.array([(1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)])


@dataclass(frozen=True)
class ScreenLayout:
    """The screen and the ArUco fiducials on its border (metres, frame {0}).

    border: half size of the white board that carries the measuring area
    (|y|, |z| <= 1 m by default, see DetectorOptions) and the fiducials;
    beyond it is the wall. marker_centres: (y, z) of each marker's
    centre; marker i has id marker_ids[i] of ``dictionary`` and side
    marker_side (black border included). The default puts 8 markers of
    DICT_4X4_50 around the area, outside it, so a laser spot never lands on one.
    """

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


_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


def _undistort(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Undistorted pixels (M,2) (P = K) of distorted pixels (M,2)."""
    return cv2.undistortPoints(pixels.reshape(-1, 1, 2).astype(np.float64), K, dist, P=K,
                               criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)


def _edge_corners(gray: np.ndarray, corners: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray | None:
    """Corners (4,2) of one marker in undistorted pixels, from its four outer edges.

    ArUco's corner refinement (cornerSubPix) pulls the corners of a blurred
    black square inwards by ~0.25 px here; an edge, in contrast, is located
    without bias where a profile across it crosses halfway between the dark
    and the light side. Each side is sampled at 15 points, the edge points are
    undistorted (lens distortion bends a 50 px side by ~0.1 px) and fitted by a
    line, and the corners are where neighbouring lines meet.
    """
    offsets = np.arange(-3.0, 3.0 + 1e-9, 0.25)
    lines = []
    for k in range(4):
        start, end = corners[k], corners[(k + 1) % 4]
        along = (end - start) / np.linalg.norm(end - start)
        normal = np.array([-along[1], along[0]])
        points = start + np.linspace(0.15, 0.85, 15)[:, None] * (end - start)
        samples = (points[:, None, :] + offsets[None, :, None] * normal).astype(np.float32)
        profiles = cv2.remap(gray, samples[..., 0], samples[..., 1], cv2.INTER_LINEAR)
        edge = []
        for point, profile in zip(points, profiles):
            middle = 0.5 * (profile[:3].mean() + profile[-3:].mean())
            above = profile > middle
            crossings = np.nonzero(above[:-1] != above[1:])[0]
            if len(crossings) == 0:
                continue
            i = crossings[np.argmin(np.abs(crossings - len(offsets) // 2))]
            fraction = (middle - profile[i]) / (profile[i + 1] - profile[i])
            edge.append(point + (offsets[i] + fraction * 0.25) * normal)
        if len(edge) < 5:
            return None
        edge = _undistort(np.array(edge), K, dist)
        centre = edge.mean(axis=0)
        direction = np.linalg.svd(edge - centre)[2][0]
        line_normal = np.array([-direction[1], direction[0]])
        lines.append((line_normal, line_normal @ centre))
    return np.array([np.linalg.solve(np.array([lines[k - 1][0], lines[k][0]]), [lines[k - 1][1], lines[k][1]])
                     for k in range(4)])


def detect_fiducials(image: np.ndarray, K: np.ndarray, dist: np.ndarray, layout: ScreenLayout = ScreenLayout()
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Corners of the layout's fiducials found in one image, given the camera's K (3,3) and dist (5,).

    Returns (pixels (M,2) undistorted image pixels (P = K), screen_yz (M,2)
    metres), four rows per marker found, in the order of layout.marker_ids.
    """
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(layout.dictionary), parameters)
    gray = _gray(image)
    corners, ids, _ = detector.detectMarkers(gray)
    found = {} if ids is None else {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners)}
    gray = gray.astype(np.float32)
    screen = layout.marker_corners()
    pixels, known = [], []
    for k, marker_id in enumerate(layout.marker_ids):
        refined = _edge_corners(gray, found[marker_id], K, dist) if marker_id in found else None
        if refined is not None:
            pixels.append(refined)
            known.append(screen[k])
    if not pixels:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(pixels), np.concatenate(known)


class TooFewBoardViews(ValueError):
    """The board images leave fewer than 4 usable ChArUco views (the command names their folder)."""


class TooFewFiducials(ValueError):
    """The screen images show fewer than 4 fiducials (the command names their folder)."""


class ScreenViewMoved(ValueError):
    """Screen view ``index`` puts the fiducials ``offset`` px away from where the other views put
    them: the camera moved between the screen views (the command names the image)."""

    def __init__(self, index: int, offset: float):
        super().__init__(f"its fiducial corners lie {offset:.2g} px (median) from the other screen views': the camera "
                         "moved between them (it must stay fixed; take the screen views again)")
        self.index = index


# A screen view's fiducial corners lie this far (median, px) from the other views' at most: a fixed
# camera's detections agree to a tenth of a pixel (rendered views with noise, JPEG or blur: 0.02-0.11),
# and one pixel is 2-3 mm on the screen, ten times a spot's noise. The views' corners are averaged
# into the map, so a camera bumped between them was written silently (26 mm RMS at 20 px).
VIEW_AGREEMENT = 1.0


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


def _mean_fiducials(images: Sequence[np.ndarray], K: np.ndarray, dist: np.ndarray, layout: ScreenLayout
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Fiducial corners averaged over images: (undistorted pixels (M,2), screen (y, z) (M,2))."""
    found: dict[tuple[float, float], list[tuple[int, np.ndarray]]] = {}
    for index, image in enumerate(images):
        for pixel, point in zip(*detect_fiducials(image, K, dist, layout)):
            found.setdefault(tuple(point), []).append((index, pixel))
    if len(found) < 16:
        raise TooFewFiducials(f"found {len(found) // 4} screen fiducials, need at least 4 (8 ArUco markers of "
                              "DICT_4X4_50, ids 0-7, 120 mm, centred at (+-1.09, +-1.09), (0, +-1.09) and "
                              "(+-1.09, 0) m on the screen: vision.screen_calibration.ScreenLayout)")
    centre = {point: np.median([pixel for _, pixel in seen], axis=0) for point, seen in found.items()}
    offsets: dict[int, list[float]] = {}
    for point, seen in found.items():
        for index, pixel in seen:
            offsets.setdefault(index, []).append(float(np.linalg.norm(pixel - centre[point])))
    index, offset = max(((i, float(np.median(o))) for i, o in offsets.items()), key=lambda item: item[1])
    if offset > VIEW_AGREEMENT:
        raise ScreenViewMoved(index, offset)
    return (np.array([np.mean([pixel for _, pixel in seen], axis=0) for seen in found.values()]),
            np.array(list(found)))


def _distort(undistorted: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Distorted pixels (M,2) of undistorted pixels (M,2) (P = K): the inverse of _undistort."""
    rays = np.column_stack([(undistorted - K[:2, 2]) / np.diag(K)[:2], np.ones(len(undistorted))])
    return cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)


def calibrate_screen(board_images: Sequence[np.ndarray], screen_images: Sequence[np.ndarray],
                     board: CharucoSpec = CharucoSpec(), layout: ScreenLayout = ScreenLayout()
                     ) -> ScreenCalibration:
    """Intrinsics, distortion and the pixel-to-screen homography from two sets of images.

    board_images: views of the ChArUco ``board`` held at different positions
    and orientations, together covering the image out to its corners (at
    least 4 usable views; 20 to 30 tilted 20 to 40 degrees are good, see
    render.board_poses). screen_images: views of the screen's fiducials
    (``layout``) from the camera's final, fixed pose; their corners are averaged
    (5 to 10 images beat down detection noise; at least 4 markers must be
    found). All images have the same size. Raises ValueError if either set is
    not enough.

    Steps: intrinsics from the board views (cv2.calibrateCamera); fiducial
    corners located with them; intrinsics again with the fiducials as one more
    planar view, because they sit at the edge of the image where distortion is
    largest and they lie in the plane the spots are measured in (this halves
    the error of the pixel-to-screen map); finally the homography from the
    undistorted fiducial corners to their screen positions (cv2.findHomography).
    """
    if not board_images or not screen_images:
        raise ValueError("need both ChArUco board images and screen fiducial images")
    height, width = board_images[0].shape[:2]
    object_points, image_points = _board_points(board_images, board)
    if len(object_points) < 4:
        raise TooFewBoardViews(f"only {len(object_points)} usable ChArUco views, need at least 4 (the board: "
                               f"{board.squares_x} x {board.squares_y} squares, markers of "
                               f"{'DICT_5X5_100' if board.dictionary == cv2.aruco.DICT_5X5_100 else board.dictionary};"
                               " vision.screen_calibration.CharucoSpec)")
    _, K, dist, _, _ = cv2.calibrateCamera(object_points, image_points, (width, height), None, None)
    undistorted, known = _mean_fiducials(screen_images, K, dist.ravel()[:5], layout)
    object_points.append(np.column_stack([known, np.zeros(len(known))]).astype(np.float32))
    image_points.append(_distort(undistorted, K, dist).astype(np.float32))
    rms_px, K, dist, _, _ = cv2.calibrateCamera(object_points, image_points, (width, height), None, None)
    dist = dist.ravel()[:5]
    undistorted, known = _mean_fiducials(screen_images, K, dist, layout)
    homography, _ = cv2.findHomography(undistorted, known, 0)
    return ScreenCalibration(width, height, K, dist, homography / homography[2, 2], rms_px)
