"""The sequencer's recording: every session topic, raw, into the session's segmented bag
(laser_calib.io.bag_writer.SegmentedBagWriter), and the node's own messages as it publishes them."""

from __future__ import annotations

import threading
import time
from collections import deque

from geometry_msgs.msg import PointStamped
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import WriterError
from sensor_msgs.msg import CameraInfo, Image, JointState

from laser_calib.io.bag_writer import SegmentedBagWriter

from laser_calib_nodes import common
from laser_calib_nodes.parameters import NodeError

# At most this long to write, at the stop, what the readers hold; a publisher still streaming would
# otherwise keep the drain going (the exit watchdog allows 15 s for the whole cleanup).
DRAIN_SECONDS = 5.0


class Recorder:
    def __init__(self, node: Node, bag_dir, work_dir, robot_name: str, record_images: bool, segment_seconds: float):
        from laser_calib_interfaces.msg import DhParameters, SpotPair
        self.node, self.bag_dir = node, bag_dir
        recorded = [
            (common.JOINT_STATES, JointState, "sensor_msgs/msg/JointState", common.STREAM_QOS),
            (common.SPOTS, SpotPair, "laser_calib_interfaces/msg/SpotPair", common.STREAM_QOS),
            (common.LASER_SPOT[0], PointStamped, "geometry_msgs/msg/PointStamped", common.STREAM_QOS),
            (common.LASER_SPOT[1], PointStamped, "geometry_msgs/msg/PointStamped", common.STREAM_QOS),
            (common.CAMERA_INFO, CameraInfo, "sensor_msgs/msg/CameraInfo", common.IMAGE_QOS),
            (common.DH_PARAMETERS, DhParameters, "laser_calib_interfaces/msg/DhParameters", common.LATCHED_QOS),
        ]
        if record_images:
            recorded.append((common.IMAGE, Image, "sensor_msgs/msg/Image", common.IMAGE_QOS))
        own = [(common.SAMPLES, "laser_calib_interfaces/msg/Sample", common.SAMPLES_QOS),
               (common.TEST_SAMPLES, "laser_calib_interfaces/msg/Sample", common.SAMPLES_QOS),
               (common.JOINT_TRAJECTORY, "trajectory_msgs/msg/JointTrajectory", common.COMMAND_QOS),
               (common.PROGRESS, "laser_calib_interfaces/msg/SessionProgress", common.LATCHED_QOS)]
        topics = {node.resolve_topic_name(name): (kind, [common.bag_qos(qos)]) for name, _, kind, qos in recorded}
        topics.update({node.resolve_topic_name(name): (kind, [common.bag_qos(qos)]) for name, kind, qos in own})
        self.lock = threading.Lock()
        self.failed: str | None = None  # why recording stopped (a full disk); check() ends the session on it
        self.said = False  # whether check() raised it
        self.bag: SegmentedBagWriter | None = SegmentedBagWriter(
            bag_dir, work_dir, topics, custom_data={"robot": robot_name}, max_segment_seconds=segment_seconds)
        # what opening the bag mended after a crash, said now and in the session's history (session_open)
        self.repairs = ([f"bag: adopted segment {name} closed just before a crash" for name in self.bag.recovered]
                        + [f"bag: segment {name} is listed in metadata.yaml but gone: struck from the list (rosbag2 "
                           "refuses a bag with a listed file missing)" for name in self.bag.missing]
                        + [f"bag: discarded unfinished segment {name} (the pose in progress at the crash)"
                           for name in self.bag.discarded])
        for line in self.repairs:
            node.get_logger().warning(line)
        self.recent_frames: deque = deque(maxlen=40)
        self.subscriptions: list = []  # drained at close
        for name, msg_type, _, qos in recorded:
            topic = node.resolve_topic_name(name)
            if msg_type not in (Image, CameraInfo):
                # The publisher's reliability and durability, every message kept until taken: the executor
                # stalls at each segment roll-over (40-400 ms), and a 500 Hz joint_states filled a keep-last
                # 200 queue behind one (test_bag_backlog).
                every = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=qos.reliability,
                                   durability=qos.durability)
                self.subscriptions.append(node.create_subscription(
                    msg_type, name, lambda data, t=topic: self.write(t, data), every, raw=True))
                continue
            # Frames of 4 MB: a bounded queue, 20 s of a 10 Hz camera (a roll-over stalled it 0.4 s at most);
            # subscribed as spot_detector is, each frame written once (write_frame).
            self.subscriptions += common.subscribe_camera(node, msg_type, name,
                                                          lambda data, t=topic: self.write_frame(t, data),
                                                          depth=max(qos.depth, 200), raw=True)

    def write(self, topic: str, data: bytes) -> None:
        self._do(lambda bag: bag.write(topic, common.now_ns(self.node), data))

    def _do(self, action) -> None:
        """A bag action; one the disk refuses (full, gone) stops the recording, and check() then ends the
        session: it raised in the executor's callback (a traceback, exit 1), and again in the sequencer's
        own 'failed' line (a second traceback). The segments closed before stay, and the samples.csv rows."""
        with self.lock:
            if self.bag is None:
                return
            try:
                action(self.bag)
            except (OSError, WriterError) as exc:
                self.bag = None
                self.failed = (f"recording into {self.bag_dir} failed ({exc}): the poses measured before are kept "
                               "there; make room and run again to resume")

    def check(self) -> None:
        if self.failed:
            self.said = True
            raise NodeError(self.failed, 1)

    def write_frame(self, topic: str, data: bytes) -> None:
        """A camera message, unless the other subscription delivered it already (same header stamp, the
        8 bytes after the CDR encapsulation); an unstamped camera's cannot be told apart: all written."""
        key = (topic, bytes(data[4:12]))
        if key[1] != bytes(8):
            with self.lock:
                if key in self.recent_frames:
                    return
                self.recent_frames.append(key)
        self.write(topic, data)

    def publish(self, publisher, name: str, msg, close_segment: bool = False) -> None:
        """Publish and record. close_segment: on disk (segment closed) before it is published."""
        if close_segment:
            topic, data = self.node.resolve_topic_name(name), serialize_message(msg)
            self._do(lambda bag: (bag.write(topic, common.now_ns(self.node), data), bag.rotate()))
            self.check()  # not on disk: not published
            publisher.publish(msg)
            return
        publisher.publish(msg)
        self.write(self.node.resolve_topic_name(name), serialize_message(msg))

    def rotate(self) -> None:
        self._do(lambda bag: bag.rotate())
        self.check()

    def drain(self) -> None:
        """Write what the subscriptions' readers hold and the executor has not taken.
        A reliable publisher counts a message delivered once it is in this node's reader, and goes on
        (a replay exits): at a stop, the executor, behind roll-overs on a loaded machine, had taken 606
        of a burst's 2000 joint states (CI), and the rest were lost with the node. Called once the
        executor has stopped; rclpy's own take, as its executor does it."""
        deadline = time.monotonic() + DRAIN_SECONDS
        for subscription in self.subscriptions:
            with subscription.handle:
                while time.monotonic() < deadline:
                    taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
                    if taken is None:
                        break
                    subscription.callback(taken[0])

    def close(self) -> int:
        """Drain, close the bag; 1 with an ERROR line when the recording failed and no check() said it
        (a failure at the stop, or one the session ended before checking): never a silent exit 0."""
        self.drain()
        self._do(lambda bag: bag.close())
        with self.lock:
            self.bag = None
        if self.failed and not self.said:
            self.node.get_logger().error(self.failed)
            return 1
        return 0
