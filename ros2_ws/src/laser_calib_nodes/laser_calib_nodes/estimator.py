"""estimator: online EKF on each measurement, batch estimate on request
(topics, QoS, services, the action and parameters: the package README).

Input 'samples' (Sample, as the sequencer or replay publishes them; subscribed
with the sequencer's transient-local QoS and with the default one, each (pose,
stamp) counted once; the held-out ones on test_samples kept apart, never fitted,
for the estimate's test figures and the diagnosis's predictive test) or 'stream'
(joint_states + spots paired by stamp within sync_tolerance, taken when every
|joint velocity| < stream.max_joint_speed, the frames of one still pose averaged into one
sample, as the sequencer's are). In
both, and in the ~/estimate request's samples, each joint's reading is found by its
name, ``joint_names``, as the sequencer does (joint_states.py; a Sample's by
laser_calib.io.joint_names, as estimate --bag reads a bag's).
Each measurement updates the online EKF, then dh_parameters and
calibration_markers (markers.py) are published. ~/estimate runs
laser_calib.session.estimate.run_calibration (the command line's code path: the
robot file's effects, the 'compensator' file when set), one request at a time
while measurements flow in, a bad request answered with success = false and one
line; ~/reset forgets the samples; ~/calibrate is the action (calibrate.py).
spot_sigma and joint_sigma (parameters.noise), the noise of the requests that leave theirs 0
and of the online EKF, are the command line's --spot-sigma and --joint-sigma; not given:
spot_sigma 0 (estimated), joint_sigma -1 (estimated from the residual, with the spot sigma or
at the one given); joint_sigma 0: no joint-reading noise. They, stream.max_joint_speed and markers can be
set at run time; the rest are read-only.
"""

from __future__ import annotations

import sys
import threading
import time
import traceback

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from laser_calib.io.errors import InputError

from laser_calib_nodes import common, parameters, responses
from laser_calib_nodes.calibrate import CalibrateServer
from laser_calib_nodes.joint_states import JointStateReader
from laser_calib_nodes.markers import MAX_POINTS, calibration_markers, online_parameters
from laser_calib_nodes.sample_rows import Row, request_options, request_sets, row_from_msg
from laser_calib_nodes.stream_input import StreamInput
from laser_calib.session.estimate import online_options, run_calibration


class Estimator(Node):
    def __init__(self):
        super().__init__("estimator")
        d = lambda *a, **k: parameters.declare(self, *a, **k)  # noqa: E731
        self.robot, self.robot_path = common.robot_param(self, lasers=True)
        self.compensator, self.compensator_path = common.compensator_param(self)
        self.input = d("input", "samples", "'samples' (synchronized Sample messages) or 'stream' (joint_states "
                                           "and spots paired by stamp).")
        self.sync_tol = d("sync_tolerance", 0.02, "'stream': max stamp difference of a pair, s (at least half the "
                                                  "joint_states period).", rule=parameters.SYNC_TOLERANCE)
        self.max_speed = d("stream.max_joint_speed", 0.002, "'stream': a pair counts only when every |joint "
                                                            "velocity| is below this, rad/s.",
                           read_only=False, rule=parameters.positive)
        pose_tolerance = d("stream.pose_tolerance", 0.003, "'stream': the still frames of one pose are averaged into "
                                                           "one sample; a reading that leaves the pose's first by "
                                                           "more than this (rad, or m for a prismatic joint) starts "
                                                           "another, as a moving one ends it.",
                           rule=parameters.positive)
        self.spot_sigma, self.joint_sigma = parameters.noise(self)
        self.markers_on = d("markers", True, "Publish calibration_markers.", read_only=False)
        names = d("joint_names", Parameter.Type.STRING_ARRAY, "The robot's joints, base to tip, found by name in "
                  "joint_states ('stream') and in each Sample's joint_names (either may list them in any order, and "
                  "more joints). Default: a URDF arm's joints; for a D-H robot joint1..jointN when the message has "
                  "them, else its own order when it has exactly the robot's joints.",
                  type_=Parameter.Type.STRING_ARRAY)
        self.joints = JointStateReader(self.robot, names, self.get_logger())
        if self.input not in ("samples", "stream"):
            raise parameters.NodeError(f"parameter input: expected 'samples' or 'stream', got {self.input!r}", 2)
        parameters.dynamic(self, {**parameters.NOISE_ATTRIBUTES, "stream.max_joint_speed": "max_speed",
                                  "markers": "markers_on"})

        from laser_calib_interfaces.msg import DhParameters, Sample
        from laser_calib_interfaces.srv import Estimate

        self.lock = threading.Lock()
        self.rows: list[Row] = []
        self.keys: set[tuple[int, float]] = set()
        self.test_rows: list[Row] = []  # held out: never fitted
        self.test_keys: set[tuple[int, float]] = set()
        self.refused: list[str] = []  # why each (test) sample was refused, said again when a request finds none
        self.online = self.make_online()

        self.param_pub = self.create_publisher(DhParameters, common.DH_PARAMETERS, common.LATCHED_QOS)
        self.marker_pub = self.create_publisher(MarkerArray, common.MARKERS, common.LATCHED_QOS)
        inputs = MutuallyExclusiveCallbackGroup()
        self.service_group = services = MutuallyExclusiveCallbackGroup()
        if self.input == "samples":
            # A volatile publisher (`ros2 topic pub`) matches only the volatile subscription: the transient-local
            # one keeps quiet of it ("incompatible QoS ... no messages"); the other still warns of a best-effort one.
            quiet = SubscriptionEventCallbacks(incompatible_qos=lambda _: None)
            for qos, events in ((common.SAMPLES_QOS, quiet), (common.SAMPLES_INPUT_QOS, None)):
                self.create_subscription(Sample, common.SAMPLES, self.on_sample, qos, callback_group=inputs,
                                         event_callbacks=events)
                self.create_subscription(Sample, common.TEST_SAMPLES, self.on_test_sample, qos, callback_group=inputs,
                                         event_callbacks=events)
        else:
            self.stream = StreamInput(self, self.sync_tol, pose_tolerance, inputs)
        self.estimate_service = self.create_service(Estimate, common.PRIVATE_ESTIMATE, self.on_estimate,
                                                    qos_profile=common.KEEP_ALL_QOS, callback_group=services)
        self.create_service(Trigger, common.PRIVATE_RESET, self.on_reset, qos_profile=common.KEEP_ALL_QOS,
                            callback_group=services)
        self.calibrate = CalibrateServer(self)
        self.get_logger().info(f"robot '{self.robot.name}' ({self.robot.n_params} parameters), input "
                               f"'{self.input}'")

    def close(self) -> None:
        """run()'s cleanup: a Calibrate goal in progress ends first (CalibrateServer.close); an
        Estimate being served is answered first: rclpy sends the response after the callback,
        before it frees the group, and a node destroyed in between failed the send ('exception
        never retrieved: cannot use Destroyable'). The process waits for that callback anyway."""
        self.calibrate.close()
        while not self.service_group.can_execute(self.estimate_service):  # the executor starts no other
            time.sleep(0.05)

    # ---- online ----
    def make_online(self):
        from laser_calib.estimation.online import OnlineEkf
        return OnlineEkf(self.robot, online_options(self.spot_sigma, self.joint_sigma))

    def on_sample(self, msg) -> None:
        row = self.new_row(msg, "sample", self.keys)
        if row is not None:
            self.add(row)

    def on_test_sample(self, msg) -> None:
        """A held-out sample: kept for the requests' test set, never given to the online EKF."""
        row = self.new_row(msg, "test sample", self.test_keys)
        if row is not None:
            with self.lock:
                self.test_rows = sorted(self.test_rows + [row], key=lambda r: r[1])

    def new_row(self, msg, what: str, keys: set):
        """The message's row, or None when it is bad (said once) or already counted."""
        # (pose id, stamp): a sample published again (sequencer resumed), or delivered by both subscriptions,
        # counts once, and a bad one is said once (it was said twice)
        key = (int(msg.pose), common.stamp_seconds(msg.header.stamp))
        with self.lock:
            if key in keys:
                return None
            keys.add(key)
        try:
            return row_from_msg(msg, f"{what} (pose {msg.pose})", self.joints, self.robot)
        except InputError as exc:
            with self.lock:
                self.refused.append(str(exc))
            self.get_logger().error(f"ignored: {exc}")
            return None

    def accumulated(self) -> tuple[list[Row], list[Row]]:
        """The rows and test rows a request with use_accumulated takes; 'stream': the pose being measured
        too (the arm has not moved on from it)."""
        with self.lock:
            pending = self.stream.pending() if self.input == "stream" else None
            return self.rows + ([pending] if pending is not None else []), list(self.test_rows)

    def add(self, row) -> None:
        with self.lock:
            self.rows = sorted(self.rows + [row], key=lambda r: r[1])  # in stamp order, as the online EKF takes them
            count = len(self.rows)
            self.online.take(row[1], row[2], row[3])
            errors = np.array(self.online.errors, dtype=float)
            std = np.array(self.online.std, dtype=float)
            identifiable = np.array(self.online.identifiable, dtype=bool)
        self.get_logger().debug(f"sample {row[0]} (stamp {row[1]:.6f} s) taken: {count} samples")  # in their order
        stamp = self.get_clock().now().to_msg()
        self.param_pub.publish(online_parameters(self.robot, errors, std, identifiable, count, stamp))
        if self.markers_on:
            with self.lock:
                rows = self.rows[-MAX_POINTS // 2:]
            self.marker_pub.publish(calibration_markers(self.robot, np.array([r[2] for r in rows]),
                                                        np.array([r[3] for r in rows]), errors, stamp))

    # ---- services ----
    def on_reset(self, request, response):
        with self.lock:
            self.rows, self.test_rows = [], []
            self.keys, self.test_keys, self.refused = set(), set(), []
            self.online = self.make_online()
            if self.input == "stream":
                self.stream.reset()
        response.success = True
        response.message = "accumulated samples cleared, online EKF restarted"
        self.get_logger().info(response.message)
        return response

    def on_estimate(self, request, response):
        try:
            # the request's own fields first (an unknown method is said as such, not as no samples)
            options, output_dir = request_options(self, request), common.request_output_dir(request.output_dir)
            samples, test, sources = request_sets(self, request)
            # the request may run for minutes (the diagnosis): say it started
            self.get_logger().info(f"estimating from {sources['samples']}"
                                   + (f", tested on {sources['test']}" if test is not None else "")
                                   + (", then the diagnosis" if request.diagnose else ""))
            outcome = run_calibration(self.robot, samples, options, output_dir, request.diagnose, sources,
                                      self.compensator, test)
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
        responses.fill(response, outcome, self.robot, len(samples), self.get_clock().now().to_msg())
        common.log_warned(self.get_logger(), outcome.warned, response.message)
        return response


def main(args=None) -> int:
    return common.run(Estimator, args, make_executor=lambda: MultiThreadedExecutor(num_threads=4))


if __name__ == "__main__":
    sys.exit(main())
