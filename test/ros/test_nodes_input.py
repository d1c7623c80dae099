"""Bad input to the nodes: one clear line and a non-zero exit, never a traceback;
and the ROS-free pieces (stamp synchronizer, pose lists, segmented bag)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from ros_harness import ROBOT


def last_line(ros, name: str) -> str:
    lines = [line for line in ros.log(name).splitlines() if line.strip()]
    assert "Traceback" not in ros.log(name), ros.log(name)
    return lines[-1]


def test_bad_parameters_and_files_give_one_line(ros, tmp_path):
    bad_poses = tmp_path / "poses.csv"
    bad_poses.write_text("pose,q1,q2,q3,q4,q5,q6,q7\n0,0,0,0,0,0,0,0\n1,0,0,x,0,0,0,0\n")
    broken_robot = tmp_path / "robot.yaml"
    broken_robot.write_text("name: r\njoints: []\n")
    ros.start("seq_poses", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={tmp_path / 'o1'}",
              "-p", f"poses_file:={bad_poses}", node="sequencer")
    ros.start("seq_robot", "-p", f"robot:={broken_robot}", "-p", f"output_dir:={tmp_path / 'o2'}", node="sequencer")
    ros.start("arm_type", "-p", f"robot:={ROBOT}", "-p", "rate:=fast", node="arm_driver")
    ros.start("arm_backend", "-p", f"robot:={ROBOT}", "-p", "backend:=ur5", node="arm_driver")
    ros.start("arm_dxl", "-p", f"robot:={ROBOT}", "-p", "backend:=dynamixel", "-p", "dynamixel.ids:=[1, 2]",
              node="arm_driver")
    ros.start("est_norobot", node="estimator", params=False)
    ros.start("est_compensator", "-p", f"robot:={ROBOT}", "-p", f"compensator:={tmp_path / 'none.json'}",
              node="estimator")
    for name in ros.procs:
        assert ros.wait_exit(name, 60) == 2, (name, ros.log(name))
    assert last_line(ros, "seq_poses") == f"error: {bad_poses}: line 3, field q3: not a number: 'x'"
    assert last_line(ros, "seq_robot") == f"error: {broken_robot}: joints: expected a non-empty list of joints"
    assert "rate" in last_line(ros, "arm_type") and last_line(ros, "arm_type").startswith("error: ")
    assert "backend" in last_line(ros, "arm_backend")
    assert "dynamixel.ticks_per_rad" in last_line(ros, "arm_dxl") or "2 entries" in last_line(ros, "arm_dxl")
    assert "robot" in last_line(ros, "est_norobot")
    assert last_line(ros, "est_compensator").startswith(f"error: {tmp_path / 'none.json'}: not a compensator file")


def test_ros_arguments_rcl_cannot_read_give_one_line(ros, tmp_path):
    """--ros-args that rcl itself refuses (a params file missing or not YAML, '-p name' without a
    value) failed in rclpy.init: a traceback ending in RCLError and exit 1, under `ros2 run` too."""
    (tmp_path / "bad.yaml").write_text("a: [1,\n")
    ros.start("missing", "--params-file", str(tmp_path / "none.yaml"), node="arm_driver", params=False)
    ros.start("not_yaml", "--params-file", str(tmp_path / "bad.yaml"), node="camera_sim", params=False)
    ros.start("no_value", "-p", "robot", node="estimator", params=False)
    ros.start("help", "--help", node="sequencer", params=False)   # after --ros-args: rcl knows no --help
    for name in ros.procs:
        assert ros.wait_exit(name, 60) == 2, (name, ros.log(name))
    assert last_line(ros, "missing") == (f"error: failed to initialize rcl: Couldn't parse params file: '--params-file "
                                         f"{tmp_path / 'none.yaml'}'. Error: Error opening YAML file")
    assert last_line(ros, "not_yaml").startswith(f"error: failed to initialize rcl: Couldn't parse params file: "
                                                 f"'--params-file {tmp_path / 'bad.yaml'}'. Error: ")
    assert last_line(ros, "no_value").startswith("error: failed to initialize rcl: Couldn't parse parameter override "
                                                 "rule: '-p robot'")
    assert last_line(ros, "help") == ("error: --ros-args: not ROS arguments: ['--help'] (a node's parameters: -p "
                                       "NAME:=VALUE or --params-file FILE; ros2 param describe lists them)")
    assert all(", at /" not in last_line(ros, name) for name in ros.procs)


def test_synchronizer_pairs_nearest_within_tolerance():
    from laser_calib.session.sync import StampSynchronizer
    sync = StampSynchronizer(0.005)
    out = []
    for k in range(10):  # joint states at 50 Hz
        out += sync.add_a(k * 0.02, f"a{k}")
    out += sync.add_b(0.061, "b1")   # nearest a3 (0.06), within 5 ms
    out += sync.add_b(0.071, "b2")   # 11 ms from a3 and 9 ms from a4: dropped
    out += sync.add_b(0.5, "b3")     # no joint state there yet: waits
    assert [(p.a, p.b) for p in out] == [("a3", "b1")]
    assert sync.dropped == 1
    out = sync.add_a(0.498, "late") + sync.add_a(0.52, "after")
    assert [(p.a, p.b) for p in out] == [("late", "b3")]
    assert math.isclose(out[0].skew, 0.002)


def test_pose_list_errors(tmp_path):
    from laser_calib.io.errors import InputError
    from laser_calib.model.robot_file import load_robot
    from laser_calib.session.poses import generate_poses, load_poses
    robot = load_robot(ROBOT)
    path = tmp_path / "p.yaml"
    path.write_text("poses:\n  - [0, 0, 0, 0, 0, 0, 0]\n  - {pose: 7, q: [0, 0, 0, 0, 0, 0]}\n")
    with pytest.raises(InputError, match=r"poses\[1\]: 6 joint positions"):
        load_poses(path, robot)
    path.write_text("poses:\n  - [0, 0, 0, 0, 0, 0, 0]\n  - {pose: 7, q: [0, 3.0, 0, 0, 0, 0, 0]}\n")
    with pytest.raises(InputError, match=r"pose 7, field q2: 3 rad outside the joint range"):
        load_poses(path, robot)
    poses = generate_poses(robot, 6, "small", 0, repeats=2)
    assert len(poses) == 8 and list(poses.pose[-2:]) == [0, 5]
    np.testing.assert_array_equal(poses.q[-1], poses.q[5])



def test_planned_pose_list_loads_into_the_sequencer(tmp_path):
    """`laser-calib plan` writes pose,q1..qN; the sequencer's pose list reader takes it as it is."""
    from laser_calib.cli.main import main
    from laser_calib.model.robot_file import load_robot
    from laser_calib.session.poses import load_poses
    robot = load_robot(ROBOT)
    path = tmp_path / "planned.csv"
    assert main(["plan", "--robot", str(ROBOT), "--n", "12", "--out", str(path)]) == 0
    poses = load_poses(path, robot)
    assert len(poses) == 12 and list(poses.pose) == list(range(12))
    assert np.all((poses.q >= robot.q_min) & (poses.q <= robot.q_max))

WRITER = textwrap.dedent("""
    import os, sys, time
    from laser_calib.io import bag
    store = bag.typestore()
    Sample = store.types['laser_calib_interfaces/msg/Sample']
    Spot = store.types['laser_calib_interfaces/msg/Spot']
    H = store.types['std_msgs/msg/Header']; T = store.types['builtin_interfaces/msg/Time']
    import numpy as np
    topics = {'/samples': ('laser_calib_interfaces/msg/Sample', [bag.qos(True, True, 100)])}
    from laser_calib.io.bag_writer import SegmentedBagWriter
    w = SegmentedBagWriter(sys.argv[1] + '/bag', sys.argv[1] + '/.recording', topics, store)
    start, n = int(sys.argv[2]), int(sys.argv[3])
    for k in range(start, start + n):
        m = Sample(H(T(1000 + k, 0), 'screen'), k, ['j'], np.array([0.1 * k]),
                   [Spot(0.1, 0.2, True), Spot(float('nan'), float('nan'), False)], 3)
        w.write('/samples', 10**9 * (1000 + k), store.serialize_cdr(m, 'laser_calib_interfaces/msg/Sample'))
        if k == start + n - 1 and sys.argv[4] == 'kill':
            os.kill(os.getpid(), 9)   # the last sample never gets its segment closed
        w.rotate()
    w.close()
""")


def test_segmented_bag_survives_sigkill(tmp_path):
    from laser_calib.io import bag
    from ros_harness import ROOT
    src = ROOT / "ros2_ws" / "src"
    env = dict(os.environ, PYTHONPATH=f"{src / 'laser_calib'}:{src / 'laser_calib_nodes'}")
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    killed = subprocess.run([sys.executable, str(script), str(tmp_path), "0", "4", "kill"], env=env)
    assert killed.returncode == -9
    samples = bag.read_samples(tmp_path / "bag")
    assert list(samples.pose) == [0, 1, 2]
    done = subprocess.run([sys.executable, str(script), str(tmp_path), "3", "2", "ok"], env=env)
    assert done.returncode == 0
    samples = bag.read_samples(tmp_path / "bag")
    assert list(samples.pose) == [0, 1, 2, 3, 4]
    assert not (tmp_path / ".recording").exists()


def test_bad_speed_and_method_are_refused_at_the_start(ros, tmp_path):
    """A simulated joint speed that is no positive number, and an estimate method that does not
    exist: one line naming the parameter, exit 2, at the start (never after the poses are measured)."""
    ros.start("arm_speed", "-p", f"robot:={ROBOT}", "-p", "sim.joint_speed:=-1.0", node="arm_driver")
    ros.start("arm_tau", "-p", f"robot:={ROBOT}", "-p", "sim.time_constant:=0.0", node="arm_driver")
    ros.start("arm_fast", "-p", f"robot:={ROBOT}", "-p", "sim.joint_speed:=fast", node="arm_driver")
    ros.start("seq_method", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={tmp_path / 'o'}",
              "-p", "estimate.method:=foo", node="sequencer")
    for name in ros.procs:
        assert ros.wait_exit(name, 60) == 2, (name, ros.log(name))
    assert last_line(ros, "arm_speed") == "error: parameter sim.joint_speed: expected > 0, got -1.0"
    assert last_line(ros, "arm_tau") == "error: parameter sim.time_constant: expected > 0, got 0.0"
    assert last_line(ros, "arm_fast").startswith("error: parameter sim.joint_speed: ")
    assert last_line(ros, "seq_method") == "error: parameter estimate.method: expected one of lm, ekf, got 'foo'"
    assert not (tmp_path / "o" / "session.yaml").exists()
    # the launch arguments (run-session's graph, as session.launch.py takes them): before any node starts
    for args, where in ((["speed:=fast"], "speed: expected a positive number, got 'fast'"),
                        (["speed:=-1"], "speed: expected a positive number, got '-1'"),
                        (["method:=foo"], "method: expected one of lm, ekf, got 'foo'")):
        out = tmp_path / args[0].replace(":=", "_")
        result = ros.run([sys.executable, "-m", "laser_calib_nodes.graph", f"output_dir:={out}", *args])
        assert result.returncode == 2 and result.stderr == f"run-session: {where}\n", result
        assert "Traceback" not in result.stderr and not out.exists()


def test_launch_refuses_bad_speed_and_method_before_any_node_starts(ros, tmp_path):
    from ros_harness import ros2_missing
    if ros2_missing():
        pytest.skip(ros2_missing())
    for arg in ("speed:=fast", "speed:=-1", "method:=foo"):
        name = arg.replace(":=", "_").replace("-", "m")
        ros.start_command(name, ["ros2", "launch", "laser_calib_nodes", "session.launch.py",
                                 f"output_dir:={tmp_path / name}", arg])
    for name in list(ros.procs):
        assert ros.wait_exit(name, 60) != 0, ros.log(name)
        log = ros.log(name)
        errors = [line for line in log.splitlines() if "ERROR" in line]
        assert "process started" not in log and "Traceback" not in log, log
        assert len(errors) == 1 and name.split("_")[0] + ": expected" in errors[0], log


def test_parameters_out_of_range_are_refused_at_the_start(ros, tmp_path):
    """A negative tolerance, timeout, seed or margin: one line naming the parameter and exit 2 at the start,
    not a traceback (the estimator at once; the sequencer once the arm had settled at its first pose)."""
    ros.start("est_sync", "-p", f"robot:={ROBOT}", "-p", "input:=stream", "-p", "sync_tolerance:=-0.01",
              node="estimator")
    sync = "parameter sync_tolerance: expected >= 0 and <= 0.5 s (a pair further apart shows two instants), got -0.01"
    cases = {"seq_sync": ("sync_tolerance:=-0.01", sync),
             "seq_wait": ("wait_timeout:=-1.0", "parameter wait_timeout: expected > 0, got -1.0"),
             "seq_segment": ("bag.max_segment_seconds:=0.0", "parameter bag.max_segment_seconds: expected > 0, "
                                                             "got 0.0"),
             "seq_estimate": ("estimate.timeout:=0.0", "parameter estimate.timeout: expected > 0, got 0.0"),
             "seq_seed": ("seed:=-1", "seed: must be >= 0, got -1"),
             # spots planned off the screen (then unseen), and nan: "found only 0 of 60 poses" before
             "seq_margin": ("margin:=-0.5", "margin: must be >= 0 m, got -0.5"),
             "seq_margin_nan": ("margin:=.nan", "margin: must be >= 0 m, got nan"),
             "seq_unseen": ("unseen_limit:=-1", "parameter unseen_limit: expected >= 0, got -1")}
    for name, (param, _) in cases.items():
        ros.start(name, "-p", f"robot:={ROBOT}", "-p", f"output_dir:={tmp_path / name}", "-p", param,
                  node="sequencer")
    for name in ros.procs:
        assert ros.wait_exit(name, 60) == 2, (name, ros.log(name))
    assert last_line(ros, "est_sync") == f"error: {sync}"
    for name, (_, line) in cases.items():
        assert last_line(ros, name) == f"error: {line}", name


def test_launch_refuses_a_missing_file_before_any_node_starts(ros, tmp_path):
    """A parameter or robot file that does not exist: launch_ros only warned of the parameter file
    and ran the session on the nodes' defaults; now one line naming the argument, no node started.
    A robot file that does not load: each node refused it after the launch had made the session
    folder and its lock; now one line naming the file, before the folder is made. So is one
    without lasers (allowed for other sensors), with which the estimator answered every request
    with an internal error."""
    from ros_harness import EXAMPLE_ARM, ros2_missing
    if ros2_missing():
        pytest.skip(ros2_missing())
    missing = tmp_path / "missing.yaml"
    for launch, arg in (("session", "params"), ("session", "robot"), ("hardware", "calibration")):
        ros.start_command(f"{launch}_{arg}", ["ros2", "launch", "laser_calib_nodes", f"{launch}.launch.py",
                                              f"output_dir:={tmp_path / arg}", f"robot:={ROBOT}",
                                              f"calibration:={tmp_path}", f"{arg}:={missing}",
                                              *([f"arm_params:={EXAMPLE_ARM}"] if launch == "hardware" else [])])
    malformed = tmp_path / "malformed.yaml"
    malformed.write_text("name: arm\njoints: [\n")
    ros.start_command("session_malformed", ["ros2", "launch", "laser_calib_nodes", "session.launch.py",
                                            f"output_dir:={tmp_path / 'malformed'}", f"robot:={malformed}"])
    no_lasers = tmp_path / "no_lasers.yaml"  # an arm for another sensor: no spot to model
    no_lasers.write_text(ROBOT.read_text().split("\nslm:")[0] + "\n")
    ros.start_command("session_nolasers", ["ros2", "launch", "laser_calib_nodes", "session.launch.py",
                                           f"output_dir:={tmp_path / 'nolasers'}", f"robot:={no_lasers}"])
    reasons = {name: f"{name.split('_')[1]}: no such file: {missing}" for name in ros.procs}
    reasons["session_malformed"] = f"{malformed}: line 3: not valid YAML"
    reasons["session_nolasers"] = f"robot: {no_lasers}: spot samples need the robot's lasers"
    for name, reason in reasons.items():
        assert ros.wait_exit(name, 60) != 0, ros.log(name)
        log = ros.log(name)
        errors = [line for line in log.splitlines() if "ERROR" in line]
        assert "process started" not in log and "Traceback" not in log, log
        assert len(errors) == 1 and reason in errors[0], log
    assert not (tmp_path / "malformed").exists()  # refused before the session folder (and its lock) is made
    assert not (tmp_path / "nolasers").exists()


def test_a_parameter_the_node_does_not_take_is_one_warning(ros):
    """A misspelt key (dynamixel.zero_tick for dynamixel.zero_ticks) was dropped by ROS without a
    word and the driver ran on the default zero; now one WARN line names it."""
    ros.start("arm_driver", "-p", f"robot:={ROBOT}", "-p", "dynamixel.zero_tick:=[1, 2]")
    # said once the node is made, just after its 'publishing at' line: a stop sent on that line
    # could come first (seen once in a full run)
    ros.wait_log("arm_driver", "does not take", 60)
    assert ros.stop("arm_driver") == 0
    warned = [line for line in ros.log("arm_driver").splitlines() if "does not take" in line]
    assert len(warned) == 1 and "[WARN]" in warned[0] and warned[0].endswith(": dynamixel.zero_tick"), warned
