"""The node graphs of a calibration session, defined once.

session.launch.py and hardware.launch.py build their launch actions from
session_nodes / hardware_nodes, and scripts/run-session starts the same
processes without the launch library (``python -m laser_calib_nodes.graph``),
so that the main job runs on a machine without ros2cli and the two cannot
drift. Either way the starter first takes the session folder's lock
(laser_calib.session.lock), every node dies with its starter
(die_with_parent), and a node that exits ends the session within seconds.

    python -m laser_calib_nodes.graph output_dir:=DIR [robot:=FILE] [robot_description_topic:=/robot_description]
        [poses:=N] ... [-- SEQUENCER ROS ARGS]

takes the launch file's arguments (SESSION_ARGS) in its ``name:=value`` form.
ROS-free: nothing here imports rclpy (launch only inside launch_actions).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from ament_index_python.packages import get_package_prefix, get_package_share_directory

from laser_calib.estimation.estimate import METHODS
from laser_calib.io.errors import InputError
from laser_calib.model.robot_file import load_robot
from laser_calib.session.folder import PLAN_DEFAULTS, SessionDir, outermost_missing, refuse_finished
from laser_calib.session.lock import SessionLock
from laser_calib.session.poses import check_plan
from laser_calib_nodes.arguments import (arm_section, existing_files, integer, loadable_robot, namespace,
                                         noise_params, positive_number, refuse_ignored_arguments)
from laser_calib_nodes.shutdown import GRACE, StopFlag, die_with_parent

PACKAGE = "laser_calib_nodes"
# From SIGINT to SIGKILL (run-session), to SIGTERM (launch, then SIGKILL 5 s later) when stopping
# the nodes: after the nodes' own bound (shutdown.GRACE), so that a node's cleanup (its files) is
# never cut and a slow middleware teardown ends with the node's code and its warning, not with
# "process has died [exit code -9]" (launch's default escalates after 5 s).
STOP_SECONDS = GRACE + 5.0


def share(*parts: str) -> str:
    return os.path.join(get_package_share_directory(PACKAGE), *parts)


def middleware_env() -> dict:
    """The environment the nodes add: Fast DDS's participant profile for camera frames
    (config/fastdds_large_frames.xml: with the default 512 KB shared-memory segment most
    best-effort 4 MB frames are lost), unless a profile is already set or another RMW runs."""
    if os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE") or \
            os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp") != "rmw_fastrtps_cpp":
        return {}
    return {"FASTRTPS_DEFAULT_PROFILES_FILE": share("config", "fastdds_large_frames.xml")}


NAMESPACE_ARG = ("", "ROS namespace of the session's nodes and topics, e.g. rig2: one session per namespace on a "
                     "ROS domain (a resume in the session's own). Empty: none.")
DESCRIPTION_TOPIC_HELP = ("Take the arm's URDF from this topic (e.g. /robot_description of robot_state_publisher); "
                          "robot is then the file of base, tip and lasers (docs/urdf.md). Empty: robot alone.")
# name: (default, description); default None: required. The launch file's arguments.
SESSION_ARGS = {
    "output_dir": (None, "Session directory (created; a partial session is resumed)."),
    "robot": (share("config", "robots", "humanoid_arm_7dof.yaml"), "Nominal robot model file (YAML)."),
    "robot_description_topic": ("", DESCRIPTION_TOPIC_HELP),
    "poses": ("60", "Poses to generate."),
    "test_poses": ("0", "Held-out poses over the whole workspace, measured after the others, never fitted."),
    "span": ("whole", "'whole' or 'small'."),
    "seed": ("0", "Pose generator seed."),
    "method": ("lm", "Final estimate: 'lm' or 'ekf'."),
    "params": (share("config", "session.yaml"), "ROS parameter file of the nodes."),
    "speed": ("", "Simulated joint speed, rad/s (empty: the parameter file's)."),
    "spot_sigma": ("", "Spot noise, m, of the final estimate and the online EKF; 0: estimated (empty: the "
                       "parameter file's)."),
    "joint_sigma": ("", "Joint-reading noise, rad (at most 0.035), of the final estimate and the online EKF; -1: not "
                        "given, 0: none (empty: the parameter file's)."),
    "namespace": NAMESPACE_ARG,
}
HARDWARE_ARGS = {
    "output_dir": (None, "Session directory (created; a partial session is resumed)."),
    "robot": (None, "Nominal robot model file (YAML)."),
    "robot_description_topic": ("", DESCRIPTION_TOPIC_HELP),
    # Required: a default drove the example file's port, servo ids and zero ticks on whatever adapter
    # was there when the argument was left out (or misspelt, before arguments.refuse_ignored_arguments).
    "arm_params": (None, "arm_driver parameters of your arm (Dynamixel port, ids, ticks); the package's "
                         "config/dynamixel_arm.yaml is an example to copy and edit."),
    "calibration": (None, "Screen calibration file of the camera."),
    "image": ("/camera/image_raw", "Camera image topic (its CameraInfo: camera_info beside it, as image_transport "
                                   "has it)."),
    "poses_file": ("", "Pose list; empty: generate."),
    "poses": ("60", "Poses to generate."),
    "test_poses": SESSION_ARGS["test_poses"],
    "span": SESSION_ARGS["span"],
    "seed": SESSION_ARGS["seed"],
    "spot_sigma": SESSION_ARGS["spot_sigma"],
    "joint_sigma": SESSION_ARGS["joint_sigma"],
    "params": (share("config", "session.yaml"), "ROS parameter file of the other nodes."),
    "namespace": NAMESPACE_ARG,
}


@dataclass(frozen=True)
class NodeSpec:
    """One node process: its executable (= node name), parameter files, then parameter overrides;
    its namespace ('' for none; relative: inside an including launch file's)."""

    executable: str
    param_files: tuple[str, ...]
    params: dict = field(default_factory=dict)
    remaps: tuple[tuple[str, str], ...] = ()
    namespace: str = ""

    def command(self) -> list[str]:
        args = [os.path.join(get_package_prefix(PACKAGE), "lib", PACKAGE, self.executable), "--ros-args"]
        for path in self.param_files:
            args += ["--params-file", path]
        for name, value in self.params.items():
            args += ["-p", f"{name}:={value}"]
        for old, new in self.remaps + ((("__ns", "/" + self.namespace.lstrip("/")),) if self.namespace else ()):
            args += ["-r", f"{old}:={new}"]
        return args


def robot_params(values: dict) -> dict:
    """The parameters of every node that needs the robot (common.robot_source); the
    topic only when given (an empty `-p name:=` is no string to ROS)."""
    topic = values["robot_description_topic"]
    return {"robot": values["robot"], **({"robot_description_topic": topic} if topic else {})}


def session_nodes(values: dict) -> list[NodeSpec]:
    """The simulated session; the sequencer last (the session ends when it ends)."""
    existing_files(values, "params", "robot")
    loadable_robot(values)
    files = (values["params"],)
    robot = robot_params(values)
    arm = dict(robot, **{"sim.true_robot_out": os.path.join(values["output_dir"], "robot_true.yaml")})
    if values["speed"]:
        arm["sim.joint_speed"] = positive_number(values, "speed")
    if values["method"] not in METHODS:  # refused now, not after every pose is measured
        raise InputError("method", f"expected one of {', '.join(METHODS)}, got {values['method']!r}")
    estimator_noise, estimate_noise = noise_params(values)
    sequencer = dict(robot, output_dir=values["output_dir"], poses=integer(values, "poses"),
                     test_poses=integer(values, "test_poses"), span=values["span"], seed=integer(values, "seed"),
                     **{"estimate.method": values["method"]}, **estimate_noise)
    check_plan(sequencer["poses"], sequencer["span"], sequencer["seed"], test_poses=sequencer["test_poses"])
    return namespaced(values, [NodeSpec("estimator", files, dict(robot, **estimator_noise)),
                               NodeSpec("arm_driver", files, arm), NodeSpec("camera_sim", files),
                               NodeSpec("spot_detector", files), NodeSpec("sequencer", files, sequencer)])


def hardware_nodes(values: dict) -> list[NodeSpec]:
    """A real arm (arm_driver on Dynamixel) and a camera driver of the user's; the sequencer last.
    The backend is given here, not left to the arm file: with a file the driver does not read,
    the sim backend's default ran."""
    existing_files(values, "params", "robot", "arm_params", "calibration", "poses_file")
    loadable_robot(values)
    arm_section(values["arm_params"])
    from laser_calib.vision.camera import load_calibration  # OpenCV: only for this graph

    load_calibration(values["calibration"])  # bad YAML now, not after the arm's torque is on
    files = (values["params"],)
    robot = robot_params(values)
    estimator_noise, estimate_noise = noise_params(values)
    sequencer = dict(robot, output_dir=values["output_dir"], poses_file=values["poses_file"],
                     poses=integer(values, "poses"), test_poses=integer(values, "test_poses"), span=values["span"],
                     seed=integer(values, "seed"), **estimate_noise)
    check_plan(None if values["poses_file"] else sequencer["poses"], sequencer["span"], sequencer["seed"],
               test_poses=sequencer["test_poses"])
    return namespaced(values, [
        NodeSpec("estimator", files, dict(robot, **estimator_noise)),
        NodeSpec("arm_driver", (values["arm_params"],), dict(robot, backend="dynamixel")),
        NodeSpec("spot_detector", files, {"calibration": values["calibration"]},
                 # the driver's CameraInfo too: remapped alone, the image's size and intrinsics went unchecked
                 (("camera/image_raw", values["image"]),
                  ("camera/camera_info", os.path.join(os.path.dirname(values["image"]), "camera_info")))),
        NodeSpec("sequencer", files, sequencer)])


def namespaced(values: dict, specs: list[NodeSpec]) -> list[NodeSpec]:
    """specs in the namespace argument's namespace (the sequencer checks a resume's is the session's)."""
    space = namespace(values)
    return [replace(spec, namespace=space) for spec in specs]


def given_plan(values: dict) -> dict:
    """The pose plan arguments among a launch file's values, typed as the sequencer takes them."""
    return {name: integer(values, name) if isinstance(default, int) else values[name]
            for name, default in PLAN_DEFAULTS.items() if name in values}


_held: list[SessionLock] = []  # the locks this process holds, for its lifetime


def take_folder(output_dir: str, values: dict | None = None) -> None:
    """Create the session folder (nodes write into it from their start) and take its lock;
    a folder that holds a finished session, or a partial one of another robot than the
    robot file in values (the sequencer checks one completed from a topic) or of another
    pose plan than the plan arguments in values (SessionDir.check_plan), is refused
    before any node starts."""
    lock = SessionLock(output_dir)
    lock.acquire()
    session = SessionDir(output_dir)
    try:
        refuse_finished(output_dir, "output_dir")
        state = session.state()
        if state == "partial" and values and values.get("robot") and not values.get("robot_description_topic"):
            session.check_robot(load_robot(values["robot"]), values["robot"])
        if state == "partial" and values:
            session.check_plan(given_plan(values))
    except BaseException:
        lock.release()
        raise
    _held.append(lock)


def launch_actions(specs: list[NodeSpec]) -> list:
    """launch_ros Node actions of specs, and the end of the launch when any of them exits: a
    shutdown when the sequencer (last) ends with 0, the session done; an error (launch exits 1,
    naming the node; the node's own one-line reason is in its output) when any exits non-zero,
    or any other node exits at all before the launch is shutting down (a camera stopped on its
    own ended a session of 3 of 12 poses with exit 0, as run-session says exit 1)."""
    from launch.actions import EmitEvent, RegisterEventHandler
    from launch.event_handlers import OnProcessExit
    from launch.events import Shutdown
    from launch_ros.actions import Node

    def ended(event, context, executable: str, last: bool):
        # A node the Ctrl-C reached inside Python's own start (its entry script's package lookup,
        # before laser_calib_nodes put its handler in) dies of the SIGINT (-2), having opened
        # nothing: that is the stop asked for, not a failure (it was "Caught exception", exit 1).
        if event.returncode in (0, -signal.SIGINT) and context.is_shutdown:
            return None
        if event.returncode != 0 or not last:
            raise RuntimeError(f"{executable} exited with code {event.returncode}")
        return [EmitEvent(event=Shutdown(reason="session finished"))]

    actions = []
    env = middleware_env()
    for spec in specs:
        node = Node(package=PACKAGE, executable=spec.executable, name=spec.executable, output="screen",
                    namespace=spec.namespace or None, parameters=[*spec.param_files, spec.params],
                    remappings=list(spec.remaps),
                    additional_env=env, sigterm_timeout=str(STOP_SECONDS))
        actions += [node, RegisterEventHandler(OnProcessExit(
            target_action=node, on_exit=lambda event, context, name=spec.executable, last=spec is specs[-1]:
            ended(event, context, name, last)))]
    return actions


def launch_description(spec: dict, make_nodes) -> "LaunchDescription":
    """A launch description with spec's arguments whose nodes are make_nodes(values), after
    the session folder has been taken (take_folder)."""
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.substitutions import LaunchConfiguration

    def start(context):
        refuse_ignored_arguments(context.argv, spec)
        values = {name: LaunchConfiguration(name).perform(context) for name in spec}
        values["output_dir"] = os.path.abspath(values["output_dir"])
        specs = make_nodes(values)  # bad arguments first: refused before the folder is made
        take_folder(values["output_dir"], values)
        return launch_actions(specs)

    arguments = [DeclareLaunchArgument(name, description=text, **({} if default is None else
                                                                  {"default_value": default}))
                 for name, (default, text) in spec.items()]
    return LaunchDescription(arguments + [OpaqueFunction(function=start)])


def parse(argv: list[str], spec: dict) -> tuple[dict, list[str]]:
    """name:=value arguments (the launch file's) and the sequencer's extra ROS arguments after --."""
    extra = []
    if "--" in argv:
        extra = argv[argv.index("--") + 1:]
        argv = argv[:argv.index("--")]
    values = {name: default for name, (default, _) in spec.items()}
    for item in argv:
        name, sep, value = item.partition(":=")
        if not sep or name not in spec:
            raise InputError(item, f"expected NAME:=VALUE with NAME one of {', '.join(spec)}")
        values[name] = value
    missing = [name for name, value in values.items() if value is None]
    if missing:
        raise InputError(missing[0], "required argument missing")
    values["output_dir"] = os.path.abspath(values["output_dir"])
    return values, extra


def last_line(path: Path) -> str:
    lines = [line for line in path.read_text(errors="replace").splitlines() if line.strip()]
    return lines[-1] if lines else "(no output)"


def run_session(values: dict, extra: list[str]) -> int:
    """Start the graph like `ros2 launch` does: each node's output in output_dir/logs/NAME.log,
    the sequencer's also on this process's stdout and stderr, as it wrote them (its error line on
    stderr); end when the sequencer ends, a node dies, or on a signal. A start the sequencer
    refuses (exit 2, no session begun) leaves no folder this run created: its line says why."""
    specs = session_nodes(values)
    die_with_parent()  # scripts/run-session killed: this process stops the nodes
    created = outermost_missing(Path(values["output_dir"]))
    take_folder(values["output_dir"], values)
    logs = Path(values["output_dir"]) / "logs"
    logs.mkdir(exist_ok=True)
    signalled = StopFlag()   # not an Event: a handler run inside itself would wait on its lock for ever
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signalled.note)
    procs: dict[str, subprocess.Popen] = {}
    env = {**os.environ, **middleware_env()}
    for spec in specs[:-1]:
        with open(logs / f"{spec.executable}.log", "ab") as log:
            procs[spec.executable] = subprocess.Popen(spec.command(), stdout=log, stderr=subprocess.STDOUT,
                                                      preexec_fn=die_with_parent, env=env)
    sequencer = subprocess.Popen(specs[-1].command() + extra, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 preexec_fn=die_with_parent, env=env)
    log, written = open(logs / "sequencer.log", "ab"), threading.Lock()
    tees = [threading.Thread(target=copy_lines, args=(stream, shown, log, written), daemon=True)
            for stream, shown in ((sequencer.stdout, sys.stdout), (sequencer.stderr, sys.stderr))]
    for tee in tees:
        tee.start()
    failed = None
    while sequencer.poll() is None and not signalled.stopped and failed is None:
        failed = next((name for name, proc in procs.items() if proc.poll() is not None), None)
        time.sleep(0.1)
    stop([*procs.values(), sequencer])
    for tee in tees:
        tee.join(timeout=2)
    with written:
        log.close()
    if failed:
        print(f"run-session: {failed} exited with code {procs[failed].returncode}: "
              f"{last_line(logs / f'{failed}.log')}", file=sys.stderr)
        return 1
    if signalled.stopped:
        return 130
    if sequencer.returncode == 2 and created is not None and SessionDir(values["output_dir"]).state() == "new":
        shutil.rmtree(created, ignore_errors=True)  # refused at its start: nothing measured, nothing to resume
    return sequencer.returncode


def copy_lines(stream, shown, log, written: threading.Lock) -> None:
    """Each line of ``stream`` to ``shown`` (stdout or stderr) and to the shared ``log``."""
    for line in stream:
        shown.buffer.write(line)
        shown.flush()
        with written:
            if not log.closed:
                log.write(line)
                log.flush()


def stop(procs: list[subprocess.Popen]) -> None:
    """SIGINT (Ctrl-C) to each live process, SIGKILL to those alive after STOP_SECONDS."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    deadline = time.monotonic() + STOP_SECONDS
    for proc in procs:
        try:
            proc.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def main(argv: list[str] | None = None) -> int:
    try:
        values, extra = parse(list(sys.argv[1:] if argv is None else argv), SESSION_ARGS)
        return run_session(values, extra)
    except InputError as exc:
        print(f"run-session: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
