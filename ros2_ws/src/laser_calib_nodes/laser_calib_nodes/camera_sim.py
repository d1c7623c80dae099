"""camera_sim: the simulated camera watching the screen.

Subscribes  sim/true_spots (laser_calib_interfaces/TrueSpots) from the sim arm_driver.
Publishes   camera/image_raw (sensor_msgs/Image, bgr8) and camera/camera_info
            (sensor_msgs/CameraInfo, plumb_bob) at ``rate`` Hz, rendered by
            laser_calib.vision.render.render_frame from the latest true spots and
            their beams (an oblique beam's footprint is elongated, as a real one is).
            The image is stamped with the stamp of the true spots it shows (the
            capture instant), which is also the stamp of a joint state.
"""

from __future__ import annotations

import sys

import numpy as np
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image

from laser_calib.vision import render
from laser_calib.vision.camera import CameraModel, default_camera

from laser_calib_nodes import common, parameters

CAMERA_FRAME = "camera_optical"


def camera_info(camera: CameraModel, stamp, frame_id: str = CAMERA_FRAME) -> CameraInfo:
    info = CameraInfo()
    info.header.stamp = stamp
    info.header.frame_id = frame_id
    info.width, info.height = int(camera.width), int(camera.height)
    info.distortion_model = "plumb_bob"
    info.d = [float(v) for v in camera.dist]
    info.k = [float(v) for v in camera.K.ravel()]
    info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    info.p = [float(v) for v in np.hstack([camera.K, np.zeros((3, 1))]).ravel()]
    return info


class CameraSim(Node):
    def __init__(self):
        super().__init__("camera_sim")
        rate = parameters.declare(self, "rate", 10.0, "Frame rate, Hz.", rule=parameters.rate)
        # a negative seed was numpy's traceback, a 0 sigma rendered no spot
        seed = parameters.declare(self, "seed", 1, "Random seed of the image noise (speckle, shot and read noise).",
                                  rule=parameters.non_negative)
        spot_sigma = parameters.declare(self, "spot_sigma", 0.002, "Gaussian sigma of a laser spot on the screen, m.",
                                        rule=parameters.up_to(0.05, "m", "more is millimetres typed as metres"))
        self.camera = default_camera()
        self.options = render.RenderOptions(spot_sigma_m=spot_sigma)
        self.rng = np.random.default_rng(seed)
        self.latest = None
        self.last_stamp = None
        from laser_calib_interfaces.msg import TrueSpots
        self.create_subscription(TrueSpots, common.TRUE_SPOTS, self.on_spots, common.STREAM_QOS)
        self.image_pub = self.create_publisher(Image, common.IMAGE, common.IMAGE_QOS)
        # volatile, as most drivers publish it: the subscribers' latched profile for drivers that latch it
        # (common.subscribe_camera) does not match, which is no fault here (it was a WARN each session)
        self.info_pub = self.create_publisher(CameraInfo, common.CAMERA_INFO, common.IMAGE_QOS, event_callbacks=
                                              PublisherEventCallbacks(incompatible_qos=lambda _: None))
        # Warm the renderer's caches (pixel maps, ~0.5 s) before the first frame is due.
        render.render_frame(self.camera, np.zeros((2, 2)), np.zeros(2, bool), self.rng, self.options)
        self.create_timer(1.0 / rate, self.on_timer)
        self.get_logger().info(f"camera {self.camera.width}x{self.camera.height} at {rate:g} Hz")

    def on_spots(self, msg) -> None:
        self.latest = msg

    def on_timer(self) -> None:
        msg = self.latest
        if msg is None or msg.header.stamp == self.last_stamp:
            return  # no new instant of the arm to show
        self.last_stamp = msg.header.stamp
        spots = common.spots_from_msg(msg.spots)
        seen = np.array([s.seen for s in msg.spots])
        frame = render.render_frame(self.camera, np.nan_to_num(spots), seen, self.rng, self.options,
                                    beams=np.array(msg.beams, dtype=float).reshape(2, 3))
        image = Image()
        image.header.stamp = msg.header.stamp
        image.header.frame_id = CAMERA_FRAME
        image.height, image.width = frame.shape[:2]
        image.encoding = render.ENCODING
        image.step = frame.shape[1] * 3
        image.data = frame.tobytes()
        self.image_pub.publish(image)
        self.info_pub.publish(camera_info(self.camera, msg.header.stamp))


def main(args=None) -> int:
    return common.run(CameraSim, args)


if __name__ == "__main__":
    sys.exit(main())
