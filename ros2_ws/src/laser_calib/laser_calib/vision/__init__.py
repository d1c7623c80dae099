"""ROS-free vision for the stationary camera: simulate it, calibrate it, find the laser spots.

- camera: CameraModel (intrinsics, distortion, pose of the screen), the
  default camera of the paper's set-up, ScreenCalibration (what the detector
  needs: K, distortion, undistorted-pixel-to-screen homography) and its YAML file.
- render: synthetic bgr8 frames of the screen with the two laser spots (laser 1
  red, laser 2 green), of its fiducials alone, and of a ChArUco board.
- screen_calibration: the calibration targets and calibrate_screen.
- detect: SpotDetector, frame -> screen (y, z) of each laser in metres, or NaN.

Screen coordinates are (y, z) in metres on the plane x = 0 of frame {0}
(conventions.md); images are sensor_msgs/Image-compatible numpy arrays.
"""

from laser_calib.vision.camera import CameraModel, ScreenCalibration, default_camera, load_calibration, save_calibration
from laser_calib.vision.detect import DetectorOptions, SpotDetector
from laser_calib.vision.render import ENCODING, RenderOptions, board_poses, render_board_frame, render_fiducial_frame, render_frame
from laser_calib.vision.screen_calibration import CharucoSpec, ScreenLayout, calibrate_screen, detect_fiducials

__all__ = [
    "CameraModel", "ScreenCalibration", "default_camera", "load_calibration", "save_calibration",
    "DetectorOptions", "SpotDetector",
    "ENCODING", "RenderOptions", "board_poses", "render_board_frame", "render_fiducial_frame", "render_frame",
    "CharucoSpec", "ScreenLayout", "calibrate_screen", "detect_fiducials",
]
