"""The sequencer's parts around its measuring loop: its estimate parameters, the
Estimate service call (or the in-process estimate), the held-out and truth
comparison after it, the worker's error handling, and the Sample message of a
core sample. The session folder is opened by session_open.py."""

from __future__ import annotations

import json
import math
import threading
import time
from types import SimpleNamespace

import numpy as np
import rclpy
from builtin_interfaces.msg import Duration

from laser_calib.io.errors import InputError
from laser_calib.io.joint_names import default_joint_names
from laser_calib.io.samples import Samples
from laser_calib.measurement.noise_bounds import JOINT_SIGMA_NOT_GIVEN
from laser_calib.model.robot_file import load_robot
from laser_calib.report import truth
from laser_calib.session.folder import ROBOT_FILE, SAMPLES_FILE, TEST_SAMPLES_FILE

from laser_calib_nodes import common, parameters, session_open, sole_owner

TRUE_ROBOT_FILE = "robot_true.yaml"   # where launch and run-session let the sim arm_driver write the truth
# s without a joint state after which a timeout says they stopped: a driver publishes at 10 Hz or more
STALE_STATES = 1.0


class Stop(Exception):
    """The node is shutting down: leave the sequence."""


def declare(node) -> SimpleNamespace:
    d = lambda *a, **k: parameters.declare(node, *a, **k)  # noqa: E731
    end = SimpleNamespace(
        method=d("estimate.method", "lm", "Final estimate: 'lm' or 'ekf'."),
        spot_sigma=d("estimate.spot_sigma", 0.0, "Final estimate: spot sigma, m (0: estimate it; 'service': the "
                                                  "estimator's spot_sigma, whose 0 is that)."),
        joint_sigma=d("estimate.joint_sigma", JOINT_SIGMA_NOT_GIVEN, "Final estimate: joint-reading sigma, rad; -1: "
                      "not given, as laser-calib estimate without --joint-sigma: estimated from the residual "
                      "('service': the estimator's joint_sigma, whose -1 is that); 0: no joint-reading noise "
                      "('local' only: an Estimate request's 0 is the estimator's); > 0: that sigma.",
                      rule=parameters.JOINT_SIGMA),
        prior=d("estimate.prior", False, "Final estimate: tolerance prior."),
        robust=d("estimate.robust", True, "Final estimate: robust fit, outlying spots rejected."),
        diagnose=d("estimate.diagnose", False, "Final estimate: residual diagnosis."),
        mode=d("estimate.mode", "service", "Final estimate: 'service' (the estimator's Estimate service), "
                                           "'local' (in this process) or 'none'."),
        shared_fs=d("estimate.shared_filesystem", True, "The estimator sees output_dir: it writes the report "
                                                        "there itself (plots included)."),
        timeout=d("estimate.timeout", 600.0, "Final estimate: wait this long for the service, s.",
                  rule=parameters.positive),
        truth=d("truth", "", f"True robot model (simulation) for the report's truth comparison; empty: "
                             f"output_dir/{TRUE_ROBOT_FILE} when it exists."))
    if end.mode not in ("service", "local", "none"):
        raise parameters.NodeError(f"parameter estimate.mode: expected 'service', 'local' or 'none', got {end.mode!r}", 2)
    try:  # at the start, not after every pose is measured
        final_options(end)
    except InputError as exc:
        raise parameters.NodeError(f"parameter estimate.{exc.where}: {exc.problem}", 2) from None
    try:  # read at the end, for the report: a bad one was said after the whole session was measured
        if end.truth:
            load_robot(end.truth)
    except InputError as exc:
        raise parameters.NodeError(f"parameter truth: {exc}", 2) from None
    if end.mode == "service" and end.joint_sigma == 0:
        raise parameters.NodeError("parameter estimate.joint_sigma: 0 (no joint-reading noise) cannot be asked of the "
                                   "estimator (an Estimate request's 0 is its joint_sigma parameter): set the "
                                   "estimator's joint_sigma to 0 and leave this -1, or estimate.mode:=local", 2)
    return end


def final_options(end):
    """The final estimate's options (end: declare()'s), as the command line makes them of its own
    (session.estimate.estimate_options): checked at the start, then the in-process estimate's. A bad
    value: InputError naming it."""
    from laser_calib.session.estimate import estimate_options  # as the final estimate imports it
    return estimate_options(end.method, end.spot_sigma, end.prior, end.robust, end.joint_sigma)


def request_joint_sigma(end) -> float:
    """The Estimate request's joint_sigma: the parameter's, not given (-1) left to the estimator's
    joint_sigma (the request's 0), as a spot_sigma 0 is left to its spot_sigma."""
    return 0.0 if end.joint_sigma == JOINT_SIGMA_NOT_GIVEN else float(end.joint_sigma)


def measured(node, line: str, spots: np.ndarray) -> None:
    """A measured pose's progress line (its spots (2, 2), NaN where unseen), a WARN naming each
    laser not seen (a fault of the setup, or a pose off the screen: worth a look while the arm
    moves on); then the unseen rule: this run's first node.unseen_limit poses without any spot end
    the session, since nothing it would measure calibrates (a whole session measured in vain)."""
    seen = ~np.isnan(spots).any(axis=1)
    line = f"{line}, {int(seen.sum())}/2 spots seen"
    if seen.all():
        node.get_logger().info(f"{line}; {node.progress.line()}")
    else:
        missing = " and ".join(f"laser {j + 1}" for j in np.flatnonzero(~seen))
        node.get_logger().warning(f"{line}: {missing} not seen (occluded, off the screen, or below the "
                                  f"spot_detector's min_peak_dn); kept as measured; {node.progress.line()}")
    if node.unseen_poses is None:
        return
    node.unseen_poses = None if seen.any() else node.unseen_poses + 1
    if node.unseen_poses == node.unseen_limit:
        raise parameters.NodeError(f"no spot seen in this run's first {node.unseen_limit} poses: are the lasers on, the "
                               "screen in the camera's view, the spot_detector's min_peak_dn reachable? Those poses "
                               f"are kept in {node.session.path}; run again to resume from the next one "
                               "(unseen_limit:=0 measures on regardless)", 2)


def warn_disturbed(node, collector) -> None:
    """Said at once: a joint reading left the goal while the frames of the pose were taken."""
    q = collector.disturbed[-1][1]
    node.get_logger().warning(
        f"{node.where}: a joint reading left the goal while its frames were taken "
        f"({collector.settle.off_goal(q, node.joint_names)}): a reading glitch, or the arm was moved; the frames "
        "are taken again once it has settled anew")


def check(node) -> None:
    """Within a wait for the arm or the camera: NodeError (exit 3) when the arm stopped on a fault its
    driver reported on /diagnostics (an ERROR, then no joint state for STALE_STATES s), naming it at
    once; and the recorder's check (a full disk)."""
    node.recorder.check()
    last = node.last_state[3] if node.last_state else node.created
    fault = node.arm_faults.stopped(last, STALE_STATES)
    if fault:
        where = getattr(node, "where", None) or "waiting for the arm"
        raise parameters.NodeError(f"{where}: the arm stopped on a fault, {fault} (no joint state for "
                                   f"{time.monotonic() - last:.1f} s)", 3)


def stale(node) -> str:
    """'; no joint state for T s ...' when the arm's joint states stopped coming (a driver that
    died leaves the sequencer waiting for a settling that cannot come), else ''."""
    age = time.monotonic() - node.last_state[3]
    return f"; no joint state for {age:.1f} s: has the arm driver stopped?" if age > STALE_STATES else ""


def client(node):
    from laser_calib_interfaces.srv import Estimate
    return node.create_client(Estimate, common.ESTIMATE_SERVICE)


def guard(node, run) -> None:
    """Run the sequence; a failure is one log line, a progress 'failed' and the exit code."""
    try:
        run()
    except Stop:
        pass
    except (InputError, parameters.NodeError) as exc:
        node.get_logger().error(str(exc))
        node.publish_progress("failed", -1)
        node.exit_code = exc.code if isinstance(exc, parameters.NodeError) else 2
    except Exception as exc:  # a bug: say it in one line, keep the data, exit non-zero
        if node.stopping.is_set() or not rclpy.ok():
            return  # shutting down (Ctrl-C): a publish after the context went away
        node.get_logger().error(f"sequencer failed: {type(exc).__name__}: {exc}")
        node.publish_progress("failed", -1)
        node.exit_code = 1
    finally:
        node.done = True


def finish(node) -> None:
    node.recorder.rotate()
    session, end, log = node.session, node.end, node.get_logger()
    samples = session.samples(None)
    test = session.samples(None, test=True) if node.poses.test.any() else None  # held out: never fitted
    measured = f"all {len(node.poses)} poses measured; samples in {session.path / 'samples.csv'}, bag in " \
               f"{session.bag_dir}"
    lost = int(np.isnan(samples.spots).any(axis=2).sum())  # spots (P,2,2) of the poses to fit
    if lost:
        log.warning(f"{measured}; {lost} of {2 * len(samples)} spots of the poses to fit were not seen")
    else:
        log.info(measured)
    if end.mode != "none":
        node.publish_progress("estimating", -1)
        if end.mode == "local":
            from laser_calib.session.estimate import run_calibration
            sources = {"robot": str(session.path / ROBOT_FILE), "samples": str(session.path / SAMPLES_FILE),
                       "test": str(session.path / TEST_SAMPLES_FILE) if test is not None else None,
                       "compensator": None}  # the files just read, as `laser-calib estimate` names its inputs
            outcome = run_calibration(node.robot, samples, final_options(end), session.path, end.diagnose, sources,
                                      test=test)
            message, warned = outcome.message, outcome.warned
            failed = outcome.calibration.failure is not None
        else:
            message, failed, warned = call_service(node, samples, test)
        if failed:  # estimated but no calibration (NOT CONVERGED ...): its files show where the fit went
            raise parameters.NodeError(f"estimate failed: {message}; its files are in {session.path}", 4)
        common.log_warned(log, warned, message)
        compare_with_truth(node)
        if history := session_open.history_lines(session, len(node.poses)):
            with open(session.path / "report.md", "a") as report:
                report.write("\n".join(history))
        log.info(f"report: {session.path / 'report.md'}; calibrated robot: {session.path / 'robot_calibrated.yaml'}")
    session.set_info(state="finished")
    node.publish_progress("finished", -1)


def compare_with_truth(node) -> None:
    """Held-out spot errors and, in simulation, the errors against the true robot: truth.json, report.md."""
    session, path = node.session, node.end.truth or str(node.session.path / TRUE_ROBOT_FILE)
    test = session.samples(node.robot, test=True) if node.poses.test.any() else None
    true = load_robot(path) if node.end.truth or (session.path / TRUE_ROBOT_FILE).exists() else None
    if test is None and true is None:
        return
    calibrated = load_robot(session.path / "robot_calibrated.yaml", failed_fit=True)  # a failed fit too
    comparison = truth.compare(node.robot, calibrated, test, true)
    (session.path / "truth.json").write_text(json.dumps(comparison, indent=2))
    truth.append_to_report(session.path / "report.md", comparison)
    for line in truth.markdown(comparison):
        # the table with its header: its rows alone were four numbers without a name or a unit
        if line.startswith(("Test poses", "Against the true robot", "| error", "| end-effector", "| spot")):
            node.get_logger().info(line)


def call_service(node, samples: Samples, test: Samples | None) -> tuple[str, bool, bool]:
    """The Estimate service's message, whether it failed (files written, no calibration)
    and whether the estimate has warnings."""
    end, path = node.end, node.session.path
    name = node.resolve_service_name(common.ESTIMATE_SERVICE)
    deadline = time.monotonic() + end.timeout
    offline = f"the data are in {path}: estimate offline with laser-calib estimate"
    if not node.estimate_client.service_is_ready():  # else minutes of silence when no estimator runs
        node.get_logger().info(f"waiting up to {end.timeout:g} s for the Estimate service on {name} "
                               "(is the estimator running?)")
    while not node.estimate_client.wait_for_service(timeout_sec=0.5):
        if node.stopping.is_set():
            raise Stop()
        if time.monotonic() > deadline:
            raise parameters.NodeError(f"no Estimate service on {name} after {end.timeout:g} s; {offline}", 3)
    try:
        sole_owner.estimator(node)
    except parameters.NodeError as exc:
        raise parameters.NodeError(f"{exc}; {offline}", 3) from None
    request = node.estimate_client.srv_type.Request(
        samples=[sample_msg(node, samples, r) for r in range(len(samples))],
        test_samples=[sample_msg(node, test, r) for r in range(len(test))] if test is not None else [],
        method=end.method,
        spot_sigma=float(end.spot_sigma), joint_sigma=request_joint_sigma(end), prior=bool(end.prior),
        robust=bool(end.robust),
        diagnose=bool(end.diagnose), output_dir=str(path) if end.shared_fs else "")
    node.get_logger().info(f"calling {name} with {len(samples)} samples"
                           + (f" and {len(test)} test samples" if test is not None else "") + f" ({end.method})")
    future = node.estimate_client.call_async(request)
    answered = threading.Event()
    future.add_done_callback(lambda _: answered.set())
    while not answered.wait(0.2):
        if node.stopping.is_set():
            raise Stop()
        # An estimator that crashed or was killed never answers: DDS drops it from the graph once its
        # lease runs out (about 20 s), and waiting the whole timeout (600 s) would say nothing more.
        if not node.estimate_client.service_is_ready():
            raise parameters.NodeError(f"the Estimate service on {name} went away before answering (the estimator "
                                       f"stopped or crashed); {offline}", 3)
        if time.monotonic() > deadline:
            raise parameters.NodeError(f"the Estimate service did not answer within {end.timeout:g} s", 3)
    response = future.result()
    if not response.result_json:  # refused: nothing was estimated
        raise parameters.NodeError(f"estimate failed: {response.message}", 4)
    if not end.shared_fs:
        for file, text in (("report.md", response.report_markdown), ("result.json", response.result_json),
                           ("robot_calibrated.yaml", response.calibrated_robot_yaml)):
            (path / file).write_text(text)
        if node.robot.chain is not None:  # the URDF to apply: the calibrated robot's own text
            calibrated = load_robot(path / "robot_calibrated.yaml", failed_fit=True)  # a failed fit's too
            (path / "robot_calibrated.urdf").write_text(calibrated.chain.urdf)
    if response.diagnosis_json:
        (path / "diagnosis.json").write_text(response.diagnosis_json)
    from laser_calib.session.estimate import warned  # as the local estimate imports it
    return response.message, not response.success, warned(json.loads(response.result_json)["warnings"],
                                                           response.diagnosis_json)


def stamps_from_float(stamp: float) -> tuple[int, int]:
    sec = math.floor(stamp)
    nanosec = int(round((stamp - sec) * 1e9))
    if nanosec >= 1_000_000_000:
        sec, nanosec = sec + 1, nanosec - 1_000_000_000
    return int(sec), nanosec


def duration(seconds: float) -> Duration:
    sec, nanosec = stamps_from_float(seconds)
    return Duration(sec=sec, nanosec=nanosec)


def sample_msg(node, samples: Samples, r: int):
    msg = node.Sample()
    msg.header.stamp.sec, msg.header.stamp.nanosec = stamps_from_float(samples.stamp[r])
    msg.header.frame_id = common.SCREEN_FRAME
    msg.pose = int(samples.pose[r])
    msg.joint_names = node.joint_names or default_joint_names(node.robot)
    msg.joint_positions = [float(v) for v in samples.q[r]]
    msg.spots = common.spots_to_msg(samples.spots[r], ~np.isnan(samples.spots[r]).any(axis=1))
    msg.frames = int(node.frames)
    return msg
