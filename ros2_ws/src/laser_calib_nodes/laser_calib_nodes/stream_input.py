"""The estimator's 'stream' input: joint_states and spots paired by stamp (session.sync), a pair
taken while every |joint velocity| is below the node's stream.max_joint_speed, and the still
frames of each pose averaged into one sample (session.average.StillPoses), as the sequencer
averages the frames of a pose: a moving pair, or a reading off the pose's first by more than the
tolerance, ends the pose, which the node then takes (Estimator.add). The frames of one pose share
its joint disturbance and are no independent measurements."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import JointState

from laser_calib.io.errors import InputError
from laser_calib.session.average import StillPoses
from laser_calib.session.sync import StampSynchronizer

from laser_calib_nodes import common
from laser_calib_nodes.sample_rows import Row, check_row, sample_row


class StreamInput:
    def __init__(self, node, sync_tolerance: float, pose_tolerance: float, group):
        from laser_calib_interfaces.msg import SpotPair
        self.node = node
        self.sync, self.reported_drops = StampSynchronizer(sync_tolerance), 0
        self.poses = StillPoses(pose_tolerance)
        node.create_subscription(JointState, common.JOINT_STATES, self.on_joint_state, common.KEEP_ALL_QOS,
                                 callback_group=group)
        node.create_subscription(SpotPair, common.SPOTS, self.on_spots, common.KEEP_ALL_QOS, callback_group=group)

    def on_joint_state(self, msg: JointState) -> None:
        reading = self.node.joints.read(msg)
        if reading is None:
            return
        self.take_pairs(self.sync.add_a(common.stamp_seconds(msg.header.stamp), reading))

    def on_spots(self, msg) -> None:
        self.take_pairs(self.sync.add_b(common.stamp_seconds(msg.header.stamp), common.spots_from_msg(msg.spots)))

    def take_pairs(self, pairs) -> None:
        for pair in pairs:
            self.add_pair(pair)
        if self.sync.dropped > self.reported_drops:  # none in a steady stream: each one said
            self.reported_drops = self.sync.dropped
            self.node.get_logger().warning(f"stream: {self.reported_drops} spot frames dropped so far: no joint "
                                           f"state within sync_tolerance of the stamp, or over "
                                           f"{self.sync.max_pending} waiting")

    def add_pair(self, pair) -> None:
        """A still pair is a frame of its pose; a moving one (joint reading and image then describe no one
        pose) ends it."""
        q, v = pair.a
        still = v is None or bool(np.all(np.abs(v) < self.node.max_speed))
        if still:
            try:
                check_row(self.node.robot, (self.poses.count, pair.b_stamp, q, pair.b), "joint state")
            except InputError as exc:
                self.node.get_logger().error(f"ignored: {exc}")
                return
        with self.node.lock:
            ended = self.poses.add(pair.b_stamp, q, pair.b, still)
        if ended is not None:
            self.node.add(sample_row(ended))

    def pending(self) -> Row | None:
        """The row of the pose still being measured (the arm has not moved on), None without one; under the
        node's lock."""
        sample = self.poses.pending()
        return None if sample is None else sample_row(sample)

    def reset(self) -> None:
        """Forget the pairs waiting and the pose being measured; under the node's lock."""
        self.sync.reset()
        self.reported_drops = 0
        self.poses = StillPoses(self.poses.tolerance)
