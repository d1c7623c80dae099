"""sequencer: runs a measurement session (the node users start with `ros2 run`).

For each step of the pose list (``poses_file`` or generated, then ``test_poses``
held-out poses) it commands the arm on joint_trajectory (one point, every joint
named, time_from_start from ``move.joint_speed``: what a ros2_control
joint_trajectory_controller accepts; remap joint_trajectory to the controller's
~/joint_trajectory), waits until joint_states show the arm settled
(laser_calib.session.settle), pairs the next ``frames`` spot frames with joint
states of the same instant and averages them (laser_calib.session.average), and
publishes one Sample: on samples for a fit pose, on test_samples for a test pose.
Everything goes to ``output_dir`` as it happens (laser_calib.session.folder): the
samples CSV files and a crash-safe bag (recorder.py). One session per folder
(laser_calib.session.lock); started again on a partial folder it repairs what a
crash left and measures the missing steps (``resume``). At the end: the
estimator's Estimate service (or the estimate in-process, ``estimate.mode``
'local'), then the held-out and truth comparison (laser_calib.report.truth).
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from laser_calib.hardware.trajectory import move_time
from laser_calib.io import bag
from laser_calib.io.joint_names import RobotJoints, default_joint_names
from laser_calib.session.average import FrameCollector
from laser_calib.session.folder import Progress
from laser_calib.session.settle import SettleDetector, SettleRule

from laser_calib_nodes import common, parameters, sequencer_parts, session_open, sole_owner
from laser_calib_nodes.arm_status import ArmFaults
from laser_calib_nodes.joint_states import ArmJointStates
from laser_calib_nodes.recorder import Recorder


class Sequencer(Node):
    def __init__(self):
        super().__init__("sequencer")
        d = lambda *a, **k: parameters.declare(self, *a, **k)  # noqa: E731
        names = d("joint_names", Parameter.Type.STRING_ARRAY, "The robot's joints, base to tip, as the arm's "
                  "joint_states and controller name them (default: joint_states' names when it has exactly the "
                  "robot's joints).", type_=Parameter.Type.STRING_ARRAY)
        self.joint_speed = d("move.joint_speed", 0.5, "Commanded: time_from_start = largest joint move / this, rad/s.",
                             rule=parameters.JOINT_SPEED)
        try:
            self.settle_rule = SettleRule(d("settle.position_tolerance", 0.003, "Settled: every |reading - goal| "
                                            "below this, rad."),
                                          d("settle.velocity_tolerance", 0.002, "Settled: every |joint velocity| "
                                            "below this, rad/s."),
                                          d("settle.hold_time", 0.2, "Settled: both tolerances held this long, s."))
        except ValueError as exc:
            raise parameters.NodeError(f"parameter {exc}", 2) from None
        # each checked at the start, not when the first pose is reached
        self.settle_timeout = d("settle.timeout", 30.0, "Give up on a pose not settled after this long, s.",
                                rule=parameters.positive)
        self.frames = d("frames", session_open.FRAMES, "Spot frames averaged per pose.", rule=parameters.at_least(1))
        self.frame_timeout = d("frame_timeout", 10.0, "Give up when the frames of a pose take longer, s.",
                               rule=parameters.positive)
        self.sync_tol = d("sync_tolerance", 0.02, "Max stamp difference pairing a frame with a joint state, s "
                                                   "(at least half the joint_states period).",
                          rule=parameters.SYNC_TOLERANCE)
        self.wait_timeout = d("wait_timeout", 60.0, "Wait this long for the arm's joint states and the spots, s.",
                              rule=parameters.positive)
        self.unseen_limit = d("unseen_limit", 5, "End the session (exit 2, what was measured kept) when this run's "
                              "first N poses saw no spot at all: lasers off, camera covered, screen out of view, or "
                              "a min_peak_dn no spot reaches. 0: never.", rule=parameters.non_negative)
        self.unseen_poses: int | None = 0  # this run's poses so far without a spot; None once one was seen
        self.end = sequencer_parts.declare(self)
        record_images = d("record_images", False, "Also record camera images (large) in the bag.")
        segment_seconds = d("bag.max_segment_seconds", 10.0, "Close a bag segment after this long even "
                                                             "within a pose, s.", rule=parameters.positive)
        self.owner_watch = sole_owner.declare(self)
        self.exit_code, self.done, self.created = 0, False, time.monotonic()

        self.session, self.lock, self.robot, self.poses, state = session_open.open_session(self)
        # a URDF arm's joints are named: found by name among joint_states' (which may hold more)
        self.joint_names = (list(names) if names else
                            default_joint_names(self.robot) if self.robot.chain else None)

        # ---- topics and recording ----
        from laser_calib_interfaces.msg import Sample, SessionProgress, SpotPair
        self.Sample, self.SessionProgress = Sample, SessionProgress
        self.traj_pub = self.create_publisher(JointTrajectory, common.JOINT_TRAJECTORY, common.COMMAND_QOS)
        self.sample_pub = self.create_publisher(Sample, common.SAMPLES, common.SAMPLES_QOS)
        self.test_pub = self.create_publisher(Sample, common.TEST_SAMPLES, common.SAMPLES_QOS)
        self.progress_pub = self.create_publisher(SessionProgress, common.PROGRESS, common.LATCHED_QOS)
        self.create_subscription(JointState, common.JOINT_STATES, self.on_joint_state, common.STREAM_QOS)
        self.create_subscription(SpotPair, common.SPOTS, self.on_spots, common.STREAM_QOS)
        self.estimate_client = sequencer_parts.client(self)
        self.arm_faults = ArmFaults(self)
        self.recorder = Recorder(self, self.session.bag_dir, self.session.work_dir, self.robot.name, record_images,
                                 segment_seconds)
        joints = RobotJoints(self.robot, self.joint_names or (), "parameter joint_names")  # as estimate --bag
        found = self.session.reconcile(self.robot, self.poses, joints)  # after the recorder adopted closed segments
        self.done_steps, self.resumed = found.done, found
        session_open.say_resume(self, found, state)

        # ---- state shared with the worker thread ----
        self.cond = threading.Condition()
        self.arm_joints = ArmJointStates(self.joint_names, self.robot.n_joints, self.get_logger())
        self.last_state = None                 # (stamp, q (N,), velocity (N,) or None, monotonic time received)
        self.state_count = self.spot_count = 0
        self.settle: SettleDetector | None = None
        self.collector: FrameCollector | None = None
        self.stopping = threading.Event()
        self.worker = threading.Thread(target=self.work, name="sequence", daemon=True)
        self.worker.start()

    # ---- callbacks (executor thread) ----
    def on_joint_state(self, msg: JointState) -> None:
        with self.cond:
            read = self.arm_joints.read(msg)  # None: not the robot's joints (another publisher's), said once
            if read is None:
                return
            (q, v), self.joint_names = read, self.arm_joints.names
            stamp = common.stamp_seconds(msg.header.stamp)
            self.last_state = (stamp, q, v, time.monotonic())
            self.state_count += 1
            if self.collector is not None:
                disturbed = len(self.collector.disturbed)
                self.collector.add_state(stamp, (q, v))
                if len(self.collector.disturbed) > disturbed:
                    sequencer_parts.warn_disturbed(self, self.collector)
            elif self.settle is not None and self.settle.update(stamp, q, v):
                self.collector = FrameCollector(self.frames, self.sync_tol, self.settle, stamp, (q, v))
                self.settle = None
            self.cond.notify_all()

    def on_spots(self, msg) -> None:
        with self.cond:
            self.spot_count += 1
            if self.collector is not None:
                self.collector.add_frame(common.stamp_seconds(msg.header.stamp), common.spots_from_msg(msg.spots))
            self.cond.notify_all()

    # ---- the sequence (worker thread) ----
    def wait(self, predicate, timeout: float, what) -> None:
        deadline = time.monotonic() + timeout
        with self.cond:
            while not predicate():
                if self.stopping.is_set():
                    raise sequencer_parts.Stop()
                sequencer_parts.check(self)  # a full disk, a faulted arm: the session ends, what was measured kept
                if time.monotonic() > deadline:
                    raise parameters.NodeError(what() if callable(what) else what, 3)
                self.cond.wait(0.1)

    def work(self) -> None:
        sequencer_parts.guard(self, self.run_sequence)

    def run_sequence(self) -> None:
        todo = np.flatnonzero(~self.done_steps)
        self.progress = Progress(len(self.poses), int(self.done_steps.sum()))
        joints, spots = (self.resolve_topic_name(t) for t in (common.JOINT_STATES, common.SPOTS))
        self.get_logger().info(f"waiting up to {self.wait_timeout:g} s for the arm on {joints} and spots on {spots}")
        self.wait(lambda: self.state_count > 0, self.wait_timeout,
                  lambda: self.arm_joints.none_read(joints, self.wait_timeout))  # raises: exit 2 or 3
        self.wait(lambda: self.spot_count > 0, self.wait_timeout, f"no spot frames on {spots} after "
                  f"{self.wait_timeout:g} s (are the camera and spot_detector running?)")
        self.wait(lambda: self.traj_pub.get_subscription_count() > 0, self.wait_timeout,
                  f"nobody subscribes to {self.resolve_topic_name(common.JOINT_TRAJECTORY)}")
        sole_owner.watch(self, self.created + self.owner_watch)
        found = self.resumed
        for r in range(len(found.to_bag)):   # restored from the CSV: back into the bag (the journal)
            test = bool(self.poses.test[self.poses.pose == found.to_bag.pose[r]][0])
            self.recorder.publish(self.test_pub if test else self.sample_pub, common.TEST_SAMPLES if test else
                                  common.SAMPLES, sequencer_parts.sample_msg(self, found.to_bag, r), close_segment=True)
        for r in range(len(found.fit)):       # for an estimator that missed them (it ignores those it has)
            self.sample_pub.publish(sequencer_parts.sample_msg(self, found.fit, r))
        self.get_logger().info(f"measuring {len(todo)} of {len(self.poses)} poses into {self.session.path}")
        for step in todo:
            self.measure_step(int(step))
        sequencer_parts.finish(self)

    def measure_step(self, step: int) -> None:
        pose_id, goal, test = int(self.poses.pose[step]), self.poses.q[step], bool(self.poses.test[step])
        started = time.monotonic()
        self.publish_progress("moving", pose_id)
        with self.cond:
            current = self.last_state[1]
            traj = JointTrajectory(joint_names=self.joint_names)   # header stamp 0: start now
            point = JointTrajectoryPoint(positions=[float(v) for v in goal])
            point.time_from_start = sequencer_parts.duration(move_time(current, goal, self.joint_speed))
            traj.points = [point]
            self.settle = SettleDetector(goal, self.settle_rule, common.now_ns(self) * 1e-9)
            self.collector = None
        self.recorder.publish(self.traj_pub, common.JOINT_TRAJECTORY, traj)
        where = self.where = f"pose {self.progress.done + 1}/{len(self.poses)} (id {pose_id})"  # as its progress line
        try:
            self.wait(lambda: self.collector is not None, self.settle_timeout,
                      lambda: f"{where}: arm not settled after {self.settle_timeout:g} s "
                              f"({self.settle.worst_joint(self.joint_names)}){sequencer_parts.stale(self)}")
            self.publish_progress("measuring", pose_id)
            self.wait(lambda: self.collector.complete, self.frame_timeout,
                      lambda: f"{where}: fewer than {self.frames} spot frames paired with joint states within "
                              f"{self.frame_timeout:g} s (sync_tolerance {self.sync_tol:g} s): "
                              f"{self.collector.shortfall(self.joint_names)}{sequencer_parts.stale(self)}")
            with self.cond:
                sample, collector, self.collector = self.collector.sample(pose_id), self.collector, None
        finally:
            with self.cond:
                self.settle = self.collector = None
        msg = sequencer_parts.sample_msg(self, sample, 0)
        # The CSV row is built from the message, so bag and CSV hold identical values; on disk (segment
        # closed) first, then published, then the row: folder.reconcile repairs a crash between the steps.
        row = bag.samples_from_rows([bag.sample_row_from_msg(msg, 'sample')], 'sample')
        self.recorder.publish(self.test_pub if test else self.sample_pub, common.TEST_SAMPLES if test else common.SAMPLES,
                              msg, close_segment=True)
        self.session.append_sample(row, test)
        self.progress.step()
        sequencer_parts.measured(self, f"pose {self.progress.done}/{len(self.poses)} (id {pose_id}"
                                 f"{', test' if test else ''}) measured in {time.monotonic() - started:.1f} s, "
                                 f"{collector.frames} frames", row.spots[0])

    def publish_progress(self, state: str, pose_id: int) -> None:
        msg = self.SessionProgress(state=state, pose=pose_id, total=len(self.poses))
        msg.header.stamp = self.get_clock().now().to_msg()
        progress = getattr(self, "progress", None)
        msg.done = progress.done if progress else int(self.done_steps.sum())
        msg.seconds_left = progress.seconds_left() if progress else float("nan")
        self.recorder.publish(self.progress_pub, common.PROGRESS, msg)

    def close(self) -> int:
        self.stopping.set()
        worker = getattr(self, "worker", None)
        if worker is not None and worker.is_alive() and worker is not threading.current_thread():
            worker.join(timeout=5.0)
        failed = self.recorder.close() if getattr(self, "recorder", None) is not None else 0
        if getattr(self, "lock", None) is not None:
            self.lock.release()
        return failed


def main(args=None) -> int:
    return common.run(Sequencer, args, until=lambda node: node.done)


if __name__ == "__main__":
    sys.exit(main())
