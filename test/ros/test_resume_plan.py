"""A partial session is resumed on its own pose plan: plan arguments (poses, test_poses, seed,
span, poses_file, ...) other than the recorded ones are refused in one line naming each with its
recorded and given value (exit 2; run-session's graph and `ros2 launch` before any node starts),
where they were silently ignored (a resume asked for 3 held-out poses ran the recorded plan).
The same command, or the plan arguments left out, resumes; another estimate method is used, with
a WARN line saying so."""

from __future__ import annotations

import sys

import pytest

from ros_harness import EXAMPLE_ARM, ROBOT, ros2_missing

FIRST = ("poses:=15", "test_poses:=5", "span:=small")
CHANGED = ("poses:=25", "test_poses:=3", "seed:=5", "span:=small")
REFUSAL = ("holds a partial session whose pose plan is fixed by what was measured: poses recorded 15, given 25; "
           "test_poses recorded 5, given 3; seed recorded 0, given 5; resume with the recorded values (or leave "
           "them out) or choose another output_dir")


def ros_params(*args: str) -> list[str]:
    return [item for arg in args for item in ("-p", arg)]


def partial_session(ros, out) -> None:
    """A session started by the sequencer with FIRST's plan, nothing measured (no arm: exit 3)."""
    ros.start("first", *ros_params(f"robot:={ROBOT}", f"output_dir:={out}", "wait_timeout:=1.0", *FIRST),
              node="sequencer")
    assert ros.wait_exit("first", 60) == 3, ros.log("first")


def test_resume_with_another_plan_is_refused(ros, tmp_path):
    out = tmp_path / "session"
    partial_session(ros, out)
    ros.start("changed", *ros_params(f"robot:={ROBOT}", f"output_dir:={out}", *CHANGED, "estimate.method:=ekf"),
              node="sequencer")
    assert ros.wait_exit("changed", 60) == 2, ros.log("changed")
    log = ros.log("changed")
    lines = [line for line in log.splitlines() if line.strip()]
    assert lines[-1] == f"error: {out}: {REFUSAL}" and "Traceback" not in log, log
    assert "resuming" not in log
    # run-session's graph: the same line, before any node starts
    result = ros.run([sys.executable, "-m", "laser_calib_nodes.graph", f"output_dir:={out}", *CHANGED,
                      "method:=ekf"])
    assert result.returncode == 2 and result.stderr == f"run-session: {out}: {REFUSAL}\n", result
    assert not (out / "logs").exists()
    # the same command, another method: resumed on the recorded plan, the method used said in a WARN;
    # then the plan arguments left out (at their defaults): resumed on the recorded plan
    for name, args in (("same", (*FIRST, "estimate.method:=ekf")), ("defaults", ())):
        ros.start(name, *ros_params(f"robot:={ROBOT}", f"output_dir:={out}", "wait_timeout:=1.0", *args),
                  node="sequencer")
        assert ros.wait_exit(name, 60) == 3, ros.log(name)
        assert f"resuming {out}: 0 of 20 poses already measured" in ros.log(name), ros.log(name)
        assert "test_poses 5" in ros.log(name)
    warnings = [line for line in ros.log("same").splitlines() if "WARN" in line]
    assert len(warnings) == 1 and "estimate.method is ekf, the session's previous run used lm: this run uses ekf" \
        in warnings[0], ros.log("same")


def test_resume_with_other_noise_sigmas_says_so(ros, tmp_path):
    """The final estimate's noise (estimate.spot_sigma, estimate.joint_sigma) sets the calibration's
    standard deviations: a resume with others is said in a WARN line each, as the method is (it
    changed them silently). A session recorded before the sigmas were (no such keys) warns of none."""
    import yaml
    out = tmp_path / "session"
    partial_session(ros, out)
    sigmas = ("estimate.spot_sigma:=0.001", "estimate.joint_sigma:=0.002")
    ros.start("sigmas", *ros_params(f"robot:={ROBOT}", f"output_dir:={out}", "wait_timeout:=1.0", *sigmas),
              node="sequencer")
    assert ros.wait_exit("sigmas", 60) == 3, ros.log("sigmas")
    warnings = [line for line in ros.log("sigmas").splitlines() if "WARN" in line]
    assert len(warnings) == 2, ros.log("sigmas")
    assert "estimate.spot_sigma is 0.001, the session's previous run used 0.0: this run uses 0.001" in warnings[0]
    assert "estimate.joint_sigma is 0.002, the session's previous run used -1.0: this run uses 0.002" in warnings[1]
    info = yaml.safe_load((out / "session.yaml").read_text())
    assert (info["settings"]["estimate.spot_sigma"], info["settings"]["estimate.joint_sigma"]) == (0.001, 0.002)
    # an older session's record: the sigmas it ran with are unknown, so nothing to compare
    for name in ("estimate.spot_sigma", "estimate.joint_sigma"):
        del info["settings"][name]
    (out / "session.yaml").write_text(yaml.safe_dump(info, sort_keys=False))
    ros.start("old", *ros_params(f"robot:={ROBOT}", f"output_dir:={out}", "wait_timeout:=1.0", *sigmas),
              node="sequencer")
    assert ros.wait_exit("old", 60) == 3, ros.log("old")
    assert "WARN" not in ros.log("old") and f"resuming {out}" in ros.log("old"), ros.log("old")


def test_launch_resume_with_another_plan_is_refused_before_any_node_starts(ros, tmp_path):
    if ros2_missing():
        pytest.skip(ros2_missing())
    out = tmp_path / "session"
    partial_session(ros, out)
    ros.start_command("launch", ["ros2", "launch", "laser_calib_nodes", "session.launch.py", f"output_dir:={out}",
                                 *CHANGED, "method:=ekf"])
    assert ros.wait_exit("launch", 60) != 0
    log = ros.log("launch")
    assert "process started" not in log and "Traceback" not in log, log
    errors = [line for line in log.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and f"{out}: {REFUSAL}" in errors[0], log


def test_plan_of_a_session_recorded_before_the_plan_was(tmp_path):
    """A session.yaml without 'plan' (older sessions): its pose description and test_poses say it."""
    from laser_calib.io.errors import InputError
    from laser_calib.model.robot_file import load_robot
    from laser_calib.session.folder import PLAN_DEFAULTS, SessionDir
    from laser_calib.session.poses import generate_poses, with_test_poses
    robot = load_robot(ROBOT)
    session = SessionDir(tmp_path / "old")
    session.start(robot, with_test_poses(generate_poses(robot, 15, "small", 0), robot, 5, 0),
                  {"robot": str(ROBOT), "poses": "generated: 15 poses, span small, seed 0, repeats 0", "test_poses": 5})
    assert session.recorded_plan() == {"poses": 15, "span": "small", "seed": 0, "repeats": 0, "test_poses": 5}
    session.check_plan({"poses": 15, "test_poses": 0, "span": "whole", "seed": 0, "margin": 0.05})
    with pytest.raises(InputError, match=r"test_poses recorded 5, given 3; resume with"):
        session.check_plan({"poses": 15, "test_poses": 3})
    # a generated session's plan holds no pose file: shown as none (it printed 'poses_file recorded , given ...')
    session.set_info(plan={**PLAN_DEFAULTS, "poses": 15})
    with pytest.raises(InputError, match=r"poses_file recorded none, given /x/poses.csv; resume with"):
        session.check_plan({"poses_file": "/x/poses.csv"})


def test_launch_refuses_a_plan_argument_it_does_not_take(ros, tmp_path):
    """A plan argument the launch file does not declare (repeats; test_poses on hardware.launch.py
    until it took it): `ros2 launch` dropped test_poses:=5 silently and the session ran without
    held-out poses (what a resume then showed: 0 test poses)."""
    if ros2_missing():
        pytest.skip(ros2_missing())
    ros.start_command("launch", ["ros2", "launch", "laser_calib_nodes", "hardware.launch.py",
                                 f"output_dir:={tmp_path / 'out'}", f"robot:={ROBOT}", f"calibration:={ROBOT}",
                                 f"arm_params:={EXAMPLE_ARM}", "repeats:=2"])  # refused before the files are read
    assert ros.wait_exit("launch", 60) != 0
    log = ros.log("launch")
    assert "process started" not in log and "Traceback" not in log, log
    errors = [line for line in log.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and "repeats: not an argument of this launch file, it would be ignored" \
        in errors[0], log
    assert not (tmp_path / "out").exists()


def test_launch_refuses_a_sequencer_parameter_given_as_its_argument(ros, tmp_path):
    """record_images:=true, unseen_limit:=0, resume:=auto: the sequencer's parameters, which the
    nodes README writes as name:=value; `ros2 launch` dropped them silently (a bag without images).
    Refused now, one line saying where such a parameter goes; the real command line."""
    if ros2_missing():
        pytest.skip(ros2_missing())
    ros.start_command("launch", ["ros2", "launch", "laser_calib_nodes", "session.launch.py",
                                 f"output_dir:={tmp_path / 'out'}", "record_images:=true"])
    assert ros.wait_exit("launch", 60) != 0
    log = ros.log("launch")
    assert "process started" not in log and "Traceback" not in log, log
    errors = [line for line in log.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and ("record_images: a parameter of the sequencer, not an argument of this launch file: "
                                 "it would be ignored; set it in the sequencer's section of a parameter file given "
                                 "as params:=FILE") in errors[0], log
    assert not (tmp_path / "out").exists()


MISSPELT = """import sys
from laser_calib.io.errors import InputError
from laser_calib_nodes.arguments import refuse_ignored_arguments
from laser_calib_nodes import graph
try:
    refuse_ignored_arguments(sys.argv[2:], getattr(graph, sys.argv[1]))
    print("taken")
except InputError as exc:
    print(f"refused: {exc}")"""


def test_a_misspelt_launch_argument_is_refused_an_including_files_own_is_not():
    """hardware.launch.py arm_param:=arm.yaml (for arm_params): launch dropped it and the arm driver
    ran the example Dynamixel file, its port, ids and zero ticks, on whatever adapter was there.
    (graph's arguments name installed files: the workspace's environment.)"""
    import subprocess
    import sys
    from ros_harness import workspace_env

    def check(spec: str, *argv: str) -> str:
        return subprocess.run([sys.executable, "-c", MISSPELT, spec, *argv], capture_output=True, text=True,
                              timeout=60, env=workspace_env(), check=True).stdout.strip()

    assert check("HARDWARE_ARGS", "output_dir:=s", "arm_param:=arm.yaml") == (
        "refused: arm_param: not an argument of this launch file (did you mean arm_params?): it would be ignored")
    assert check("SESSION_ARGS", "ouput_dir:=s").startswith("refused: ouput_dir: not an argument of this launch "
                                                          "file (did you mean output_dir?)")
    # another file's own arguments, when one includes this launch file: passed over
    assert check("HARDWARE_ARGS", "calibration_file:=c.yaml", "use_sim_time:=true", "namespace:=rig1") == "taken"


HARDWARE_GRAPH = """import json, sys
from laser_calib.io.errors import InputError
from laser_calib_nodes.graph import HARDWARE_ARGS, hardware_nodes, share
values = {name: default for name, (default, _) in HARDWARE_ARGS.items()}
values.update(arm_params=share("config", "dynamixel_arm.yaml"))
values.update(dict(item.split("=", 1) for item in sys.argv[1:]), test_poses="5", seed="3")
try:
    print(json.dumps({spec.executable: spec.params for spec in hardware_nodes(values)}))
except InputError as exc:
    print(f"refused: {exc}")"""


def test_the_hardware_graph_takes_held_out_poses_and_refuses_files_it_would_misread(ros, tmp_path):
    """On a real arm the held-out poses are the report's before/after: hardware.launch.py's
    test_poses (and the generator's span and seed) reach its sequencer. The arm_driver runs the
    Dynamixel backend whatever its file says: an arm file keyed 'arm:' (which ROS does not give
    the node) ran the simulated arm, a session measured by nobody; such a file, and a screen
    calibration that is not YAML (a 9-line parser dump, after the arm's torque was on), are
    refused in one line before any node starts."""
    import json
    from laser_calib.vision.camera import default_camera, save_calibration
    save_calibration(default_camera().ideal_calibration(), tmp_path / "screen.yaml")
    (tmp_path / "arm.yaml").write_text("arm:\n  ros__parameters:\n    dynamixel.ids: [1, 2, 3, 4]\n")
    (tmp_path / "broken.yaml").write_text("fx: [1, 2\nfy: 3\n")

    def graph(**files):
        given = {"output_dir": str(tmp_path / "out"), "robot": str(ROBOT), "calibration": str(tmp_path / "screen.yaml"),
                 **files}
        out = ros.run([sys.executable, "-c", HARDWARE_GRAPH, *(f"{k}={v}" for k, v in given.items())])
        assert out.returncode == 0, out
        return out.stdout.strip()

    params = json.loads(graph())
    assert (params["sequencer"]["test_poses"], params["sequencer"]["seed"], params["sequencer"]["span"]) == \
        (5, 3, "whole"), params
    assert params["arm_driver"]["backend"] == "dynamixel", params
    assert graph(arm_params=tmp_path / "arm.yaml") == (
        f"refused: arm_params: {tmp_path / 'arm.yaml'} has no 'arm_driver: ros__parameters:' section (its top-level "
        "keys: arm): the arm_driver would take none of it")
    assert graph(calibration=tmp_path / "broken.yaml") == (
        f"refused: {tmp_path / 'broken.yaml'}: line 2: not valid YAML (expected ',' or ']', but got ':')")


def test_resume_with_other_spot_frames_is_refused(ros, tmp_path):
    """frames (spot frames averaged per pose) sets each sample's noise, and the estimate gives every
    pose one spot sigma: a resume with frames:=1 on a session of 3 measured its remaining poses with
    sqrt(3) times the noise, unsaid. Now it is refused as another plan is; the default given (a
    resume with its arguments left out) takes the recorded value, and says so; settle.hold_time,
    which does not change a sample's noise, is used with a WARN as the other settings are."""
    out = tmp_path / "session"
    ros.start("first", *ros_params(f"robot:={ROBOT}", f"output_dir:={out}", "wait_timeout:=1.0", *FIRST,
                                   "frames:=5"), node="sequencer")
    assert ros.wait_exit("first", 60) == 3, ros.log("first")
    ros.start("fewer", *ros_params(f"robot:={ROBOT}", f"output_dir:={out}", "wait_timeout:=1.0", "frames:=1"),
              node="sequencer")
    assert ros.wait_exit("fewer", 60) == 2, ros.log("fewer")
    lines = [line for line in ros.log("fewer").splitlines() if line.strip()]
    assert lines[-1] == (f"error: {out} holds a partial session whose poses average 5 spot frames each, given "
                         "frames:=1: the poses left would carry another noise than those measured, which the "
                         "estimate cannot tell apart; resume with frames:=5 (or leave it out) or choose another "
                         "output_dir"), ros.log("fewer")
    ros.start("defaults", *ros_params(f"robot:={ROBOT}", f"output_dir:={out}", "wait_timeout:=1.0",
                                      "settle.hold_time:=0.5"), node="sequencer")
    assert ros.wait_exit("defaults", 60) == 3, ros.log("defaults")
    log = ros.log("defaults")
    assert "resume: 5 spot frames per pose, as the session's poses were measured" in log, log
    warnings = [line for line in log.splitlines() if "WARN" in line]
    assert len(warnings) == 1 and "settle.hold_time is 0.5, the session's previous run used 0.2" in warnings[0], log
