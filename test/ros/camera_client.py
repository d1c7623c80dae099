"""A camera driver as most publish (sensor-data QoS: best effort) for spot_detector, run as a
subprocess in the workspace environment. Prints one JSON document.

    camera_client.py ENCODING [INFO_WIDTH [SECONDS [QOS [FRAMES [INFO]]]]]   rendered frames
        of known spots in ENCODING with CameraInfo (its width INFO_WIDTH, 0: the camera's), published
        with QoS 'sensor_data' (best effort, default) or 'reliable' until 3 spot pairs came back or
        SECONDS (60) passed; with FRAMES (0: as without), exactly FRAMES frames, one per PERIOD s.
        INFO: each frame's CameraInfo first ('first', default), or its image first ('image_first');
        or one CameraInfo only, before any subscriber matched, volatile ('once': lost) or latched
        ('once_latched': transient local); 'zero_distortion': first, its D zeros (the camera's k1 is
        -0.12); 'repeat_stamp': first, every second frame other pixels with the stamp of the one before.
        Prints the spots spot_detector published back, their stamps and the frames published.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image

from laser_calib.vision import RenderOptions, default_camera, render_frame
from laser_calib_interfaces.msg import SpotPair

TRUE = np.array([[-0.3, 0.25], [0.4, -0.15]])
UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"  # rmw's name of a node whose discovery data has not come yet
PERIOD = 0.3  # s between frames; the detector needs ~2 ms a frame


def encode(bgr: np.ndarray, encoding: str) -> tuple[bytes, int]:
    """(data, step) of a rendered bgr8 frame in a driver's encoding."""
    h, w = bgr.shape[:2]
    if encoding == "rgb8":
        return bgr[:, :, ::-1].tobytes(), 3 * w
    if encoding == "bayer_rggb8":
        raw = bgr[:, :, 1].copy()
        raw[0::2, 0::2] = bgr[0::2, 0::2, 2]
        raw[1::2, 1::2] = bgr[1::2, 1::2, 0]
        return raw.tobytes(), w
    return bgr.tobytes(), 3 * w


def main() -> None:
    encoding = sys.argv[1]
    camera = default_camera()
    info_width = int(sys.argv[2]) if len(sys.argv) > 2 and int(sys.argv[2]) else camera.width
    qos = 10 if len(sys.argv) > 4 and sys.argv[4] == "reliable" else qos_profile_sensor_data
    frames = int(sys.argv[5]) if len(sys.argv) > 5 else 0
    info_mode = sys.argv[6] if len(sys.argv) > 6 else "first"
    rclpy.init()
    node = rclpy.create_node("test_camera")
    got = []
    spot_sub = node.create_subscription(SpotPair, "spots", got.append, 10)
    image_pub = node.create_publisher(Image, "camera/image_raw", qos)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    info_pub = node.create_publisher(CameraInfo, "camera/camera_info", latched if info_mode == "once_latched" else qos)

    def info(stamp) -> CameraInfo:
        msg = CameraInfo(width=info_width, height=camera.height, distortion_model="plumb_bob",
                         k=[float(v) for v in camera.K.ravel()], d=[0.0] * 5 * (info_mode == "zero_distortion"))
        msg.header.stamp = stamp
        return msg

    if info_mode.startswith("once"):
        info_pub.publish(info(node.get_clock().now().to_msg()))
        print("camera info sent", flush=True)
    rng = np.random.default_rng(5)
    data, step = encode(render_frame(camera, TRUE, np.ones(2, bool), rng, RenderOptions()), encoding)
    other, _ = encode(render_frame(camera, TRUE, np.ones(2, bool), rng, RenderOptions()), encoding)
    deadline = time.monotonic() + (float(sys.argv[3]) if len(sys.argv) > 3 else 60.0)
    while image_pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    # the rest of the round trip is matched too: a frame whose CameraInfo found no subscription yet is
    # held back by the detector, and a SpotPair sent before its reader matched is lost
    waiting = []
    if not info_mode.startswith("once"):
        waiting.append(info_pub.get_subscription_count)
    readers = node.get_subscriptions_info_by_topic(image_pub.topic_name)
    while any(reader.node_name == UNKNOWN_NODE for reader in readers) and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)  # a reader's node is named a little after it matched
        readers = node.get_subscriptions_info_by_topic(image_pub.topic_name)
    if any(reader.node_name == "spot_detector" for reader in readers):
        waiting.append(spot_sub.get_publisher_count)
    while not all(count() for count in waiting) and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    published = 0
    stamp = None
    while (published < frames if frames else len(got) < 3) and time.monotonic() < deadline:
        repeat = info_mode == "repeat_stamp" and published % 2 == 1
        stamp = stamp if repeat else node.get_clock().now().to_msg()
        image = Image(height=camera.height, width=camera.width, encoding=encoding, step=step,
                      data=other if repeat else data)
        image.header.stamp = stamp
        first = [(info_pub, info(stamp)), (image_pub, image)]
        sent = {"first": first, "zero_distortion": first, "repeat_stamp": first,
                "image_first": [(image_pub, image), (info_pub, info(stamp))]}.get(info_mode, [(image_pub, image)])
        for publisher, msg in sent:
            publisher.publish(msg)
        published += 1
        end = time.monotonic() + PERIOD
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
    end = time.monotonic() + 2.0  # the last frames' spots
    while frames and len(got) < published and time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    spots = [[[s.y, s.z, s.seen] for s in pair.spots] for pair in got]
    stamps = [(pair.header.stamp.sec, pair.header.stamp.nanosec) for pair in got]
    print(json.dumps({"frames": len(got), "published": published, "spots": spots, "true": TRUE.tolist(),
                      "stamps": stamps}))


if __name__ == "__main__":
    main()
