"""What every node shares: topic names, QoS profiles, the robot and compensator parameters,
message conversions and the main() wrapper (exit 0 on Ctrl-C, one line on bad input)."""

from __future__ import annotations

import math
import re
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import rclpy
from rclpy.executors import ExternalShutdownException, Executor, SingleThreadedExecutor
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException, ParameterException
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.node import Node
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions, install_signal_handlers
from sensor_msgs.msg import CameraInfo

from laser_calib.io.errors import InputError
from laser_calib.io.samples import check_lasers
from laser_calib.model.robot import Robot
from laser_calib.model.robot_file import load_robot

from laser_calib.io import bag
from laser_calib_nodes.parameters import NodeError, declare, refuse_clock_change
from laser_calib_nodes.shutdown import ExitWatchdog, StopFlag, die_with_parent, interruptible

# Topic and service names (relative: a namespace or a remap moves them).
JOINT_STATES = "joint_states"
JOINT_TRAJECTORY = "joint_trajectory"
TRUE_SPOTS = "sim/true_spots"          # private to the simulation: true spots for camera_sim
IMAGE = "camera/image_raw"
CAMERA_INFO = "camera/camera_info"
SPOTS = "spots"                        # laser_calib_interfaces/SpotPair, every frame
LASER_SPOT = ("laser1/spot", "laser2/spot")  # geometry_msgs/PointStamped, only when seen
SAMPLES = "samples"
TEST_SAMPLES = "test_samples"           # the held-out samples: never on samples, so no estimator fits them
PROGRESS = "session/progress"
DH_PARAMETERS = "dh_parameters"
MARKERS = "calibration_markers"
# The estimator's private services and action (~/estimate is /estimator/estimate for a node
# named estimator); ESTIMATE_SERVICE is the name another node calls.
ESTIMATE_SERVICE = "estimator/estimate"
PRIVATE_ESTIMATE = "~/estimate"
PRIVATE_RESET = "~/reset"
PRIVATE_CALIBRATE = "~/calibrate"
SCREEN_FRAME = "screen"

# QoS. Results and session state are transient-local (a late subscriber gets the last one).
STREAM_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
                        history=HistoryPolicy.KEEP_LAST)
# Every message kept until taken, for what must not be pushed out while a node is busy:
# - the estimator's 'stream' input (joint_states, spots). Keep-last 50 dropped the oldest while its
#   callbacks lagged (a replay at --rate 10: 180 of 200 still frames lost, unsaid, the spots finding
#   no joint state to pair with);
# - service requests, waiting in the server's request reader while an estimate runs. The default
#   services profile keeps the last 10, so the 11th request in flight pushed out the oldest one
#   unanswered (its client waited for ever).
KEEP_ALL_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
                          history=HistoryPolicy.KEEP_ALL)
COMMAND_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
# Images (4 MB) are reliable: best effort over Fast DDS loses most frames of this size.
IMAGE_QOS = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
# Samples from any publisher: a default-QoS one (volatile, e.g. `ros2 topic pub`) matches
# only a volatile subscription; the sequencer's history (transient local) only a
# transient-local one. The estimator subscribes with both and counts each sample once.
SAMPLES_INPUT_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                               durability=DurabilityPolicy.VOLATILE)
LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Every sample of a session is kept for late subscribers (an estimator started late).
SAMPLES_QOS = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)


def subscribe_camera(node: Node, msg_type, name: str, callback: Callable, depth: int, raw: bool = False) -> list:
    """Subscribe to a camera topic (image or CameraInfo) with every profile a driver may publish it
    with; a message two of them deliver reaches ``callback`` twice (the caller keeps one by its stamp):
    - best effort: the sensor-data QoS camera drivers publish with, which a reliable subscription
      never matches (a best-effort 4 MB frame also needs the driver's Fast DDS profile,
      config/fastdds_large_frames.xml);
    - reliable: camera_sim and drivers that publish reliable;
    - CameraInfo also transient local: a driver that latches it sends it once, maybe before this
      node started, and a volatile subscription never gets that one.
    ``depth`` frames kept per profile; the profiles a publisher does not match stay quiet. Returns the
    subscriptions."""
    quiet = SubscriptionEventCallbacks(incompatible_qos=lambda _: None)
    profiles = [QoSProfile(depth=depth, reliability=reliability)
                for reliability in (ReliabilityPolicy.BEST_EFFORT, ReliabilityPolicy.RELIABLE)]
    if msg_type is CameraInfo:
        profiles.append(LATCHED_QOS)
    return [node.create_subscription(msg_type, name, callback, profile, raw=raw, event_callbacks=quiet)
            for profile in profiles]


def bag_qos(profile: QoSProfile):
    """The rosbags description of an rclpy QoS profile (for the bag's metadata)."""
    return bag.qos(reliable=profile.reliability == ReliabilityPolicy.RELIABLE,
                   transient_local=profile.durability == DurabilityPolicy.TRANSIENT_LOCAL, depth=profile.depth)


ROBOT_HELP = ("Nominal robot model file (YAML, conventions.md; a URDF arm with its lasers: docs/urdf.md), e.g. "
              "the package's share/laser_calib_nodes/config/robots/humanoid_arm_7dof.yaml (a relative path is "
              "taken from the node's working directory).")
# robot_state_publisher's /robot_description: std_msgs/String, reliable, transient local, depth 1.
DESCRIPTION_QOS = LATCHED_QOS


@dataclass(frozen=True)
class RobotSource:
    """Where a node takes its robot from: the robot file, and the URDF text from
    ``topic`` when set (the file then names base, tip and the lasers, no urdf:)."""

    path: str
    topic: str
    timeout: float

    def load(self, node: Node, lasers: bool) -> tuple[Robot, str]:
        """The robot and a label of its source (for result.json); waits for the topic. ``lasers``:
        the node handles laser spots, and a robot file without lasers is refused (InputError)."""
        if not self.path:
            raise NodeError("parameter 'robot' is empty: give the robot model file (YAML)", 2)
        if not self.topic:
            robot, label = load_robot(self.path), self.path
        else:
            text, name = wait_for_description(node, self.topic, self.timeout)
            robot, label = load_robot(self.path, description=text), f"{self.path} with the URDF of {name}"
        if lasers:
            check_lasers(robot, f"parameter robot: {self.path}")
        return robot, label


def robot_source(node: Node) -> RobotSource:
    """Declare the parameters that say where the robot comes from."""
    path = declare(node, "robot", "", ROBOT_HELP)
    topic = declare(node, "robot_description_topic", "",
                    "Take the arm's URDF from this topic (std_msgs/String, reliable + transient local, as "
                    "robot_state_publisher publishes /robot_description); 'robot' then gives base, tip and the "
                    "lasers. Empty: the robot file alone.")
    timeout = declare(node, "robot_description_timeout", 30.0,
                      "Seconds to wait for the robot description on robot_description_topic before exiting.")
    if not (math.isfinite(timeout) and timeout > 0):
        raise NodeError(f"parameter robot_description_timeout: expected > 0 s, got {timeout}", 2)
    return RobotSource(path, topic, timeout)


def robot_param(node: Node, lasers: bool) -> tuple[Robot, str]:
    return robot_source(node).load(node, lasers)


def compensator_param(node: Node) -> tuple[Any, str | None]:
    """The 'compensator' parameter: a diagnosis's compensator.json, which the batch estimate
    applies (laser_calib.report.calibration), loaded, and its path; (None, None) for ''.
    A bad file: InputError (exit 2)."""
    path = declare(node, "compensator", "", "A diagnosis's compensator.json, applied by every batch estimate "
                                            "(made for the robot file's model, its effects); '' for none.")
    if not path:
        return None, None
    from laser_calib.diagnosis.compensator import load_compensator  # scikit-learn: only when asked for
    return load_compensator(path), path


def wait_for_description(node: Node, topic: str, timeout: float) -> tuple[str, str]:
    """The first URDF text on topic (its latched one) and the topic's resolved name;
    NodeError (exit 2) after timeout s. Spins only this subscription's node, before
    the node is given to its executor: run()'s, made before a stop signal could shut the
    context (one made here, on a context shut meanwhile, failed halfway: see run)."""
    from std_msgs.msg import String

    texts: list[str] = []
    subscription = node.create_subscription(String, topic, lambda msg: texts.append(msg.data), DESCRIPTION_QOS)
    name = subscription.topic_name
    node.get_logger().info(f"waiting up to {timeout:g} s for the robot description on {name} (std_msgs/String, "
                           "transient local, as robot_state_publisher publishes it)")
    executor = _executor or SingleThreadedExecutor()
    executor.add_node(node)
    deadline = time.monotonic() + timeout
    try:
        while not texts and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
    finally:
        executor.remove_node(node)
        if executor is not _executor:
            executor.shutdown()
        node.destroy_subscription(subscription)
    if not texts:
        raise NodeError(f"no robot description on {name} within {timeout:g} s: is robot_state_publisher running "
                        "(or set robot_description_topic:='' to use the robot file alone)?", 2)
    node.get_logger().info(f"robot description received on {name} ({len(texts[0])} characters)")
    return texts[0], name


def request_output_dir(output_dir: str) -> Path | None:
    """A request's output_dir (Estimate, Calibrate): None when empty; a relative one is refused
    (InputError), since the node would resolve it in its own working directory, which the
    caller, another process and perhaps another host, neither chose nor sees."""
    if not output_dir:
        return None
    if not Path(output_dir).is_absolute():
        raise InputError("output_dir", f"{output_dir!r} is relative; give an absolute path on a file "
                                                "system the estimator sees")
    return Path(output_dir)


def warn_undeclared(node: Node) -> None:
    """One WARN line naming the parameters given to the node (file, -p) that it does not declare:
    ROS drops them silently, so a misspelt key ran on the default (dynamixel.zero_tick left every
    servo's zero at 2048 ticks). rclpy keeps the overrides only privately, hence the attribute."""
    given = getattr(node, "_parameter_overrides", {})
    unknown = sorted(name for name in given if not node.has_parameter(name))
    if unknown:
        node.get_logger().warning(f"parameters given that {node.get_name()} does not take, ignored (misspelt, or "
                                  f"another node's?): {', '.join(unknown)}")


def log_warned(logger, warned: bool, message: str) -> None:
    """``message`` at WARN when ``warned`` (a summary holding an estimate's warnings), else INFO. Two call
    sites: rclpy pins the severity of each logging line, and one line logging at both raises
    'Logger severity cannot be changed between calls' (it took the estimator down at its second request)."""
    if warned:
        logger.warning(message)
    else:
        logger.info(message)


def stamp_seconds(stamp) -> float:
    return bag.stamp_seconds(stamp.sec, stamp.nanosec)


def now_ns(node: Node) -> int:
    return node.get_clock().now().nanoseconds


def spots_to_msg(spots: np.ndarray, seen: Sequence[bool]):
    from laser_calib_interfaces.msg import Spot
    out = []
    for j in range(2):
        if seen[j] and np.isfinite(spots[j]).all():
            out.append(Spot(y=float(spots[j][0]), z=float(spots[j][1]), seen=True))
        else:
            out.append(Spot(y=math.nan, z=math.nan, seen=False))
    return out


def spots_from_msg(spots) -> np.ndarray:
    """(2,2) array, NaN where a laser was not seen."""
    out = np.full((2, 2), np.nan)
    for j, spot in enumerate(spots):
        if spot.seen:
            out[j] = (spot.y, spot.z)
    return out


def rcl_error_line(exc: Exception) -> str:
    """rcl's message of an RCLError in one line, without its C source locations (', at /project/src/...:N'):
    --ros-args it cannot parse (a params file missing or not YAML, '-p name' without ':=')."""
    if isinstance(exc, rclpy_implementation.UnknownROSArgsError):  # its message is the list alone
        return (f"--ros-args: not ROS arguments: {exc} (a node's parameters: -p NAME:=VALUE or --params-file FILE; "
                "ros2 param describe lists them)")
    return re.sub(r"\s*(, at /\S+:\d+)+", "", " ".join(str(exc).split())).strip()


# What rclpy.init raises for --ros-args it cannot take: rcl's parse errors, and an argument rcl does not
# know ('--ros-args --help' was a traceback, exit 1).
ROS_ARGUMENT_ERRORS = (rclpy_implementation.RCLError, rclpy_implementation.UnknownROSArgsError)


_executor: Executor | None = None  # run()'s


def run(make_node: Callable[[], Node], args: Sequence[str] | None = None,
        make_executor: Callable[[], Executor] | None = None,
        until: Callable[[Node], bool] | None = None) -> int:
    """Initialise, spin (until ``until(node)`` when given), clean up in finally.

    Exit codes: 0 normal or Ctrl-C/SIGTERM; 2 bad input (one line, no
    traceback); a NodeError's code; 1 unexpected errors; the non-zero code a
    node's close() returns when the exit would otherwise be 0 (a fault found
    while cleaning up; an earlier fault keeps its own code, the cause).
    """
    global _executor
    given = list(sys.argv[1:] if args is None else args)
    if {"-h", "--help"} & set(given[:given.index("--ros-args")] if "--ros-args" in given else given):
        # rclpy takes no --help: the node started and stopped on its first missing parameter
        print(f"{sys.modules[make_node.__module__].__doc__.strip()}\n\nParameters: the package README "
              "(laser_calib_nodes), or `ros2 param describe` on the running node; set them after --ros-args "
              "(-p NAME:=VALUE, --params-file FILE).")
        return 0
    die_with_parent()
    watchdog = ExitWatchdog(Path(sys.argv[0]).name)
    # rclpy's signal handlers call the one installed before them: this one notes the
    # signal, so that an error it causes inside rclpy (a KeyboardInterrupt while a large
    # message is converted surfaces as RuntimeError) is taken for the stop it is.
    stop = StopFlag()
    # A stop during rclpy.init is taken once it returns: raised inside it, the KeyboardInterrupt
    # would leave a context made but not kept, with no clean way down (seen as a traceback when a
    # session was stopped while its nodes started).
    initialising = True

    def on_signal(signum, frame):
        first = stop.note()
        watchdog.arm()
        # a second Ctrl-C must not break the cleanup; one inside rclpy's code is left to the context it shut
        if first and signum == signal.SIGINT and not initialising and interruptible(frame):
            raise KeyboardInterrupt

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    # rclpy's handlers, which shut the context on SIGINT and SIGTERM, are installed once the executor is
    # made: rclpy's Executor.__init__ on a context a stop had shut fails halfway, and the half-made
    # executor's __del__ printed a traceback ("AttributeError: ... no attribute '_sigint_gc'", camera_sim
    # stopped right after its start).
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except ROS_ARGUMENT_ERRORS as exc:  # --ros-args rcl cannot read: one line, as every bad input
        print(f"error: {rcl_error_line(exc)}", file=sys.stderr, flush=True)
        return 2
    executor = _executor = make_executor() if make_executor else SingleThreadedExecutor()
    watchdog.watch_executor(executor)
    install_signal_handlers(SignalHandlerOptions.ALL)
    initialising = False
    node = None
    code = 0
    try:
        try:
            if stop.stopped:
                raise KeyboardInterrupt
            node = make_node()
            refuse_clock_change(node)
            warn_undeclared(node)
            executor.add_node(node)
            if until is None:
                executor.spin()
            else:
                while rclpy.ok() and not until(node):
                    executor.spin_once(timeout_sec=0.1)
            code = getattr(node, "exit_code", 0)
        except (KeyboardInterrupt, ExternalShutdownException):
            code = 0
        except InputError as exc:
            print(f"error: {exc}", file=sys.stderr, flush=True)
            code = 2
        except NodeError as exc:
            print(f"error: {exc}", file=sys.stderr, flush=True)
            code = exc.code
        except (ParameterException, InvalidParameterTypeException, InvalidParameterValueException) as exc:
            print(f"error: parameter: {exc}", file=sys.stderr, flush=True)
            code = 2
        except OSError as exc:  # a file the parameters name cannot be read or written
            print(f"error: {exc}", file=sys.stderr, flush=True)
            code = 2
        except Exception:
            if rclpy.ok() and not stop.stopped:
                code = 1
                raise
            code = 0  # Ctrl-C/SIGTERM under a running callback (a publish, a message being taken)
    except KeyboardInterrupt:
        # The stop signal's own handler ran while an error it caused was handled: rclpy's C handler
        # shuts the context at once (a node being built then fails, 'context is invalid'), ours runs
        # at the next Python line, inside the except clause (seen as a traceback under run-session).
        code = 0
    finally:
        # A terminal's Ctrl-C reaches a node under `ros2 launch` twice (from the terminal and from
        # launch); once shutting down, a second one must not break the cleanup with a traceback.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if not rclpy.ok():
            # rclpy's signal handler shut the context but not rcl's logging: each line logged from
            # here would still go to the node's /rosout publisher, which then fails ('Failed to
            # publish log message to rosout: publisher's context is invalid'). The cleanup's lines
            # go to the console (launch's log) only, as they do after rclpy's own shutdown.
            rclpy_implementation.rclpy_logging_fini()
        watchdog.cleanup_started()
        if node is not None:
            close = getattr(node, "close", None)
            try:
                closed = close() if close is not None else None
                if closed and not code:  # a fault the cleanup found (arm_driver: torque off not confirmed)
                    code = closed
            except Exception as exc:  # cleanup must not hide the exit code
                print(f"warning: cleanup of {node.get_name()} failed: {exc}", file=sys.stderr, flush=True)
        watchdog.cleanup_done(code)
        if node is not None:
            node.destroy_node()
        watchdog.watch_executor(None)
        executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown()
    return code
