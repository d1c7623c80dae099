"""spot_detector: camera frames in, the two laser spots on the screen out.

Subscribes  camera/image_raw (sensor_msgs/Image, bgr8), detected with
            laser_calib.vision.detect.SpotDetector and the screen calibration
            (``calibration`` file; empty: the simulated camera's exact one).
Publishes   laser1/spot, laser2/spot (geometry_msgs/PointStamped, frame
            `screen`: x = 0, y, z in metres), only when that laser is seen.
            spots (laser_calib_interfaces/SpotPair): both lasers of every
            frame, with seen = false (and NaN) for a missing spot. A missing
            spot is therefore "not published" on laserN/spot, and explicit on
            spots, which is what the sequencer and the estimator use: they can
            tell a frame without a spot from a frame not yet arrived.
All outputs carry the image's stamp.
"""

from __future__ import annotations

import sys

import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from sensor_msgs.msg import Image

from laser_calib.vision.camera import default_camera, load_calibration
from laser_calib.vision.detect import DetectorOptions, SpotDetector

from laser_calib_nodes import common


class SpotDetectorNode(Node):
    def __init__(self):
        super().__init__("spot_detector")
        path = common.declare(self, "calibration", "", "Screen calibration file (laser_calib.vision, YAML); "
                                                       "empty: the exact calibration of the simulated camera.")
        half_y = common.declare(self, "screen.half_y", 1.0, "Measuring area half width, m (robot file 'screen').")
        half_z = common.declare(self, "screen.half_z", 1.0, "Measuring area half height, m (robot file 'screen').")
        min_peak = common.declare(self, "min_peak_dn", DetectorOptions().min_peak_dn,
                                  "Least smoothed colour contrast of a spot, DN.")
        if path:
            calibration = load_calibration(path)
        else:
            calibration = default_camera().ideal_calibration()
            self.get_logger().info("calibration: the simulated camera's exact one (parameter calibration is empty)")
        self.detector = SpotDetector(calibration, DetectorOptions(half_y=half_y, half_z=half_z,
                                                                  min_peak_dn=min_peak))
        from laser_calib_interfaces.msg import SpotPair
        self.SpotPair = SpotPair
        self.point_pubs = [self.create_publisher(PointStamped, topic, common.STREAM_QOS)
                           for topic in common.LASER_SPOT]
        self.pair_pub = self.create_publisher(SpotPair, common.SPOTS, common.STREAM_QOS)
        self.create_subscription(Image, common.IMAGE, self.on_image, common.IMAGE_QOS)
        self.bad_frames = 0

    def on_image(self, msg: Image) -> None:
        if msg.encoding != "bgr8" or msg.step != msg.width * 3 or len(msg.data) != msg.height * msg.step:
            self.bad_frames += 1
            if self.bad_frames == 1 or self.bad_frames % 100 == 0:
                self.get_logger().error(f"image rejected ({self.bad_frames} so far): expected bgr8 "
                                        f"{msg.width}x{msg.height}, got {msg.encoding}, step {msg.step}, "
                                        f"{len(msg.data)} bytes")
            return
        image = np.frombuffer(msg.data, dtype=np.uint8).reshape(msg.height, msg.width, 3)
        try:
            spots, seen = self.detector.detect(image)
        except ValueError as exc:  # wrong size for the calibration
            self.bad_frames += 1
            if self.bad_frames == 1 or self.bad_frames % 100 == 0:
                self.get_logger().error(f"image rejected ({self.bad_frames} so far): {exc}")
            return
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


def main(args=None) -> int:
    return common.run(SpotDetectorNode, args)


if __name__ == "__main__":
    sys.exit(main())
