"""sequencer: runs a measurement session (the node users start with `ros2 run`).

For each pose of the list (loaded from ``poses_file`` or generated) it commands
the arm (joint_trajectory, one point), waits until the arm has settled (joint
velocity and position error measured on joint_states, held for
``settle.hold_time``), pairs the next ``frames`` spot frames (spots) with the
joint states of the same instant (sync.StampSynchronizer), averages them and
publishes one laser_calib_interfaces/Sample on samples. Everything is written
to the session directory ``output_dir`` as it happens (session.SessionDir):
samples.csv one row per pose, and a rosbag2 MCAP bag of all session topics in
closed segments (io.bag_writer.SegmentedBagWriter), so a crash loses at most the pose in
progress. Started again on a partial session directory it resumes after the
last completed pose (``resume``). At the end it calls the estimator's Estimate
service (or runs laser_calib.session.estimate.run_calibration itself, ``estimate.mode``
'local') and writes the command line's report, result and calibrated robot.

Progress: one log line per pose (pose k of n, time left) and
laser_calib_interfaces/SessionProgress on session/progress (transient local).
"""

from __future__ import annotations

import math
import sys
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import CameraInfo, Image, JointState
from geometry_msgs.msg import PointStamped
from rclpy.serialization import serialize_message
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from laser_calib.io.errors import InputError
from laser_calib.model.robot_file import load_robot
from laser_calib.io.samples import Samples

from laser_calib.io import bag
from laser_calib.io.bag_writer import SegmentedBagWriter

from laser_calib_nodes import common
from laser_calib.session.folder import POSES_FILE, Progress, SessionDir, generate_poses, load_poses
from laser_calib.session.sync import StampSynchronizer


class Stop(Exception):
    """The node is shutting down: leave the sequence."""


class Sequencer(Node):
    def __init__(self):
        super().__init__("sequencer")
        d = lambda *a, **k: common.declare(self, *a, **k)  # noqa: E731
        robot_path = d("robot", "", "Nominal robot model file (YAML, conventions.md).")
        self.output_dir = d("output_dir", "", "Session directory: samples.csv, bag/, report (created; resumed "
                                              "when it holds a partial session).")
        poses_file = d("poses_file", "", "Pose list (YAML or CSV, rad); empty: generate 'poses' poses.")
        n_poses = d("poses", 60, "Number of poses to generate when poses_file is empty.")
        span = d("span", "whole", "Generated poses: 'whole' (joint ranges) or 'small' (+-10 deg around zero).")
        seed = d("seed", 0, "Seed of the pose generator.")
        repeats = d("repeats", 0, "Generated poses measured a second time at the end (same pose id).")
        margin = d("margin", 0.02, "Generated poses keep both spots this far inside the screen edge, m.")
        self.resume = d("resume", "auto", "'auto': resume a partial session in output_dir, else start one; "
                                          "'yes': resume (error if none); 'no': never (error if output_dir "
                                          "holds a session).")
        self.vel_tol = d("settle.velocity_tolerance", 0.002, "Settled: every |joint velocity| below this, rad/s.")
        self.pos_tol = d("settle.position_tolerance", 0.003, "Settled: every |reading - goal| below this, rad.")
        self.hold = d("settle.hold_time", 0.2, "Settled: both tolerances held this long, s.")
        self.settle_timeout = d("settle.timeout", 30.0, "Give up on a pose not settled after this long, s.")
        self.frames = d("frames", 3, "Spot frames averaged per pose.")
        self.frame_timeout = d("frame_timeout", 10.0, "Give up when the frames of a pose take longer, s.")
        self.sync_tol = d("sync_tolerance", 0.02, "Max stamp difference pairing a frame with a joint state, s "
                                                   "(at least half the joint_states period).")
        self.wait_timeout = d("wait_timeout", 60.0, "Wait this long for the arm's joint states and the spots, s.")
        self.method = d("estimate.method", "lm", "Final estimate: 'lm' or 'ekf'.")
        self.spot_sigma = d("estimate.spot_sigma", 0.0, "Final estimate: spot sigma, m (0: estimate it).")
        self.prior = d("estimate.prior", False, "Final estimate: tolerance prior.")
        self.robust = d("estimate.robust", False, "Final estimate: reject outlying spots.")
        self.diagnose = d("estimate.diagnose", False, "Final estimate: residual diagnosis.")
        self.estimate_mode = d("estimate.mode", "service", "Final estimate: 'service' (the estimator's Estimate "
                                                           "service), 'local' (in this process) or 'none'.")
        self.shared_fs = d("estimate.shared_filesystem", True, "The estimator sees output_dir: it writes the "
                                                              "report there itself (plots included).")
        self.service_timeout = d("estimate.timeout", 600.0, "Final estimate: wait this long for the service, s.")
        record_images = d("record_images", False, "Also record camera images (large) in the bag.")
        segment_seconds = d("bag.max_segment_seconds", 10.0, "Close a bag segment after this long even "
                                                             "within a pose, s.")
        self.exit_code = 0
        self.done = False

        if not self.output_dir:
            raise common.NodeError("parameter output_dir is empty: give the session directory", 2)
        if self.resume not in ("auto", "yes", "no"):
            raise common.NodeError(f"parameter resume: expected 'auto', 'yes' or 'no', got {self.resume!r}", 2)
        if self.frames < 1:
            raise common.NodeError(f"parameter frames: must be at least 1, got {self.frames}", 2)
        if self.estimate_mode not in ("service", "local", "none"):
            raise common.NodeError(f"parameter estimate.mode: expected 'service', 'local' or 'none', "
                                   f"got {self.estimate_mode!r}", 2)

        # ---- the session directory: new or resumed ----
        self.session = SessionDir(Path(self.output_dir).resolve())
        state = self.session.state()
        if state == "finished":
            raise common.NodeError(f"{self.session.path} holds a finished session; choose another output_dir", 2)
        if state == "partial" and self.resume == "no":
            raise common.NodeError(f"{self.session.path} holds a partial session and resume is 'no'", 2)
        if state == "new" and self.resume == "yes":
            raise common.NodeError(f"{self.session.path}: no session to resume", 2)
        if state == "partial":
            self.robot, self.poses = self.session.load_for_resume()
            done = self.session.completed(self.robot, self.poses)
            self.done_count = 0 if done is None else len(done)
            self.get_logger().info(f"resuming {self.session.path}: {self.done_count} of {len(self.poses)} poses "
                                   f"already measured (pose list from {POSES_FILE})")
        else:
            if not robot_path:
                raise common.NodeError("parameter robot is empty: give the robot model file (YAML)", 2)
            self.robot = load_robot(robot_path)
            if poses_file:
                self.poses = load_poses(poses_file, self.robot)
            else:
                self.poses = generate_poses(self.robot, n_poses, span, seed, repeats, margin)
            source = poses_file or f"generated: {n_poses} poses, span {span}, seed {seed}, repeats {repeats}"
            self.session.start(self.robot, self.poses, {"robot": str(robot_path), "poses": source})
            self.done_count = 0

        # ---- topics ----
        from laser_calib_interfaces.msg import Sample, SessionProgress, SpotPair, DhParameters
        from laser_calib_interfaces.srv import Estimate
        self.Sample, self.SessionProgress, self.EstimateSrv = Sample, SessionProgress, Estimate
        self.traj_pub = self.create_publisher(JointTrajectory, common.JOINT_TRAJECTORY, common.COMMAND_QOS)
        self.sample_pub = self.create_publisher(Sample, common.SAMPLES, common.SAMPLES_QOS)
        self.progress_pub = self.create_publisher(SessionProgress, common.PROGRESS, common.LATCHED_QOS)
        self.create_subscription(JointState, common.JOINT_STATES, self.on_joint_state, common.STREAM_QOS)
        self.create_subscription(SpotPair, common.SPOTS, self.on_spots, common.STREAM_QOS)
        self.estimate_client = self.create_client(Estimate, common.ESTIMATE_SERVICE)

        # ---- recording: every session topic, raw, into the segmented bag ----
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
        # This node's own topics are written to the bag as they are published (no loss at exit).
        own = [(common.SAMPLES, "laser_calib_interfaces/msg/Sample", common.SAMPLES_QOS),
               (common.JOINT_TRAJECTORY, "trajectory_msgs/msg/JointTrajectory", common.COMMAND_QOS),
               (common.PROGRESS, "laser_calib_interfaces/msg/SessionProgress", common.LATCHED_QOS)]
        self.samples_topic = self.resolve_topic_name(common.SAMPLES)
        topics = {self.resolve_topic_name(name): (kind, [common.bag_qos(qos)]) for name, _, kind, qos in recorded}
        topics.update({self.resolve_topic_name(name): (kind, [common.bag_qos(qos)]) for name, kind, qos in own})
        self.bag_lock = threading.Lock()
        self.bag = SegmentedBagWriter(self.session.bag_dir, self.session.work_dir, topics,
                                          custom_data={"robot": self.robot.name},
                                          max_segment_seconds=segment_seconds)
        for name in self.bag.recovered:
            self.get_logger().warning(f"bag: adopted segment {name} closed just before a crash")
        for name in self.bag.discarded:
            self.get_logger().warning(f"bag: discarded unfinished segment {name} (the pose in progress at the crash)")
        for name, msg_type, _, qos in recorded:
            topic = self.resolve_topic_name(name)
            # The publisher's reliability and durability, but a deep queue: the recorder must not drop
            # (a latched topic's depth 1 would lose messages published in a burst).
            deep = QoSProfile(depth=max(qos.depth, 200), reliability=qos.reliability, durability=qos.durability)
            self.create_subscription(msg_type, name, lambda data, t=topic: self.record(t, data), deep, raw=True)

        # ---- state shared with the worker thread ----
        self.cond = threading.Condition()
        self.joint_names: list[str] | None = None
        self.last_state = None         # (stamp, q, velocity)
        self.state_count = 0
        self.spot_count = 0
        self.collecting = False
        self.sync = StampSynchronizer(self.sync_tol)
        self.pairs = []
        self.stopping = threading.Event()
        self.worker = threading.Thread(target=self.work, name="sequence", daemon=True)
        self.worker.start()

    # ---- callbacks (executor thread) ----
    def record(self, topic: str, data: bytes) -> None:
        with self.bag_lock:
            if self.bag is not None:
                self.bag.write(topic, common.now_ns(self), data)

    def on_joint_state(self, msg: JointState) -> None:
        stamp = common.stamp_seconds(msg.header.stamp)
        with self.cond:
            if self.joint_names is None:
                self.joint_names = list(msg.name)
            q = np.array(msg.position, dtype=float)
            v = np.array(msg.velocity, dtype=float) if len(msg.velocity) == len(msg.position) else None
            self.last_state = (stamp, q, v)
            self.state_count += 1
            if self.collecting:
                self.pairs.extend(self.sync.add_a(stamp, (q, v)))
            self.cond.notify_all()

    def on_spots(self, msg) -> None:
        stamp = common.stamp_seconds(msg.header.stamp)
        with self.cond:
            self.spot_count += 1
            if self.collecting and stamp >= self.collect_after:
                self.pairs.extend(self.sync.add_b(stamp, common.spots_from_msg(msg.spots)))
            self.cond.notify_all()

    # ---- the sequence (worker thread) ----
    def wait(self, predicate, timeout: float, what: str):
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                if self.stopping.is_set():
                    raise Stop()
                value = predicate()
                if value:
                    return value
                left = deadline - time.monotonic()
                if left <= 0:
                    raise common.NodeError(what, 3)
                self.cond.wait(min(left, 0.1))

    def work(self) -> None:
        try:
            self.run_sequence()
            self.finish()
        except Stop:
            pass
        except (InputError, common.NodeError) as exc:
            code = exc.code if isinstance(exc, common.NodeError) else 2
            self.get_logger().error(str(exc))
            self.publish_progress("failed", -1)
            self.exit_code = code
        except Exception as exc:  # a bug: say it in one line, keep the data, exit non-zero
            if self.stopping.is_set() or not rclpy.ok():
                return  # shutting down (Ctrl-C): a publish after the context went away
            self.get_logger().error(f"sequencer failed: {type(exc).__name__}: {exc}")
            self.publish_progress("failed", -1)
            self.exit_code = 1
        finally:
            self.done = True

    def run_sequence(self) -> None:
        n = len(self.poses)
        self.progress = Progress(n, self.done_count)
        if self.done_count >= n:
            self.get_logger().info("every pose is measured already")
            return
        self.get_logger().info(f"waiting for joint states on {self.resolve_topic_name(common.JOINT_STATES)} "
                               f"and spots on {self.resolve_topic_name(common.SPOTS)}")
        self.wait(lambda: self.state_count > 0, self.wait_timeout,
                  f"no joint states on {self.resolve_topic_name(common.JOINT_STATES)} after {self.wait_timeout:g} s "
                  "(is arm_driver running?)")
        self.wait(lambda: self.spot_count > 0, self.wait_timeout,
                  f"no spot frames on {self.resolve_topic_name(common.SPOTS)} after {self.wait_timeout:g} s "
                  "(are the camera and spot_detector running?)")
        self.wait(lambda: self.traj_pub.get_subscription_count() > 0, self.wait_timeout,
                  f"nobody subscribes to {self.resolve_topic_name(common.JOINT_TRAJECTORY)}")
        if len(self.joint_names) != self.robot.n_joints:
            raise common.NodeError(f"joint_states has {len(self.joint_names)} joints, robot '{self.robot.name}' "
                                   f"has {self.robot.n_joints}", 2)
        if self.done_count:
            # The samples measured before the resume, for an estimator that missed them (transient local).
            done = self.session.samples(None)
            for r in range(self.done_count):
                self.sample_pub.publish(self.sample_msg(done, r))
        self.get_logger().info(f"measuring {n - self.done_count} of {n} poses into {self.session.path}")
        for step in range(self.done_count, n):
            self.measure_step(step)

    def measure_step(self, step: int) -> None:
        n = len(self.poses)
        pose_id = int(self.poses.pose[step])
        goal = self.poses.q[step]
        started = time.monotonic()
        self.publish_progress("moving", pose_id)
        traj = JointTrajectory()
        traj.header.stamp = self.get_clock().now().to_msg()
        traj.joint_names = self.joint_names
        point = JointTrajectoryPoint()
        point.positions = [float(v) for v in goal]
        traj.points = [point]
        self.publish_recorded(self.traj_pub, common.JOINT_TRAJECTORY, traj)
        command_time = common.stamp_seconds(traj.header.stamp)

        # settled: velocity and position measured, held for hold_time (stamps of the readings)
        settled_since = [None]

        def settled():
            stamp, q, v = self.last_state
            if stamp < command_time:
                return False
            ok = bool(np.all(np.abs(q - goal) < self.pos_tol)) and (v is None or bool(np.all(np.abs(v) < self.vel_tol)))
            if not ok:
                settled_since[0] = None
                return False
            if settled_since[0] is None:
                settled_since[0] = stamp
            return stamp - settled_since[0] >= self.hold

        def describe():
            stamp, q, v = self.last_state
            worst = int(np.argmax(np.abs(q - goal)))
            return (f"pose {pose_id} (step {step + 1}): arm not settled after {self.settle_timeout:g} s "
                    f"({self.joint_names[worst]} at {q[worst]:.5f} rad, goal {goal[worst]:.5f})")

        try:
            self.wait(settled, self.settle_timeout, "")
        except common.NodeError:
            raise common.NodeError(describe(), 3) from None
        self.publish_progress("measuring", pose_id)
        with self.cond:
            self.sync.reset()
            self.pairs = []
            stamp, q, v = self.last_state
            self.collect_after = stamp
            self.sync.add_a(stamp, (q, v))  # a frame of this very instant pairs with it
            self.collecting = True
        try:
            self.wait(lambda: len(self.pairs) >= self.frames, self.frame_timeout,
                      f"pose {pose_id} (step {step + 1}): fewer than {self.frames} spot frames paired with joint "
                      f"states within {self.frame_timeout:g} s (sync_tolerance {self.sync_tol:g} s)")
        finally:
            with self.cond:
                self.collecting = False
                pairs = list(self.pairs[:self.frames])
        sample = self.average(pose_id, pairs)
        self.publish_sample(sample)
        self.progress.step()
        seen = int(np.sum(~np.isnan(sample.spots[0]).any(axis=1)))
        self.get_logger().info(f"pose {step + 1}/{n} (id {pose_id}) measured in {time.monotonic() - started:.1f} s, "
                               f"{len(pairs)} frames, {seen}/2 spots seen; {self.progress.line()}")

    def average(self, pose_id: int, pairs) -> Samples:
        q = np.mean([pair.a[0] for pair in pairs], axis=0)
        frames = np.array([pair.b for pair in pairs])  # (F,2,2)
        spots = np.full((2, 2), np.nan)
        for j in range(2):
            seen = ~np.isnan(frames[:, j]).any(axis=1)
            if seen.sum() * 2 >= len(frames):  # seen in at least half the frames
                spots[j] = frames[seen, j].mean(axis=0)
        stamp = pairs[-1].b_stamp
        return Samples(np.array([pose_id]), np.array([stamp]), q[None], spots[None])

    def publish_sample(self, sample: Samples) -> None:
        msg = self.Sample()
        stamp = self.stamps_from_float(sample.stamp[0])
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp
        msg.header.frame_id = common.SCREEN_FRAME
        msg.pose = int(sample.pose[0])
        msg.joint_names = self.joint_names
        msg.joint_positions = [float(v) for v in sample.q[0]]
        msg.spots = common.spots_to_msg(sample.spots[0], ~np.isnan(sample.spots[0]).any(axis=1))
        msg.frames = int(self.frames)
        # The CSV row is built from the message, so bag and CSV hold identical values.
        row = bag.samples_from_rows([bag.sample_row_from_msg(msg, "sample")], "sample")
        # On disk first (closed segment: the pose is done), then published, then the CSV row. A crash
        # between the steps is repaired on resume: the CSV from the bag, and the bag's samples are
        # published again (the estimator ignores those it has).
        with self.bag_lock:
            self.bag.write(self.samples_topic, common.now_ns(self), serialize_message(msg))
            self.bag.rotate()
        self.sample_pub.publish(msg)
        self.session.append_sample(row)

    @staticmethod
    def stamps_from_float(stamp: float) -> tuple[int, int]:
        sec = math.floor(stamp)
        nanosec = int(round((stamp - sec) * 1e9))
        if nanosec >= 1_000_000_000:
            sec, nanosec = sec + 1, nanosec - 1_000_000_000
        return int(sec), nanosec

    def publish_progress(self, state: str, pose_id: int) -> None:
        msg = self.SessionProgress()
        msg.header.stamp = self.get_clock().now().to_msg()
        progress = getattr(self, "progress", None)
        msg.done = progress.done if progress else self.done_count
        msg.total = len(self.poses)
        msg.pose = pose_id
        msg.seconds_left = progress.seconds_left() if progress else math.nan
        msg.state = state
        self.publish_recorded(self.progress_pub, common.PROGRESS, msg)

    def publish_recorded(self, publisher, name: str, msg) -> None:
        publisher.publish(msg)
        with self.bag_lock:
            if self.bag is not None:
                self.bag.write(self.resolve_topic_name(name), common.now_ns(self), serialize_message(msg))

    # ---- the end: estimate and report ----
    def finish(self) -> None:
        with self.bag_lock:
            self.bag.rotate()
        samples = self.session.samples(None)
        self.get_logger().info(f"all {len(samples)} poses measured; samples in {self.session.path / 'samples.csv'}, "
                               f"bag in {self.session.bag_dir}")
        if self.estimate_mode == "none":
            self.session.set_info(state="finished")
            self.publish_progress("finished", -1)
            return
        self.publish_progress("estimating", -1)
        if self.estimate_mode == "local":
            from laser_calib.session.estimate import estimate_options, run_calibration
            options = estimate_options(self.method, self.spot_sigma, self.prior, self.robust)
            message = run_calibration(self.robot, samples, options, self.session.path, self.diagnose).calibration.summary()
        else:
            message = self.call_service(samples)
        self.session.set_info(state="finished")
        self.publish_progress("finished", -1)
        self.get_logger().info(message)
        self.get_logger().info(f"report: {self.session.path / 'report.md'}; calibrated robot: "
                               f"{self.session.path / 'robot_calibrated.yaml'}")

    def call_service(self, samples: Samples) -> str:
        client = self.estimate_client
        deadline = time.monotonic() + self.service_timeout
        while not client.wait_for_service(timeout_sec=0.5):
            if self.stopping.is_set():
                raise Stop()
            if time.monotonic() > deadline:
                raise common.NodeError(f"no Estimate service on {self.resolve_service_name(common.ESTIMATE_SERVICE)} "
                                       f"after {self.service_timeout:g} s; the data are in {self.session.path}: "
                                       "estimate offline with laser-calib estimate", 3)
        request = self.EstimateSrv.Request()
        request.samples = [self.sample_msg(samples, r) for r in range(len(samples))]
        request.method = self.method
        request.spot_sigma = float(self.spot_sigma)
        request.prior, request.robust, request.diagnose = bool(self.prior), bool(self.robust), bool(self.diagnose)
        request.output_dir = str(self.session.path) if self.shared_fs else ""
        self.get_logger().info(f"calling {self.resolve_service_name(common.ESTIMATE_SERVICE)} with "
                               f"{len(samples)} samples ({self.method})")
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _: done.set())
        while not done.wait(0.2):
            if self.stopping.is_set():
                raise Stop()
            if time.monotonic() > deadline:
                raise common.NodeError(f"the Estimate service did not answer within {self.service_timeout:g} s", 3)
        response = future.result()
        if not response.success:
            raise common.NodeError(f"estimate failed: {response.message}", 4)
        if not self.shared_fs:
            for name, text in (("report.md", response.report_markdown), ("result.json", response.result_json),
                               ("robot_calibrated.yaml", response.calibrated_robot_yaml)):
                (self.session.path / name).write_text(text)
        if response.diagnosis_json:
            (self.session.path / "diagnosis.json").write_text(response.diagnosis_json)
        return response.message

    def sample_msg(self, samples: Samples, r: int):
        msg = self.Sample()
        msg.header.stamp.sec, msg.header.stamp.nanosec = self.stamps_from_float(samples.stamp[r])
        msg.header.frame_id = common.SCREEN_FRAME
        msg.pose = int(samples.pose[r])
        msg.joint_names = self.joint_names or common.default_joint_names(samples.n_joints)
        msg.joint_positions = [float(v) for v in samples.q[r]]
        msg.spots = common.spots_to_msg(samples.spots[r], ~np.isnan(samples.spots[r]).any(axis=1))
        msg.frames = int(self.frames)
        return msg

    def close(self) -> None:
        self.stopping.set()
        worker = getattr(self, "worker", None)
        if worker is not None and worker.is_alive() and worker is not threading.current_thread():
            worker.join(timeout=5.0)
        with getattr(self, "bag_lock", threading.Lock()):
            if getattr(self, "bag", None) is not None:
                self.bag.close()
                self.bag = None


def main(args=None) -> int:
    return common.run(Sequencer, args, until=lambda node: node.done)


if __name__ == "__main__":
    sys.exit(main())
