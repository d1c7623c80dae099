"""estimator: online EKF on each measurement, batch estimate on request.

Inputs (``input``):
  'samples'  samples (laser_calib_interfaces/Sample): one synchronized,
             averaged measurement per pose, as the sequencer publishes them
             (and replay republishes them). The default.
  'stream'   joint_states (sensor_msgs/JointState) and spots
             (laser_calib_interfaces/SpotPair), paired by header stamp within
             ``sync_tolerance`` s (sync.StampSynchronizer); a pair counts only
             when every |joint velocity| is below ``stream.max_joint_speed``
             (the arm is still). For a live arm driven by something other than
             the sequencer.
Each measurement is accumulated and updates the online EKF
(laser_calib.estimation.online.OnlineEkf); after each update the node publishes
  dh_parameters (laser_calib_interfaces/DhParameters, transient local)
  calibration_markers (visualization_msgs/MarkerArray, frame `screen`): the
    measured spots, the spots predicted by the current estimate, and the two
    beams of the latest pose.
Services
  estimator/estimate (laser_calib_interfaces/Estimate): batch estimate of the
    request's samples or of the accumulated ones, by
    laser_calib.session.estimate.run_calibration (the command line's code path). Bad
    requests get success = false and a one-line message; the node keeps serving.
    Requests are served one at a time (a mutually exclusive callback group);
    measurements keep flowing in meanwhile (another group, a lock on the state).
  estimator/reset (std_srvs/Trigger): forget the accumulated samples, restart the EKF.
"""

from __future__ import annotations

import math
import sys
import threading
import traceback

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA

from laser_calib.io.errors import InputError
from laser_calib.model.kinematics import predict
from laser_calib.io.samples import Samples

from laser_calib.io import bag

from laser_calib_nodes import common
from laser_calib.report.files import calibrated_robot_yaml, report_markdown, result_json
from laser_calib.session.estimate import estimate_options, laser_statistics, online_options, run_calibration
from laser_calib.session.sync import StampSynchronizer

MAX_MARKER_POINTS = 2000

LASER_COLOURS = ((1.0, 0.1, 0.1), (0.1, 0.9, 0.1))


class Estimator(Node):
    def __init__(self):
        super().__init__("estimator")
        d = lambda *a, **k: common.declare(self, *a, **k)  # noqa: E731
        self.robot, self.robot_path = common.robot_param(self)
        self.input = d("input", "samples", "'samples' (synchronized Sample messages) or 'stream' (joint_states "
                                           "and spots paired by stamp).")
        self.sync_tol = d("sync_tolerance", 0.02, "'stream': max stamp difference of a pair, s (at least half "
                                                   "the joint_states period).")
        self.max_speed = d("stream.max_joint_speed", 0.002, "'stream': a pair counts only when every |joint "
                                                            "velocity| is below this, rad/s.")
        self.spot_sigma = d("spot_sigma", 0.0, "Spot sigma, m, for the online EKF and for requests with "
                                               "spot_sigma 0; 0: estimate it (batch) / 1 mm (online).")
        self.markers_on = d("markers", True, "Publish calibration_markers.")
        if self.input not in ("samples", "stream"):
            raise common.NodeError(f"parameter input: expected 'samples' or 'stream', got {self.input!r}", 2)
        if not (math.isfinite(self.spot_sigma) and self.spot_sigma >= 0):
            raise common.NodeError(f"parameter spot_sigma: expected >= 0 m, got {self.spot_sigma}", 2)

        from laser_calib_interfaces.msg import DhParameters, Sample, SpotPair, SpotStatistics
        from laser_calib_interfaces.srv import Estimate
        self.DhParameters, self.SpotStatistics = DhParameters, SpotStatistics

        self.lock = threading.Lock()
        self.rows: list[tuple[int, float, np.ndarray, np.ndarray]] = []
        self.keys: set[tuple[int, float]] = set()
        self.online = self.make_online()

        self.param_pub = self.create_publisher(DhParameters, common.DH_PARAMETERS, common.LATCHED_QOS)
        self.marker_pub = self.create_publisher(MarkerArray, common.MARKERS, common.LATCHED_QOS)
        inputs = MutuallyExclusiveCallbackGroup()
        services = MutuallyExclusiveCallbackGroup()
        if self.input == "samples":
            self.create_subscription(Sample, common.SAMPLES, self.on_sample, common.SAMPLES_QOS,
                                     callback_group=inputs)
        else:
            self.sync = StampSynchronizer(self.sync_tol)
            self.create_subscription(JointState, common.JOINT_STATES, self.on_joint_state, common.STREAM_QOS,
                                     callback_group=inputs)
            self.create_subscription(SpotPair, common.SPOTS, self.on_spots, common.STREAM_QOS,
                                     callback_group=inputs)
        self.create_service(Estimate, common.ESTIMATE_SERVICE, self.on_estimate, callback_group=services)
        self.create_service(Trigger, common.RESET_SERVICE, self.on_reset, callback_group=services)
        self.get_logger().info(f"robot '{self.robot.name}' ({self.robot.n_params} parameters), input "
                               f"'{self.input}'")

    # ---- online ----
    def make_online(self):
        from laser_calib.estimation.online import OnlineEkf
        return OnlineEkf(self.robot, online_options(self.spot_sigma))

    def on_sample(self, msg) -> None:
        try:
            row = bag.sample_row_from_msg(msg, f"sample (pose {msg.pose})")
            self.check_row(row, f"sample (pose {msg.pose})")
        except InputError as exc:
            self.get_logger().error(f"ignored: {exc}")
            return
        key = (row[0], row[1])  # (pose id, stamp): a sample published again (sequencer resumed) counts once
        with self.lock:
            if key in self.keys:
                return
            self.keys.add(key)
        self.add(row)

    def on_joint_state(self, msg: JointState) -> None:
        q = np.array(msg.position, dtype=float)
        v = np.array(msg.velocity, dtype=float) if len(msg.velocity) == len(msg.position) else None
        for pair in self.sync.add_a(common.stamp_seconds(msg.header.stamp), (q, v)):
            self.add_pair(pair)

    def on_spots(self, msg) -> None:
        for pair in self.sync.add_b(common.stamp_seconds(msg.header.stamp), common.spots_from_msg(msg.spots)):
            self.add_pair(pair)

    def add_pair(self, pair) -> None:
        q, v = pair.a
        if v is not None and not bool(np.all(np.abs(v) < self.max_speed)):
            return  # moving: joint reading and image do not describe the same pose
        row = (len(self.rows), pair.b_stamp, q, pair.b)
        try:
            self.check_row(row, "joint state")
        except InputError as exc:
            self.get_logger().error(f"ignored: {exc}")
            return
        self.add(row)

    def check_row(self, row, where: str) -> None:
        n = len(row[2])
        if n != self.robot.n_joints:
            raise InputError(where, f"{n} joint positions, robot '{self.robot.name}' has {self.robot.n_joints}")
        bad = np.flatnonzero(~np.isfinite(row[2]))
        if bad.size:
            raise InputError(where, f"joint_positions[{bad[0]}] is not finite ({row[2][bad[0]]})")

    def add(self, row) -> None:
        with self.lock:
            self.rows.append(row)
            count = len(self.rows)
            self.online.update(row[2], row[3])
            errors = np.array(self.online.errors, dtype=float)
            std = np.array(self.online.std, dtype=float)
            identifiable = np.array(self.online.identifiable, dtype=bool)
        self.publish_online(errors, std, identifiable, count)
        if self.markers_on:
            self.publish_markers(errors)

    def publish_online(self, errors: np.ndarray, std: np.ndarray, identifiable: np.ndarray, count: int) -> None:
        msg = self.DhParameters()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = common.SCREEN_FRAME
        msg.robot_name = self.robot.name
        msg.method = "ekf"
        msg.names = list(self.robot.param_names)
        values = np.nan_to_num(errors)
        msg.values = [float(v) for v in self.robot.vector() + values]
        msg.errors = [float(v) for v in errors]
        msg.std = [float(v) for v in std]
        msg.identifiable = [bool(v) for v in identifiable]
        msg.iterations = 0
        msg.sample_count = count
        self.param_pub.publish(msg)

    def publish_markers(self, errors: np.ndarray) -> None:
        with self.lock:
            rows = self.rows[-MAX_MARKER_POINTS // 2:]
        q = np.array([r[2] for r in rows])
        measured = np.array([r[3] for r in rows])
        prediction = predict(self.robot, q, np.nan_to_num(errors))
        stamp = self.get_clock().now().to_msg()
        array = MarkerArray()

        def marker(ns: str, ident: int, kind: int, scale: float, colour, alpha=1.0) -> Marker:
            m = Marker()
            m.header.stamp = stamp
            m.header.frame_id = common.SCREEN_FRAME
            m.ns, m.id, m.type, m.action = ns, ident, kind, Marker.ADD
            m.pose.orientation.w = 1.0
            m.scale.x = m.scale.y = m.scale.z = scale
            m.color = ColorRGBA(r=colour[0], g=colour[1], b=colour[2], a=alpha)
            return m

        for j in range(2):
            points = marker("measured", j, Marker.SPHERE_LIST, 0.01, LASER_COLOURS[j])
            points.points = [Point(x=0.0, y=float(s[0]), z=float(s[1])) for s in measured[:, j] if np.isfinite(s).all()]
            predicted = marker("predicted", j, Marker.SPHERE_LIST, 0.006, (0.2, 0.4, 1.0), 0.8)
            hit = prediction.hit[:, j]
            predicted.points = [Point(x=0.0, y=float(s[0]), z=float(s[1])) for s in prediction.spots[hit, j]]
            beam = marker("beams", j, Marker.LINE_LIST, 0.003, LASER_COLOURS[j], 0.7)
            if hit[-1]:
                origin = prediction.state.origin[-1]
                end = prediction.spots[-1, j]
                beam.points = [Point(x=float(origin[0]), y=float(origin[1]), z=float(origin[2])),
                               Point(x=0.0, y=float(end[0]), z=float(end[1]))]
            array.markers += [points, predicted, beam]
        self.marker_pub.publish(array)

    # ---- services ----
    def on_reset(self, request, response):
        with self.lock:
            self.rows = []
            self.keys = set()
            self.online.reset()
            if self.input == "stream":
                self.sync.reset()
        response.success = True
        response.message = "accumulated samples cleared, online EKF restarted"
        self.get_logger().info(response.message)
        return response

    def on_estimate(self, request, response):
        try:
            samples, source = self.request_samples(request)
            options = estimate_options(request.method, request.spot_sigma or self.spot_sigma, request.prior,
                                       request.robust)
            outcome = run_calibration(self.robot, samples, options, request.output_dir or None, request.diagnose,
                                      sources={"robot": self.robot_path, "samples": source})
        except InputError as exc:
            response.success = False
            response.message = str(exc)
            self.get_logger().warning(f"estimate refused: {exc}")
            return response
        except Exception as exc:  # never let a request take the node down
            response.success = False
            response.message = f"internal error: {type(exc).__name__}: {exc}"
            self.get_logger().error(response.message + "\n" + traceback.format_exc())
            return response
        self.fill(response, outcome, len(samples))
        self.get_logger().info(response.message)
        return response

    def request_samples(self, request) -> tuple[Samples, str]:
        if request.use_accumulated:
            with self.lock:
                rows = list(self.rows)
            if not rows:
                raise InputError("request", "use_accumulated is true but no samples have been accumulated yet")
            source = f"{len(rows)} samples accumulated by {self.get_fully_qualified_name()}"
        else:
            if not request.samples:
                raise InputError("request", "no samples (and use_accumulated is false)")
            rows = []
            for k, msg in enumerate(request.samples):
                where = f"request: sample {k + 1} (pose {msg.pose})"
                row = bag.sample_row_from_msg(msg, where)
                self.check_row(row, where)
                rows.append(row)
            source = f"{len(rows)} samples of an Estimate request"
        return bag.samples_from_rows(rows, "request"), source

    def fill(self, response, outcome, count: int) -> None:
        calibration = outcome.calibration
        est = calibration.estimate
        params = self.DhParameters()
        params.header.stamp = self.get_clock().now().to_msg()
        params.header.frame_id = common.SCREEN_FRAME
        params.robot_name = self.robot.name
        params.method = calibration.options.method
        params.names = list(est.names)
        params.values = [float(v) for v in calibration.calibrated.vector()]
        params.errors = [float(v) for v in est.errors]
        params.std = [float(v) for v in est.std]
        params.identifiable = [bool(v) for v in est.identifiable]
        params.iterations = int(est.fit.iterations)
        params.sample_count = count
        response.parameters = params
        stats = calibration.spot_error["calibration"]
        for field in ("before", "after"):
            values = laser_statistics(stats[field])
            msg = self.SpotStatistics()
            msg.mean, msg.std, msg.max = values["mean"], values["std"], values["max"]
            msg.count = values["count"]
            setattr(response, field, msg)
        response.diagnosis_json = outcome.diagnosis_json
        response.report_markdown = report_markdown(calibration)
        response.result_json = result_json(calibration)
        response.calibrated_robot_yaml = calibrated_robot_yaml(calibration)
        response.success = True
        response.message = calibration.summary()


def main(args=None) -> int:
    return common.run(Estimator, args, make_executor=lambda: MultiThreadedExecutor(num_threads=3))


if __name__ == "__main__":
    sys.exit(main())
