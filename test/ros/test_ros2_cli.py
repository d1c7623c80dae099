"""The node set under the real ROS 2 command line, as a user runs it: `ros2 launch`
of a session on a fresh, a partial and a finished folder, Ctrl-C (SIGINT to the
launch's process group, as a terminal sends it) once and twice, a node that fails,
`ros2 run` of each node, `ros2 service call`, `ros2 param get/set`, `ros2 topic
echo/pub`, and the Calibrate action. Skipped, with the reason, when ros2cli is not
installed (.ci/run installs it from ../shared/tools/ros2cli).

The sessions are 10 poses, too few for the diagnosis (12 needed with 5 folds and
4 values per pose): the estimate succeeds with "diagnosis skipped".
"""

from __future__ import annotations

import json
import os
import re
import signal
import sys
import time
from pathlib import Path

import pytest

from ros_harness import EXAMPLE_ARM, PARAMS, ROBOT, Ros, children, ros2_missing

POSES = 10
LAUNCH = ["ros2", "launch", "laser_calib_nodes", "session.launch.py"]
SKIPPED = f"diagnosis skipped: {POSES} poses, at least 12 needed"
SESSION_SECONDS = 300  # a 10-pose session, seen 30 s on a busy 2-core machine
STOP_SECONDS = 30      # Ctrl-C to the end of the launch (launch escalates to SIGTERM after graph.STOP_SECONDS)


@pytest.fixture(scope="module", autouse=True)
def need_ros2():
    reason = ros2_missing()
    if reason:
        pytest.skip(reason)


def csv_rows(path) -> int:
    try:
        return max(0, len(path.read_text().strip().splitlines()) - 1)
    except OSError:
        return 0


def wait_for(condition, timeout: float, what: str, ros: Ros, name: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert ros.procs[name].poll() is None, f"{name} ended before {what}:\n{ros.log(name)[-3000:]}"
        assert time.monotonic() < deadline, f"no {what} within {timeout} s:\n{ros.log(name)[-3000:]}"
        time.sleep(0.1)


def assert_clean_stop(log: str) -> None:
    """Every node of the launch exited 0, without a traceback, without launch's escalation and
    without rcl's complaint about lines logged to /rosout after the signal shut the context."""
    started = re.findall(r"\[INFO\] \[([\w-]+)\]: process started", log)
    assert started, log[-3000:]
    for node in started:
        assert re.search(rf"\[{node}\]: process has finished cleanly", log), f"{node} did not exit 0:\n{log[-4000:]}"
    assert "Traceback" not in log and "KeyboardInterrupt" not in log, log[-4000:]
    assert "SIGTERM" not in log, log[-4000:]
    assert "Failed to publish log message" not in log, log[-4000:]


def launch_session(ros: Ros, name: str, out, *args: str, speed: float = 4.0):
    return ros.start_command(name, LAUNCH + [f"output_dir:={out}", f"poses:={POSES}", f"speed:={speed}", "seed:=3",
                                             *args])


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A session launched on a folder that does not exist yet, run to its end."""
    tmp = tmp_path_factory.mktemp("launch")
    ros = Ros(tmp)
    out = tmp / "new" / "session"
    launch_session(ros, "launch", out)
    try:
        code = ros.wait_exit("launch", SESSION_SECONDS)
    finally:
        ros.stop_all()
    return ros, out, code


GRAPH = """import json, sys
from laser_calib_nodes.graph import SESSION_ARGS, session_nodes
values = {name: default for name, (default, _) in SESSION_ARGS.items()} | {"output_dir": sys.argv[1]}
print(json.dumps([spec.executable for spec in session_nodes(values)]))"""


def test_launch_on_a_fresh_folder_runs_the_session(finished):
    ros, out, code = finished
    log = ros.log("launch")
    assert code == 0, log[-4000:]
    assert (out / "report.md").exists() and (out / "robot_true.yaml").exists()
    assert "finished" in (out / "session.yaml").read_text()
    assert SKIPPED in log                      # a data limit, not a failure: the estimate succeeded
    assert_clean_stop(log)
    # the processes are those of the one graph definition that scripts/run-session starts too
    started = re.findall(r"\[INFO\] \[(\w+)-\d+\]: process started", log)
    graph = ros.run([sys.executable, "-c", GRAPH, str(out)])
    assert started == json.loads(graph.stdout), graph


def test_launch_on_a_finished_folder_is_refused_before_any_node_starts(finished, tmp_path):
    _, out, _ = finished
    ros = Ros(tmp_path)
    start = time.monotonic()
    launch_session(ros, "again", out)
    code = ros.wait_exit("again", 60)
    log = ros.log("again")
    assert code != 0 and time.monotonic() - start < 60
    assert "process started" not in log
    errors = [line for line in log.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "holds a finished session" in errors[0], log
    assert "Traceback" not in log


def test_ctrl_c_once_on_a_partial_session_then_resume(tmp_path):
    ros = Ros(tmp_path)
    out = tmp_path / "session"
    # a slow arm (0.3 rad/s): the 8 poses left must outlast the two refused starts below, which took
    # longer than they do at 4 rad/s on a loaded machine (the session ended before its Ctrl-C)
    proc = launch_session(ros, "launch", out, speed=0.3)
    try:
        wait_for(lambda: csv_rows(out / "samples.csv") >= 2, SESSION_SECONDS, "2 measured poses", ros, "launch")
        # a second session on the live folder: one line naming the owner (the launch process)
        second = ros.run(LAUNCH + [f"output_dir:={out}"], timeout=60)
        refusal = [line for line in (second.stdout + second.stderr).splitlines() if "ERROR" in line]
        assert second.returncode != 0 and len(refusal) == 1 and f"PID {proc.pid}" in refusal[0], second
        runner = ros.run([sys.executable, "-m", "laser_calib_nodes.graph", f"output_dir:={out}"], timeout=60)
        assert runner.returncode == 2 and f"PID {proc.pid}" in runner.stderr, runner
        assert len(runner.stderr.strip().splitlines()) == 1, runner.stderr
        ros.interrupt("launch")
        ros.wait_exit("launch", STOP_SECONDS)
    finally:
        ros.stop_all()
    assert_clean_stop(ros.log("launch"))
    from laser_calib.io import bag
    done = len(bag.read_samples(out / "bag"))  # the session's journal (samples.csv may lag a pose)
    assert 2 <= done < POSES

    launch_session(ros, "resumed", out)
    try:
        assert ros.wait_exit("resumed", SESSION_SECONDS) == 0, ros.log("resumed")[-4000:]
    finally:
        ros.stop_all()
    log = ros.log("resumed")
    assert f"resuming {out}: {done} of {POSES} poses already measured" in log, log[-4000:]
    assert SKIPPED in log
    assert_clean_stop(log)


def test_ctrl_c_twice(tmp_path):
    ros = Ros(tmp_path)
    launch_session(ros, "launch", tmp_path / "session")
    try:
        wait_for(lambda: "measuring" in ros.log("launch") and "input 'samples'" in ros.log("launch"),
                 SESSION_SECONDS, "every node up", ros, "launch")
        ros.interrupt("launch")
        time.sleep(0.3)
        ros.interrupt("launch")
        ros.wait_exit("launch", STOP_SECONDS)
    finally:
        ros.stop_all()
    assert_clean_stop(ros.log("launch"))


def test_a_failing_node_ends_the_launch_with_its_reason(tmp_path):
    """A parameter only the node checks (the estimator's sync_tolerance below 0, in the user's
    parameter file): the node exits 2 with the reason and the launch ends (exit 1) naming it.
    (A robot file that does not exist or does not load is refused before any node starts:
    test_nodes_input.py.)"""
    ros = Ros(tmp_path)
    params = tmp_path / "params.yaml"
    params.write_text("estimator:\n  ros__parameters:\n    sync_tolerance: -0.01\n")
    start = time.monotonic()
    launch_session(ros, "launch", tmp_path / "session", f"params:={params}")
    try:
        code = ros.wait_exit("launch", 120)
    finally:
        ros.stop_all()
    log = ros.log("launch")
    seconds = time.monotonic() - start
    assert code == 1 and seconds < 120, log[-3000:]
    reasons = [line for line in log.splitlines()
               if "error: parameter sync_tolerance: expected >= 0 and <= 0.5 s" in line and line.endswith("got -0.01")]
    assert reasons, log[-3000:]
    assert re.search(r"\[ERROR\] \[launch\]: .*estimator\S* exited with code 2", log), log[-3000:]
    assert "Traceback" not in log, log[-4000:]


def child_pid(parent: int, executable: str) -> int:
    """The pid of the descendant of ``parent`` running ``executable`` (a launch's node)."""
    for pid in children(parent):
        try:
            if executable.encode() in Path(f"/proc/{pid}/cmdline").read_bytes():
                return pid
        except OSError:  # a process that ended meanwhile
            continue
    raise AssertionError(f"no child {executable} of {parent}")


def test_a_node_that_stops_cleanly_mid_session_ends_the_launch_with_exit_1(tmp_path):
    """The camera given Ctrl-C on its own, 2 poses in: it exits 0, and the launch ended the session
    with exit 0 and no reason, 3 of 12 poses measured (run-session said exit 1). A node that ends
    before the session does is a failure whatever its code."""
    ros = Ros(tmp_path)
    out = tmp_path / "session"
    proc = launch_session(ros, "launch", out, speed=0.3)
    try:
        wait_for(lambda: csv_rows(out / "samples.csv") >= 2, SESSION_SECONDS, "2 measured poses", ros, "launch")
        os.kill(child_pid(proc.pid, "camera_sim"), signal.SIGINT)
        code = ros.wait_exit("launch", STOP_SECONDS + 30)
    finally:
        ros.stop_all()
    log = ros.log("launch")
    assert code == 1, log[-3000:]
    assert re.search(r"\[ERROR\] \[launch\]: .*camera_sim\S* exited with code 0", log), log[-3000:]
    assert "Traceback" not in log, log[-4000:]


def test_ros2_run_service_param_and_topics(tmp_path):
    ros = Ros(tmp_path)
    run = ["ros2", "run", "laser_calib_nodes"]
    params = ["--ros-args", "--params-file", str(PARAMS)]
    ros.start_command("estimator", run + ["estimator"] + params + ["-p", f"robot:={ROBOT}"])
    ros.start_command("arm_driver", run + ["arm_driver"] + params + ["-p", f"robot:={ROBOT}"])
    ros.start_command("camera_sim", run + ["camera_sim"] + params)
    ros.start_command("spot_detector", run + ["spot_detector"] + params)
    try:
        wait_for(lambda: "input 'samples'" in ros.log("estimator"), 120, "the estimator", ros, "estimator")
        # the wheels' packages are on AMENT_PREFIX_PATH (scripts/env.sh), and the action is built
        header = ros.ros2("interface", "show", "std_msgs/msg/Header")
        assert header.returncode == 0 and "builtin_interfaces/Time stamp" in header.stdout, header
        action = ros.ros2("interface", "show", "laser_calib_interfaces/action/Calibrate")
        assert action.returncode == 0 and "fraction_done" in action.stdout, action
        # --timeout: wait for the node until it is seen (--spin-time would spin its whole length, every call);
        # each `ros2 param` is a new process that discovers the graph anew, and its default (1 s) is too short
        # for that on a loaded machine ('Node not found' from a `param set` right after a `param get` worked)
        spin = ["--timeout", "30"]
        got = ros.ros2("param", "get", "/estimator", "spot_sigma", *spin)
        assert got.returncode == 0 and "0.0" in got.stdout, got
        # run-time parameter: validated
        changed = ros.ros2("param", "set", "/estimator", "spot_sigma", "0.001", *spin)
        assert "Set parameter successful" in changed.stdout, changed
        assert "0.001" in ros.ros2("param", "get", "/estimator", "spot_sigma", *spin).stdout
        refused = ros.ros2("param", "set", "/estimator", "spot_sigma", "0.5", *spin)  # 0.5 mm typed as m
        assert "0.5 m is not a plausible spot noise" in refused.stdout + refused.stderr, refused
        assert "0.001" in ros.ros2("param", "get", "/estimator", "spot_sigma", *spin).stdout
        read_only = ros.ros2("param", "set", "/estimator", "robot", "x.yaml", *spin)
        assert "read-only" in (read_only.stdout + read_only.stderr).lower(), read_only
        # the detector's threshold is tuned while the camera runs; a bad value changes nothing
        changed = ros.ros2("param", "set", "/spot_detector", "min_peak_dn", "30", *spin)
        assert "Set parameter successful" in changed.stdout, changed
        refused = ros.ros2("param", "set", "/spot_detector", "min_peak_dn", "0.0", *spin)
        assert "expected 0..255" in refused.stdout + refused.stderr, refused
        assert "30" in ros.ros2("param", "get", "/spot_detector", "min_peak_dn", *spin).stdout
        # what a value must be, as `param describe` says it (it said the description alone)
        described = ros.ros2("param", "describe", "/spot_detector", "min_peak_dn", "false_refusal_rate", *spin)
        assert "Additional constraints: 0 < value < 255\n" in described.stdout, described
        assert "Additional constraints: 0 < value < 1\n" in described.stdout, described
        described = ros.ros2("param", "describe", "/estimator", "spot_sigma", *spin)
        assert "Additional constraints: 0 (estimated) or 1e-09 .. 0.05 m" in described.stdout, described
        spots = ["topic", "echo", "--once", "/spots", "laser_calib_interfaces/msg/SpotPair"]
        seen = ros.ros2(*spots, timeout=60)
        assert seen.returncode == 0 and seen.stdout.count("seen: true") == 2, seen
        assert "Set parameter successful" in ros.ros2("param", "set", "/spot_detector", "min_peak_dn",
                                                  "254.0", *spin).stdout
        unseen = ros.ros2(*spots, timeout=60)  # a frame after the set: no spot's contrast is that high
        assert unseen.returncode == 0 and unseen.stdout.count("seen: false") == 2, unseen
        # private service names
        reset = ros.ros2("service", "call", "/estimator/reset", "std_srvs/srv/Trigger")
        assert reset.returncode == 0 and "success=True" in reset.stdout, reset
        state = ros.ros2("topic", "echo", "--once", "/joint_states", "sensor_msgs/msg/JointState", timeout=60)
        assert state.returncode == 0 and "joint1" in state.stdout, state
        # a sample from a default-QoS publisher reaches the estimator
        sample = ("{pose: 0, joint_positions: [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7], "
                  "spots: [{y: 0.1, z: 0.2, seen: true}, {y: -0.1, z: 0.2, seen: true}]}")
        # (sent 5 times: the same (pose, stamp) counts once)
        pub = ros.ros2("topic", "pub", "-w", "1", "-t", "5", "-r", "5", "/samples",
                   "laser_calib_interfaces/msg/Sample", sample)
        assert pub.returncode == 0, pub
        assert ros.client("params", "1")["sample_count"] == 1
        # and is not said to be lost: the transient-local subscription (for the sequencer's history), which
        # a volatile publisher does not match, warned 'No messages will be received from it' at each one
        assert "incompatible QoS" not in ros.log("estimator"), ros.log("estimator")
        # nodes that cannot start say why in one line and exit 2
        sequencer = ros.run(run + ["sequencer"] + params + ["-p", f"robot:={ROBOT}"], timeout=90)
        assert sequencer.returncode == 2 and "output_dir is empty" in sequencer.stderr, sequencer
        replay = ros.run(run + ["replay", str(tmp_path / "no_bag")], timeout=90)
        assert replay.returncode == 2 and "Traceback" not in replay.stderr, replay
    finally:
        codes = ros.stop_all()
    assert codes == {name: 0 for name in codes}, {name: ros.log(name)[-2000:] for name in codes}
    for name in codes:
        assert "Traceback" not in ros.log(name), ros.log(name)


def test_calibrate_action_feedback_and_cancel(finished, tmp_path):
    _, out, _ = finished
    ros = Ros(tmp_path)
    ros.start("estimator", "-p", f"robot:={ROBOT}")
    try:
        ros.start_command("replay", ["ros2", "run", "laser_calib_nodes", "replay", str(out / "bag"), "--topics",
                                     "/samples", "--rate", "50", "--wait-for", "/samples"])
        assert ros.wait_exit("replay", 120) == 0, ros.log("replay")
        assert ros.client("params", str(POSES))["sample_count"] == POSES
        done = ros.client("calibrate", "diagnose")
        assert done["status"] == "succeeded" and done["success"], done
        assert done["stages"] == ["estimate", "diagnosis", "done"], done
        assert SKIPPED in done["message"] and "skipped" in done["diagnosis_json"]
        assert done["sample_count"] == POSES
        # A cancel sent on acceptance stops the estimate itself: it used to run to its end, the cancel
        # honoured only before the diagnosis.
        canceled = ros.client("calibrate", "diagnose", "cancel")
        assert canceled["status"] == "canceled" and not canceled["success"], canceled
        assert canceled["message"] == "canceled during the estimate; no file was written", canceled
        assert canceled["stages"] == ["estimate"], canceled
        # the service beside the action answers as before
        assert ros.client("estimate-accumulated")["success"]
    finally:
        codes = ros.stop_all()
    assert codes["estimator"] == 0, ros.log("estimator")


def test_hardware_launch_without_an_arm_file_or_with_a_mismatched_one_ends_with_its_reason(tmp_path):
    """Without arm_params the launch is refused before any node starts: its default was the
    shipped example, whose port, servo ids and zero ticks then drove whatever adapter was there.
    The shipped example (4 servos) with the 7-DOF robot: one line, the launch ends. The spot
    detector gets a valid screen calibration, so that no other node's refusal can end the launch
    first (a missing one did, in one run: the two nodes start together)."""
    from laser_calib.vision.camera import default_camera, save_calibration
    save_calibration(default_camera().ideal_calibration(), tmp_path / "screen.yaml")
    ros = Ros(tmp_path)
    shown = ros.run(["ros2", "launch", "laser_calib_nodes", "hardware.launch.py", "--show-args"], timeout=60)
    assert shown.returncode == 0 and "'arm_params'" in shown.stdout, shown
    given = ["ros2", "launch", "laser_calib_nodes", "hardware.launch.py", f"robot:={ROBOT}",
             f"calibration:={tmp_path / 'screen.yaml'}", f"output_dir:={tmp_path / 'session'}"]
    refused = ros.run(given, timeout=60)
    errors = [line for line in (refused.stdout + refused.stderr).splitlines() if "ERROR" in line]
    assert refused.returncode != 0 and "process started" not in refused.stdout + refused.stderr, refused
    assert len(errors) == 1 and "missing required argument 'arm_params'" in errors[0], refused
    assert not (tmp_path / "session").exists()
    ros.start_command("launch", given + [f"arm_params:={EXAMPLE_ARM}"])
    try:
        code = ros.wait_exit("launch", 120)
    finally:
        ros.stop_all()
    log = ros.log("launch")
    assert code == 1, log[-3000:]
    assert re.search(r"\[arm_driver-\d+\] error: .*dynamixel.ids has 4 entries, the arm has 7 joints", log), log
    assert "arm_driver exited with code 2" in log and "Traceback" not in log, log[-3000:]
