"""ROS side of the tests, run as a subprocess in the workspace environment
(the pytest process itself stays ROS-free). Prints one JSON document.

    ros_client.py params COUNT [TOPIC]         latest dh_parameters once sample_count >= COUNT
    ros_client.py markers                      the latched calibration_markers
    ros_client.py move Q1 Q2 ...               send a joint_trajectory goal, wait until joint_states reach it
    ros_client.py reset                        call estimator/reset
    ros_client.py estimate-accumulated         Estimate with use_accumulated
    ros_client.py bad-and-concurrent ROBOT     the service test: bad requests and concurrent clients
    ros_client.py estimate-csv SAMPLES.csv [OUTPUT_DIR]  Estimate the samples of a CSV (spot samples, any robot)
    ros_client.py estimate-csv-diagnose SAMPLES.csv      the same, with the diagnosis
    ros_client.py estimate-joint-sigma SAMPLES.csv SIGMA ...  the same, one request per joint_sigma in turn: the
                                               noise result.json says (or success false and the message)
    ros_client.py calibrate [diagnose] [cancel]  a goal of the estimator/calibrate action
    ros_client.py calibrate-until-diagnosis ROBOT  a goal of 80 poses, until its diagnosis starts
    ros_client.py samples-named-twice ROBOT   Estimate requests whose samples name joint1 twice, then once
    ros_client.py longer-arm-samples N         N samples of 7 joints on /samples, then Estimate with use_accumulated
    ros_client.py set-param NODE NAME JSON [NODE NAME JSON ...]   set each parameter in turn to a JSON
                                               value (its type: int, float, ...) through the node's
                                               set_parameters service, then get it back; a list of results
    ros_client.py parameters-of NODE          every parameter of NODE with its value, as `ros2 param dump` gets them
    ros_client.py stream ROBOT LAYOUT N [WAIT]  N exact still poses on joint_states + spots (an estimator with
                                               input stream); LAYOUT: 'robot' (joint1..jointN in order),
                                               'reversed' (the same readings, names in reverse order) or
                                               'gripper' (robot order and one more joint); then up to WAIT s
                                               (10) for the estimator to have taken the N
    ros_client.py stream-replay ROBOT N RATE [SUBS] [DEPTH]  N exact still frames as a live stream has them (5
                                               joint_states at 50 Hz per spots frame at 10 Hz), played RATE times
                                               faster, once each topic has SUBS subscriptions (default 1), from
                                               publishers of history DEPTH (default 100)
"""

from __future__ import annotations

import json
import math
import sys
import threading
import time

import numpy as np
import rclpy
from rclpy.duration import Duration
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from laser_calib_interfaces.msg import DhParameters, Sample, Spot
from laser_calib_interfaces.srv import Estimate
from std_srvs.srv import Trigger

TIMEOUT = 60.0


def latched() -> QoSProfile:
    return QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def params(count: int, topic: str, timeout: float = TIMEOUT) -> dict:
    node = rclpy.create_node("test_params")
    latest = []
    node.create_subscription(DhParameters, topic, latest.append, latched())
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
        if latest and latest[-1].sample_count >= count:
            m = latest[-1]
            return {"sample_count": m.sample_count, "method": m.method, "names": list(m.names),
                    "errors": list(m.errors), "std": list(m.std), "values": list(m.values),
                    "identifiable": list(m.identifiable), "robot_name": m.robot_name}
    raise SystemExit(f"no dh_parameters with sample_count >= {count} within {timeout} s "
                     f"(last: {latest[-1].sample_count if latest else 'none'})")


ATTEMPT = 15.0  # resend a request not answered by then (see call)


def markers() -> dict:
    from visualization_msgs.msg import MarkerArray
    node = rclpy.create_node("test_markers")
    got = []
    node.create_subscription(MarkerArray, "calibration_markers", got.append, latched())
    deadline = time.monotonic() + TIMEOUT
    while not got and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    if not got:
        raise SystemExit("no calibration_markers")
    return {f"{m.ns}/{m.id}": {"frame": m.header.frame_id, "points": len(m.points)} for m in got[-1].markers}


def move(goal: list[float], tolerance: float = 0.01) -> dict:
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
    node = rclpy.create_node("test_move")
    states = []
    node.create_subscription(JointState, "joint_states", states.append, 50)
    pub = node.create_publisher(JointTrajectory, "joint_trajectory", 10)
    deadline = time.monotonic() + TIMEOUT
    while (not states or pub.get_subscription_count() == 0) and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    if not states:
        raise SystemExit("no joint_states")
    first = list(states[-1].position)
    traj = JointTrajectory()
    traj.joint_names = list(states[-1].name)
    traj.points = [JointTrajectoryPoint(positions=[float(v) for v in goal])]
    pub.publish(traj)
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
        q = np.array(states[-1].position)
        if np.all(np.abs(q - goal) < tolerance) and np.all(np.abs(states[-1].velocity) < 1e-3):
            return {"first": first, "reached": q.tolist(), "names": list(states[-1].name)}
    raise SystemExit(f"goal not reached: {list(states[-1].position)}")


def call(node: Node, client, request, timeout: float = TIMEOUT, attempt: float = ATTEMPT):
    """Call and wait. A request sent right after discovery can lose its answer
    (the server may not have matched this client's response reader yet, a known
    DDS race), so an unanswered request is sent again after ATTEMPT seconds."""
    if not client.wait_for_service(timeout_sec=timeout):
        raise SystemExit(f"service {client.srv_name} not available")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        future = client.call_async(request)
        rclpy.spin_until_future_complete(node, future, timeout_sec=attempt)
        if future.done():
            return future.result()
        client.remove_pending_request(future)
    raise SystemExit(f"service {client.srv_name} did not answer")


def response_dict(r) -> dict:
    return {"success": r.success, "message": r.message, "errors": list(r.parameters.errors),
            "values": list(r.parameters.values), "std": list(r.parameters.std),
            "identifiable": list(r.parameters.identifiable), "sample_count": r.parameters.sample_count,
            "iterations": r.parameters.iterations,
            "before_mean": np.asarray(r.before.mean).tolist(), "after_mean": np.asarray(r.after.mean).tolist(),
            "after_max": np.asarray(r.after.max).tolist(), "after_count": np.asarray(r.after.count).tolist(), "report": r.report_markdown, "result_json": r.result_json,
            "diagnosis_json": r.diagnosis_json}


def reset() -> dict:
    node = rclpy.create_node("test_reset")
    r = call(node, node.create_client(Trigger, "estimator/reset"), Trigger.Request())
    return {"success": r.success, "message": r.message}


def estimate_csv(path: str, output_dir: str = "", diagnose: bool = False) -> dict:
    from laser_calib.io.samples import load_samples
    samples = load_samples(path)
    node = rclpy.create_node("test_estimate")
    request = Estimate.Request()
    request.samples = [sample(int(samples.pose[k]), samples.q[k], samples.spots[k]) for k in range(len(samples))]
    request.method = "lm"
    request.output_dir = output_dir
    request.diagnose = diagnose
    r = call(node, node.create_client(Estimate, "estimator/estimate"), request)
    return dict(response_dict(r), names=list(r.parameters.names), calibrated_robot_yaml=r.calibrated_robot_yaml)


def estimate_joint_sigma(path: str, sigmas: list[float]) -> list[dict]:
    from laser_calib.io.samples import load_samples
    samples = load_samples(path)
    node = rclpy.create_node("test_estimate_joint_sigma")
    client = node.create_client(Estimate, "estimator/estimate")
    out = []
    for sigma in sigmas:
        request = Estimate.Request(method="lm", joint_sigma=sigma)
        request.samples = [sample(int(samples.pose[k]), samples.q[k], samples.spots[k]) for k in range(len(samples))]
        r = call(node, client, request)
        result = json.loads(r.result_json) if r.result_json else {}
        out.append({"success": r.success, "message": r.message} | {
            key: result.get(key) for key in ("spot_sigma_estimated", "joint_sigma_rad", "joint_sigma_estimated")})
    return out


def estimate_accumulated() -> dict:
    node = rclpy.create_node("test_estimate")
    request = Estimate.Request()
    request.use_accumulated = True
    request.method = "lm"
    return response_dict(call(node, node.create_client(Estimate, "estimator/estimate"), request))


def calibrate(diagnose: bool, cancel: bool) -> dict:
    """A Calibrate goal on the accumulated samples; with cancel, canceled as soon as accepted
    (the server stops the estimate). The final status, feedback stages, result."""
    from action_msgs.msg import GoalStatus
    from rclpy.action import ActionClient
    from laser_calib_interfaces.action import Calibrate
    node = rclpy.create_node("test_calibrate")
    client = ActionClient(node, Calibrate, "estimator/calibrate")
    if not client.wait_for_server(timeout_sec=TIMEOUT):
        raise SystemExit("no action server estimator/calibrate")
    stages = []
    # The feedback topic read directly: rclpy's ActionClient drops a goal's feedback callback when its
    # result arrives, and feedback and result travel on separate DDS channels, so a 'done' published
    # just before the result but delivered after it never reached feedback_callback (loaded machine).
    feedback = node.create_subscription(Calibrate.Impl.FeedbackMessage, "estimator/calibrate/_action/feedback",
                                        lambda msg: stages.append(msg.feedback.stage), 10)
    deadline = time.monotonic() + TIMEOUT
    while feedback.get_publisher_count() == 0 and time.monotonic() < deadline:  # matched before the goal
        rclpy.spin_once(node, timeout_sec=0.05)
    # To be canceled, the goal runs the paper's EKF (hundreds of iterations, against LM's few
    # milliseconds on 10 poses), so the cancel sent on acceptance arrives while the estimate runs.
    method = "ekf" if cancel else "lm"
    sent = client.send_goal_async(Calibrate.Goal(use_accumulated=True, method=method, diagnose=diagnose))
    rclpy.spin_until_future_complete(node, sent, timeout_sec=TIMEOUT)
    handle = sent.result()
    if handle is None or not handle.accepted:
        raise SystemExit("goal not accepted")
    if cancel:
        rclpy.spin_until_future_complete(node, handle.cancel_goal_async(), timeout_sec=TIMEOUT)
    done = handle.get_result_async()
    rclpy.spin_until_future_complete(node, done, timeout_sec=5 * TIMEOUT)
    if not done.done():
        raise SystemExit("no result")
    names = {GoalStatus.STATUS_SUCCEEDED: "succeeded", GoalStatus.STATUS_CANCELED: "canceled",
             GoalStatus.STATUS_ABORTED: "aborted"}
    result = done.result()
    # the 'done' feedback, published just before the result, may arrive after it (seconds later on a
    # loaded machine)
    deadline = time.monotonic() + TIMEOUT
    while result.status == GoalStatus.STATUS_SUCCEEDED and "done" not in stages and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.05)
    for _ in range(10):  # any later feedback would show here: the test checks there is none
        rclpy.spin_once(node, timeout_sec=0.05)
    return {"status": names.get(result.status, str(result.status)), "stages": stages,
            "success": result.result.success, "message": result.result.message,
            "diagnosis_json": result.result.diagnosis_json, "sample_count": result.result.parameters.sample_count}


def calibrate_until_diagnosis(robot_path: str) -> dict:
    """A Calibrate goal with 80 simulated poses and the diagnosis; returns as soon as the
    'diagnosis' stage starts (it runs for seconds: the test stops the estimator in it)."""
    from rclpy.action import ActionClient
    from laser_calib.model.robot_file import load_robot
    from laser_calib.sim.simulation import NoiseSpec, measure, sample_poses, true_errors
    from laser_calib_interfaces.action import Calibrate
    robot = load_robot(robot_path)
    rng = np.random.default_rng(5)
    true = robot.with_errors(true_errors(robot))
    measured, _ = measure(true, sample_poses([robot, true], 80, rng, "whole"), rng, NoiseSpec())
    node = rclpy.create_node("test_calibrate_stopped")
    client = ActionClient(node, Calibrate, "estimator/calibrate")
    if not client.wait_for_server(timeout_sec=TIMEOUT):
        raise SystemExit("no action server estimator/calibrate")
    stages = []
    goal = Calibrate.Goal(samples=[sample(k, measured.q[k], measured.spots[k]) for k in range(len(measured))],
                          method="lm", diagnose=True)
    client.send_goal_async(goal, feedback_callback=lambda msg: stages.append(msg.feedback.stage))
    deadline = time.monotonic() + 5 * TIMEOUT
    while "diagnosis" not in stages:
        if time.monotonic() > deadline:
            raise SystemExit(f"no diagnosis stage (feedback: {stages})")
        rclpy.spin_once(node, timeout_sec=0.05)
    return {"stages": stages}


def sample(pose: int, q, spots) -> Sample:
    msg = Sample()
    msg.header.stamp.sec = 1000 + pose
    msg.header.frame_id = "screen"
    msg.pose = pose
    msg.joint_positions = [float(v) for v in q]
    msg.spots = [Spot(y=float(s[0]), z=float(s[1]), seen=bool(np.isfinite(s).all())) if np.isfinite(s).all()
                 else Spot(y=math.nan, z=math.nan, seen=False) for s in spots]
    return msg


def bad_and_concurrent(robot_path: str) -> dict:
    from laser_calib.model.robot_file import load_robot
    from laser_calib.sim.simulation import NoiseSpec, measure, sample_poses, true_errors
    robot = load_robot(robot_path)
    rng = np.random.default_rng(3)
    true = robot.with_errors(true_errors(robot))
    q = sample_poses([robot, true], 30, rng, "whole")
    measured, _ = measure(true, q, rng, NoiseSpec())
    good = [sample(k, measured.q[k], measured.spots[k]) for k in range(len(measured))]

    def request(samples, **fields):
        r = Estimate.Request()
        r.samples = samples
        r.method = fields.pop("method", "lm")
        for key, value in fields.items():
            setattr(r, key, value)
        return r

    wrong_count = [sample(0, measured.q[0][:-1], measured.spots[0])] + good[1:]
    nan_joint = [sample(k, measured.q[k], measured.spots[k]) for k in range(len(measured))]
    nan_joint[4].joint_positions[2] = math.nan
    nan_spot = [sample(k, measured.q[k], measured.spots[k]) for k in range(len(measured))]
    nan_spot[2].spots[0].y = math.nan  # seen, but not finite
    held_out, _ = measure(true, sample_poses([robot, true], 5, np.random.default_rng(4), "whole"), rng, NoiseSpec())
    tests = [sample(100 + k, held_out.q[k], held_out.spots[k]) for k in range(len(held_out))]
    nan_test = [sample(100 + k, held_out.q[k], held_out.spots[k]) for k in range(len(held_out))]
    nan_test[1].joint_positions[0] = math.nan
    unseen_test = [sample(100 + k, held_out.q[k], np.full((2, 2), np.nan)) for k in range(len(held_out))]
    cases = {
        "empty": request([]),
        "wrong_joint_count": request(wrong_count),
        "nan_joint": request(nan_joint),
        "nan_spot": request(nan_spot),
        "bad_method": request(good, method="gauss"),
        "bad_method_nothing_accumulated": request([], method="gauss", use_accumulated=True),
        "samples_and_accumulated": request(good, use_accumulated=True),
        "negative_sigma": request(good, spot_sigma=-1.0),
        "too_few": request(good[:2]),
        "nan_test_joint": request(good, test_samples=nan_test),
        "unseen_test": request(good, test_samples=unseen_test),
        "tested": request(good, test_samples=tests),
        "good_lm_1": request(good),
        "good_lm_2": request(good),
        "good_ekf": request(good, method="ekf", spot_sigma=0.00115),
        "good_lm_3": request(good, diagnose=True),
    }
    nodes, futures = {}, {}
    # Every client's response reader gets every answer of the service (Fast DDS: they are told apart
    # when taken); under the default services profile, KEEP_LAST 10, the 16 answers of this burst
    # pushed an early one out before its client took it ('empty' unanswered, about half the runs
    # beside another test). What is tested is the server: each client keeps all it is sent.
    answers_qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)
    for name in cases:
        node = rclpy.create_node(f"client_{name}")
        client = node.create_client(Estimate, "estimator/estimate", qos_profile=answers_qos)
        # warm-up: an instantly refused request, until this client gets answers
        assert not call(node, client, request([]), attempt=2.0).success
        nodes[name] = (node, client)
    executor = MultiThreadedExecutor(num_threads=len(cases))
    for node, _ in nodes.values():  # after the warm-up: a node is in one executor at a time
        executor.add_node(node)
    for name, (node, client) in nodes.items():  # all in flight at once
        futures[name] = client.call_async(cases[name])
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    # No resend: each client had an answer in its warm-up, so a request unanswered here was lost
    # by the server (its request queue once held 10 and dropped the oldest); on a loaded machine
    # the 14 (one a diagnosis) take up to a minute.
    deadline = time.monotonic() + 120
    while not all(f.done() for f in futures.values()):
        if time.monotonic() > deadline:
            unanswered = [name for name, future in futures.items() if not future.done()]
            raise SystemExit(f"not answered in 120 s: {', '.join(unanswered)}")
        time.sleep(0.05)
    out = {name: response_dict(f.result()) for name, f in futures.items()}
    # the node still serves afterwards
    node, client = nodes["good_lm_1"]
    after = client.call_async(cases["good_lm_1"])
    while not after.done():
        time.sleep(0.05)
    out["after_all"] = response_dict(after.result())
    # the spin thread joined and the nodes destroyed before rclpy shuts down: a daemon thread
    # still in the executor's wait at interpreter exit aborted this client (std::terminate)
    executor.shutdown()
    spin.join(timeout=10)
    for node, _ in nodes.values():
        node.destroy_node()
    for name in out:
        if isinstance(out[name], dict):
            out[name].pop("report", None)
    return out


def samples_by_name(robot_path: str) -> dict:
    """Estimate requests of one noisy set, its samples' joint_positions in the robot's order with
    and without joint_names, and in reversed order with their names; then two mislabelled sets."""
    from laser_calib.model.robot_file import load_robot
    from laser_calib.sim.simulation import NoiseSpec, measure, sample_poses, true_errors
    robot = load_robot(robot_path)
    rng = np.random.default_rng(5)
    true = robot.with_errors(true_errors(robot))
    q = sample_poses([robot, true], 30, rng, "whole")
    measured, _ = measure(true, q, rng, NoiseSpec())
    names = [f"joint{i + 1}" for i in range(robot.n_joints)]

    def samples(order, labels):
        msgs = [sample(k, measured.q[k][order], measured.spots[k]) for k in range(len(measured))]
        for msg in msgs:
            msg.joint_names = labels
        return msgs

    forward, backward = list(range(robot.n_joints)), list(reversed(range(robot.n_joints)))
    cases = {"unnamed": samples(forward, []), "named": samples(forward, names),
             "reversed": samples(backward, [names[i] for i in backward]),
             "one_unknown": samples(forward, names[:-1] + ["gripper"]),
             "count_mismatch": samples(forward, names[:-1])}
    node = rclpy.create_node("test_samples_by_name")
    client = node.create_client(Estimate, "estimator/estimate")
    out = {}
    for name, msgs in cases.items():
        request = Estimate.Request()
        request.samples, request.method = msgs, "lm"
        out[name] = response_dict(call(node, client, request))
        out[name].pop("report", None)
    node.destroy_node()
    return out


def samples_named_twice(robot_path: str) -> dict:
    """Estimate requests whose samples name joint1 twice, the other reading 0.01 rad off (last, then
    first), and the same samples named once; an Estimate answer for each."""
    from laser_calib.model.robot_file import load_robot
    from laser_calib.sim.simulation import NoiseSpec, measure, sample_poses, true_errors
    robot = load_robot(robot_path)
    rng = np.random.default_rng(5)
    true = robot.with_errors(true_errors(robot))
    measured, _ = measure(true, sample_poses([robot, true], 30, rng, "whole"), rng, NoiseSpec())
    names = [f"joint{i + 1}" for i in range(robot.n_joints)]

    def samples(case):
        msgs = []
        for k in range(len(measured)):
            q = [float(v) for v in measured.q[k]]
            msg = sample(k, q, measured.spots[k])
            msg.joint_names, msg.joint_positions = {
                "once": (names, q),
                "twice_last": (names + ["joint1"], q + [q[0] + 0.01]),
                "twice_first": (["joint1"] + names, [q[0] + 0.01] + q)}[case]
            msgs.append(msg)
        return msgs

    node = rclpy.create_node("test_samples_named_twice")
    client = node.create_client(Estimate, "estimator/estimate")
    out = {}
    for case in ("twice_last", "twice_first", "once"):
        request = Estimate.Request()
        request.samples, request.method = samples(case), "lm"
        out[case] = response_dict(call(node, client, request))
        out[case].pop("report", None)
    node.destroy_node()
    return out


def longer_arm_samples(count: int) -> dict:
    """``count`` samples of a 7-joint arm published on /samples as the sequencer publishes them (a bag
    of another robot replayed), then an Estimate with use_accumulated: its answer."""
    from laser_calib_nodes.common import SAMPLES_QOS  # the sequencer's, as a replay publishes with
    node = rclpy.create_node("test_longer_arm_samples")
    publisher = node.create_publisher(Sample, "samples", SAMPLES_QOS)
    deadline = time.monotonic() + TIMEOUT
    while publisher.get_subscription_count() < 2 and time.monotonic() < deadline:  # the estimator's two
        rclpy.spin_once(node, timeout_sec=0.05)
    for k in range(count):
        msg = sample(k, [0.1 * (j + 1) for j in range(7)], np.array([[0.01, 0.02], [0.03, 0.04]]))
        msg.joint_names = [f"joint{j + 1}" for j in range(7)]
        publisher.publish(msg)
    time.sleep(1.0)
    request = Estimate.Request()
    request.use_accumulated, request.method = True, "lm"
    out = response_dict(call(node, node.create_client(Estimate, "estimator/estimate"), request))
    node.destroy_node()
    return out


def set_params(settings: list[tuple[str, str, object]]) -> list[dict]:
    """For each (node, name, value) in turn, as `ros2 param set NODE NAME VALUE` does (an integer
    stays an integer), then as `ros2 param get`: one process for them all (each costs ~2 s)."""
    from rcl_interfaces.srv import GetParameters, SetParameters
    from rclpy.parameter import Parameter
    node = rclpy.create_node("test_set_param")
    clients = {}  # node name -> its (set, get) clients, each discovered once
    out = []
    for node_name, name, value in settings:
        if node_name not in clients:
            clients[node_name] = (node.create_client(SetParameters, f"{node_name}/set_parameters"),
                                  node.create_client(GetParameters, f"{node_name}/get_parameters"))
        set_client, get_client = clients[node_name]
        request = SetParameters.Request(parameters=[Parameter(name, value=value).to_parameter_msg()])
        result = call(node, set_client, request).results[0]
        got = call(node, get_client, GetParameters.Request(names=[name])).values[0]
        stored = Parameter.from_parameter_msg(type("P", (), {"name": name, "value": got})())
        out.append({"successful": result.successful, "reason": result.reason, "type": stored.type_.name,
                    "value": stored.value})
    return out


def parameters_of(node_name: str) -> dict:
    """As `ros2 param dump` does: list_parameters, then get_parameters of all the names at once."""
    from rcl_interfaces.srv import GetParameters, ListParameters
    from rclpy.parameter import parameter_value_to_python
    node = rclpy.create_node("test_parameters_of")
    names = sorted(call(node, node.create_client(ListParameters, f"{node_name}/list_parameters"),
                        ListParameters.Request()).result.names)
    values = call(node, node.create_client(GetParameters, f"{node_name}/get_parameters"),
                  GetParameters.Request(names=names)).values
    return {"names": names, "values": {name: parameter_value_to_python(v) for name, v in zip(names, values)}}


def _stream_publishers(robot_path: str, count: int, name: str, depth: int, subscribers: int = 1):
    """The robot, ``count`` poses q (count,N) and their exact spots (count,2,2) (nominal model), a
    node ``name`` with the dh_parameters it receives (a list), reliable joint_states and spots
    publishers of history ``depth`` matched to ``subscribers`` subscriptions each, and the deadline
    of the whole call."""
    from sensor_msgs.msg import JointState
    from laser_calib_interfaces.msg import SpotPair
    from laser_calib.model.kinematics import predict
    from laser_calib.model.robot_file import load_robot
    from laser_calib.sim.simulation import sample_poses
    robot = load_robot(robot_path)
    q = sample_poses([robot], count, np.random.default_rng(3))
    node = rclpy.create_node(name)
    got = []
    node.create_subscription(DhParameters, "dh_parameters", got.append, latched())
    qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
    states = node.create_publisher(JointState, "joint_states", qos)
    pairs = node.create_publisher(SpotPair, "spots", qos)
    deadline = time.monotonic() + TIMEOUT
    while (states.get_subscription_count() < subscribers or pairs.get_subscription_count() < subscribers) \
            and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
    return robot, q, predict(robot, q).spots, node, got, states, pairs, deadline


def stream(robot_path: str, layout: str, count: int, wait: float = 10.0) -> dict:
    """Publish ``count`` still poses, each as a joint_states message and a spots message of one stamp,
    with the robot's exact spots (nominal model), in the joint layout asked; then the latest
    dh_parameters (the online EKF: errors ~0 when every reading went to its joint), once it counts
    them all or ``wait`` s have passed (an estimator that refuses the poses never counts them)."""
    from sensor_msgs.msg import JointState
    from laser_calib_interfaces.msg import SpotPair
    robot, q, spots, node, got, states, pairs, deadline = _stream_publishers(robot_path, count, "test_stream", 50)
    n = robot.n_joints
    order = list(reversed(range(n))) if layout == "reversed" else list(range(n))
    extra = ["gripper"] if layout == "gripper" else []
    for k in range(count):
        stamp = node.get_clock().now().to_msg()
        state = JointState(name=[f"joint{i + 1}" for i in order] + extra,
                           position=[float(q[k, i]) for i in order] + [0.0] * len(extra),
                           velocity=[0.0] * (n + len(extra)))
        state.header.stamp = stamp
        pair = SpotPair(spots=[Spot(y=float(spots[k, j, 0]), z=float(spots[k, j, 1]), seen=True) for j in range(2)])
        pair.header.stamp, pair.header.frame_id = stamp, "screen"
        states.publish(state)
        pairs.publish(pair)
        until = time.monotonic() + 0.1
        while time.monotonic() < until:
            rclpy.spin_once(node, timeout_sec=0.02)
    # the arm moves on: a moving pair ends the last pose (the estimator averages a pose's still frames)
    stamp = node.get_clock().now().to_msg()
    state = JointState(name=[f"joint{i + 1}" for i in order] + extra, position=[float(q[-1, i]) for i in order]
                       + [0.0] * len(extra), velocity=[1.0] * (n + len(extra)))
    state.header.stamp = stamp
    pair = SpotPair(spots=[Spot(y=math.nan, z=math.nan, seen=False) for _ in range(2)])
    pair.header.stamp, pair.header.frame_id = stamp, "screen"
    states.publish(state)
    pairs.publish(pair)
    until = time.monotonic() + wait
    while time.monotonic() < until and not (got and got[-1].sample_count >= count):
        rclpy.spin_once(node, timeout_sec=0.1)
    last = got[-1] if got else None
    return {"sample_count": last.sample_count if last else 0,
            "largest_error": float(np.nanmax(np.abs(last.errors))) if last else None}


def stream_replay(robot_path: str, count: int, rate: float, subscribers: int = 1, depth: int = 100) -> dict:
    """As a replay of a recorded stream at --rate RATE (its QoS: reliable, keep last ``depth``): per still
    frame 5 joint_states 20 ms apart and one spots message with the stamp of the third; then the
    estimator's latest sample_count once it has stopped changing for 3 s."""
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import JointState
    from laser_calib_interfaces.msg import SpotPair
    robot, q, spots, node, got, states, pairs, deadline = _stream_publishers(robot_path, count, "test_stream_replay",
                                                                             depth, subscribers)
    n = robot.n_joints
    start = time.monotonic()
    for k in range(5 * count):
        t = 1000.0 + 0.02 * k
        while time.monotonic() < start + 0.02 * k / rate:
            time.sleep(0.0005)
        stamp = Time(sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
        state = JointState(name=[f"joint{i + 1}" for i in range(n)], position=[float(v) for v in q[k // 5]],
                           velocity=[0.0] * n)
        state.header.stamp = stamp
        states.publish(state)
        if k % 5 == 2:
            pair = SpotPair(spots=[Spot(y=float(spots[k // 5, j, 0]), z=float(spots[k // 5, j, 1]), seen=True)
                                   for j in range(2)])
            pair.header.stamp, pair.header.frame_id = stamp, "screen"
            pairs.publish(pair)
    # as replay does: a publisher that exits with messages unacknowledged loses them (a keep-all
    # reader's history is bounded by its resource limits; the rest wait in this history while the
    # subscriber's executor lags behind a segment roll-over's fsync)
    for publisher in (states, pairs):
        publisher.wait_for_all_acked(Duration(seconds=max(deadline - time.monotonic(), 0.0)))
    last, quiet_since = None, time.monotonic()
    while time.monotonic() - quiet_since < 3.0 and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
        if got and got[-1].sample_count != last:
            last, quiet_since = got[-1].sample_count, time.monotonic()
    return {"sample_count": last or 0}


def main() -> int:
    rclpy.init()
    try:
        command = sys.argv[1]
        if command == "params":
            result = params(int(sys.argv[2]), sys.argv[3] if len(sys.argv) > 3 else "dh_parameters")
        elif command == "move":
            result = move([float(v) for v in sys.argv[2:]])
        elif command == "markers":
            result = markers()
        elif command == "reset":
            result = reset()
        elif command == "estimate-csv":
            result = estimate_csv(*sys.argv[2:4])
        elif command == "estimate-csv-diagnose":
            result = estimate_csv(sys.argv[2], diagnose=True)
        elif command == "estimate-joint-sigma":
            result = estimate_joint_sigma(sys.argv[2], [float(v) for v in sys.argv[3:]])
        elif command == "estimate-accumulated":
            result = estimate_accumulated()
        elif command == "calibrate":
            result = calibrate("diagnose" in sys.argv[2:], "cancel" in sys.argv[2:])
        elif command == "calibrate-until-diagnosis":
            result = calibrate_until_diagnosis(sys.argv[2])
        elif command == "set-param":
            args = sys.argv[2:]
            result = set_params([(args[k], args[k + 1], json.loads(args[k + 2])) for k in range(0, len(args), 3)])
        elif command == "parameters-of":
            result = parameters_of(sys.argv[2])
        elif command == "stream":
            result = stream(sys.argv[2], sys.argv[3], int(sys.argv[4]), *map(float, sys.argv[5:6]))
        elif command == "stream-replay":
            result = stream_replay(sys.argv[2], int(sys.argv[3]), float(sys.argv[4]), *map(int, sys.argv[5:7]))
        elif command == "samples-named-twice":
            result = samples_named_twice(sys.argv[2])
        elif command == "longer-arm-samples":
            result = longer_arm_samples(int(sys.argv[2]))
        elif command == "samples-by-name":
            result = samples_by_name(sys.argv[2])
        elif command == "bad-and-concurrent":
            result = bad_and_concurrent(sys.argv[2])
        else:
            raise SystemExit(f"unknown command {command}")
        print(json.dumps(result))
        return 0
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
