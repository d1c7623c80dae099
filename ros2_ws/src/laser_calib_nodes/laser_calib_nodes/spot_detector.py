"""spot_detector: camera frames in, the two laser spots on the screen out.

Subscribes  camera/image_raw (sensor_msgs/Image), best effort (the sensor-data QoS
            camera drivers publish with) and reliable (camera_sim), whichever the
            publisher offers; in any encoding of laser_calib.vision.encodings
            (bgr8, rgb8, bayer_*8, yuv422, yuv422_yuy2; mono8 only as a raw
            mosaic, ``mono_pattern``), detected with
            laser_calib.vision.detect.SpotDetector and the screen calibration
            (``calibration`` file; empty: the simulated camera's exact one).
            camera/camera_info (sensor_msgs/CameraInfo): the driver's image size
            must be the calibration's (else frames are refused, one line); its
            intrinsics are compared with the calibration's (a warning when they
            differ: the camera was changed or refocused since screen-calibrate).
            Also transient local, for a driver that latches it. While the topic
            has a publisher but none has come, INFO_WAIT_FRAMES frames are held
            back; then a warning, and the frames are detected unchecked.
Publishes   laser1/spot, laser2/spot (geometry_msgs/PointStamped, frame
            `screen`: x = 0, y, z in metres), only when that laser is seen.
            spots (laser_calib_interfaces/SpotPair): both lasers of every
            frame, with seen = false (and NaN) for a missing spot, which is what
            the sequencer and the estimator use: they can tell a frame without
            a spot from a frame not yet arrived. A spot there but refused (not one
            clean spot, white light, ambiguous, cut by the image edge, too large)
            is a WARN line with why, at most one every 5 s.
Capture     ``capture_dir`` non-empty: also save ``capture_count`` frames, one
            every ``capture_period`` s, as PNG (bgr8) for `laser-calib
            screen-calibrate` (board views while the board is moved, or screen
            views), then carry on detecting. Frames are saved whatever the
            calibration (they are for making one): a camera of another size than
            the calibration's has its frames saved, and refused for detection.
All outputs carry the image's stamp.
"""

from __future__ import annotations

import dataclasses
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from laser_calib.vision.camera import default_camera, load_calibration
from laser_calib.vision.detect import DetectorOptions, SpotDetector
from laser_calib.vision.encodings import pattern_of, to_bgr8

from laser_calib_nodes import common, parameters

# Frames held back waiting for a CameraInfo a publisher on the topic has not sent. A driver sends one
# with each frame, and it may come second; one that sent it once, volatile, before this node started
# never will, and waiting for it would refuse the whole session's frames.
INFO_WAIT_FRAMES = 5
RECENT_FRAMES = 20   # stamps remembered, to use a frame two subscriptions deliver once
PIXEL_SAMPLE = 997   # every 997th byte tells two frames apart (noise alone differs in thousands of them)
# A lens model off by a pixel at the image's edge moves a spot there by 2-3 mm on the screen, 20 times the
# detector's noise; the calibration's own reprojection error is a few tenths of a pixel.
DISTORTION_TOLERANCE_PX = 1.0


class SpotDetectorNode(Node):
    def __init__(self):
        super().__init__("spot_detector")
        d = lambda *a, **k: parameters.declare(self, *a, **k)  # noqa: E731
        path = d("calibration", "", "Screen calibration file (laser_calib.vision, YAML); "
                                    "empty: the exact calibration of the simulated camera.")
        # a measuring area of no size: no spot is ever inside, every frame 'not seen'
        half_y = d("screen.half_y", 1.0, "Measuring area half width, m (robot file 'screen').",
                   rule=parameters.positive)
        half_z = d("screen.half_z", 1.0, "Measuring area half height, m (robot file 'screen').",
                   rule=parameters.positive)
        min_peak = d("min_peak_dn", DetectorOptions().min_peak_dn, "Least smoothed colour contrast of a spot, DN "
                                                                  "(settable at run time, from the next frame).",
                     read_only=False, rule=parameters.inside(0.0, 255.0))   # an 8-bit image's contrast
        pattern = d("bayer_pattern", "RGGB", "Photosite mosaic behind demosaiced (rgb8/bgr8) images; 'none' for a "
                                             "camera measuring every colour per pixel. Raw bayer_* images give it.")
        self.mono_pattern = d("mono_pattern", "", "mono8 images are this raw Bayer mosaic (e.g. RGGB); empty: "
                                                  "mono8 is refused (it cannot tell the lasers apart).") or None
        defaults = DetectorOptions()
        noise = {name: d(name, getattr(defaults, name), text, rule=rule) for name, text, rule in (
            ("gain_e_per_dn", "Camera gain, electrons per DN (data sheet): the spot fit's shot noise.",
             parameters.positive),
            ("read_noise_dn", "Read noise with the 8-bit quantisation, DN (data sheet).", parameters.positive),
            ("speckle_contrast", "Speckle on the screen, std / spot signal (from the scatter of fits to a still "
                                 "spot). Too low, clean spots are refused as not one clean spot (a WARN says so).",
             parameters.non_negative),
            ("false_refusal_rate", "Chance that the spot fit's chi^2 test refuses a clean spot.",
             parameters.inside(0.0, 1.0)))}
        self.capture_dir = d("capture_dir", "", "Save frames here (PNG) for laser-calib screen-calibrate; empty: off.")
        self.capture_left = d("capture_count", 10, "Frames to save in capture_dir.", rule=parameters.non_negative)
        self.capture_period = d("capture_period", 1.0, "Seconds between saved frames (move the board meanwhile).",
                                rule=parameters.non_negative)
        if path:
            self.calibration = load_calibration(path)
        else:
            self.calibration = default_camera().ideal_calibration()
            self.get_logger().info("calibration: the simulated camera's exact one (parameter calibration is empty)")
        self.options = DetectorOptions(half_y=half_y, half_z=half_z, min_peak_dn=min_peak, **noise,
                                       bayer_pattern=None if pattern.lower() == "none" else pattern.upper())
        checked = {}
        for name, value in (("bayer_pattern", self.options.bayer_pattern), ("mono_pattern", self.mono_pattern)):
            try:  # as the detector checks it (a bad mono_pattern was refused frame by frame)
                checked[name] = SpotDetector(self.calibration, dataclasses.replace(self.options, bayer_pattern=value))
            except ValueError as exc:
                raise parameters.NodeError(f"parameter {name}: {exc}", 2) from None
        self.detectors = {None: checked["bayer_pattern"]}
        parameters.dynamic(self, {"min_peak_dn": "min_peak_dn"})
        try:
            if self.capture_dir:
                Path(self.capture_dir).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise parameters.NodeError(f"parameter capture_dir: cannot make {self.capture_dir} "
                                       f"({exc.strerror or exc})", 2) from None
        self.captured, self.last_capture = 0, -np.inf
        from laser_calib_interfaces.msg import SpotPair
        self.SpotPair = SpotPair
        self.point_pubs = [self.create_publisher(PointStamped, topic, common.STREAM_QOS)
                           for topic in common.LASER_SPOT]
        self.pair_pub = self.create_publisher(SpotPair, common.SPOTS, common.STREAM_QOS)
        # a frame two subscriptions deliver is used once (on_image's recent stamps; on_info takes the first)
        common.subscribe_camera(self, Image, common.IMAGE, self.on_image, depth=5)
        common.subscribe_camera(self, CameraInfo, common.CAMERA_INFO, self.on_info, depth=5)
        self.recent = {}                 # (stamp sec, nanosec, frame_id) -> a digest of the pixels, of the frames used
        self.repeated_stamps = 0
        self.bad_frames = 0
        self.info_problem: str | None = None
        self.info_checked = False
        self.held_back = 0   # frames held back waiting for CameraInfo

    @property
    def min_peak_dn(self) -> float:
        return self.options.min_peak_dn

    @min_peak_dn.setter
    def min_peak_dn(self, value: float) -> None:
        # the executor is single-threaded: no frame is being detected while this runs
        self.options = dataclasses.replace(self.options, min_peak_dn=value)
        self.detectors = {None: SpotDetector(self.calibration, self.options)}

    def on_info(self, msg: CameraInfo) -> None:
        if self.info_checked:
            return
        self.info_checked = True
        c = self.calibration
        if (msg.width, msg.height) != (c.width, c.height):
            self.info_problem = (f"the camera's CameraInfo says {msg.width}x{msg.height}, the calibration is for "
                                 f"{c.width}x{c.height}")
            self.get_logger().error(f"frames refused: {self.info_problem}")
            return
        k = np.array(msg.k, dtype=float).reshape(3, 3)
        if k[0, 0] > 0 and not np.allclose(k, c.K, rtol=0.01, atol=1.0):
            self.get_logger().warning("the driver's CameraInfo intrinsics differ from the calibration file's "
                                      "(the file's are used): re-run screen-calibrate if the camera changed")
        # a driver's D of the calibration's model (plumb_bob: k1 k2 p1 p2 k3) that moves the image's edge
        if msg.distortion_model == "plumb_bob" and len(msg.d) == 5 and np.all(np.isfinite(msg.d)):
            apart = c.distortion_difference_px(np.array(msg.d, dtype=float))
            if apart > DISTORTION_TOLERANCE_PX:
                self.get_logger().warning(
                    f"the driver's CameraInfo distortion differs from the calibration file's by up to {apart:.1f} "
                    "px at the image's edge (the file's is used): re-run screen-calibrate if the lens changed")

    def reject(self, why: str) -> None:
        self.bad_frames += 1
        if self.bad_frames == 1 or self.bad_frames % 100 == 0:
            self.get_logger().error(f"image rejected ({self.bad_frames} so far): {why}")

    def detector(self, encoding: str) -> SpotDetector:
        """The detector for the photosites behind this encoding: a raw mosaic's own pattern, every
        pixel for 4:2:2 video (chroma shared by pixel pairs), else the bayer_pattern parameter's."""
        pattern = "none" if encoding.startswith("yuv422") else pattern_of(encoding, self.mono_pattern)
        if pattern not in self.detectors:
            options = dataclasses.replace(self.options, bayer_pattern=None if pattern == "none" else pattern)
            self.detectors[pattern] = SpotDetector(self.calibration, options)
        return self.detectors[pattern]

    def on_image(self, msg: Image) -> None:
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec, msg.header.frame_id)
        digest = zlib.crc32(bytes(msg.data[::PIXEL_SAMPLE]))
        if key in self.recent:  # the same frame through the other subscription, or a stamp used twice
            if self.recent[key] != digest:
                self.repeated_stamps += 1
                self.get_logger().warning(
                    f"frames with the stamp of an earlier frame and other pixels dropped ({self.repeated_stamps} so "
                    "far): the camera repeats stamps (a coarse clock?), and a spot is matched to the joint readings "
                    "by its stamp", throttle_duration_sec=5.0)
            return
        if key[:2] != (0, 0):  # an unstamped camera's frames cannot be told apart: all are used
            self.recent[key] = digest
            while len(self.recent) > RECENT_FRAMES:
                del self.recent[next(iter(self.recent))]
        if (not self.info_checked and self.held_back < INFO_WAIT_FRAMES
                and self.count_publishers(self.resolve_topic_name(common.CAMERA_INFO)) > 0):  # remapped: rclpy won't
            # the driver's CameraInfo, sent with each frame, may arrive second: its size is checked first
            self.held_back += 1
            if self.held_back == INFO_WAIT_FRAMES:
                self.get_logger().warning(
                    f"no CameraInfo on {self.resolve_topic_name(common.CAMERA_INFO)} in {INFO_WAIT_FRAMES} frames, "
                    "though it has a publisher (one that sent it once, before this node started?): frames are "
                    "detected without checking their size against it")
            return
        try:
            image = to_bgr8(bytes(msg.data), msg.width, msg.height, msg.step, msg.encoding, self.mono_pattern)
        except ValueError as exc:  # an encoding or layout it cannot read
            return self.reject(str(exc))
        # captured whatever the calibration: the frames are for making one, of a camera of any size
        self.capture(image, common.stamp_seconds(msg.header.stamp))
        if self.info_problem:
            return self.reject(self.info_problem)
        try:
            spots, seen, refused = self.detector(msg.encoding).detect_why(image)
        except ValueError as exc:  # a size the calibration is not for
            return self.reject(str(exc))
        if any(refused):  # a spot there, not measured: the sequencer sees only 'not seen'
            said = "; ".join(f"laser {j + 1} refused: {why}" for j, why in enumerate(refused) if why)
            self.get_logger().warning(said, throttle_duration_sec=5.0)
        pair = self.SpotPair()
        pair.header.stamp = msg.header.stamp
        pair.header.frame_id = common.SCREEN_FRAME
        pair.spots = common.spots_to_msg(spots, seen)
        for j in range(2):
            if pair.spots[j].seen:
                point = PointStamped()
                point.header = pair.header
                point.point.x, point.point.y, point.point.z = 0.0, float(spots[j][0]), float(spots[j][1])
                self.point_pubs[j].publish(point)
        self.pair_pub.publish(pair)

    def capture(self, image: np.ndarray, stamp: float) -> None:
        if not self.capture_dir or self.captured >= self.capture_left:
            return
        if stamp - self.last_capture < self.capture_period:
            return
        path = Path(self.capture_dir) / f"frame_{self.captured:04d}.png"
        cv2.imwrite(str(path), image)
        self.captured += 1
        self.last_capture = stamp
        self.get_logger().info(f"captured {path} ({self.captured}/{self.capture_left})"
                               + ("; capture done" if self.captured == self.capture_left else ""))


def main(args=None) -> int:
    return common.run(SpotDetectorNode, args)


if __name__ == "__main__":
    sys.exit(main())
