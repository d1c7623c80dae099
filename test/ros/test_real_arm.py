"""A session against a stand-in ros2_control arm (jtc_standin.py): the sequencer's commands are
what joint_trajectory_controller accepts, with the remapping docs/real-arm.md gives."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from ros_harness import ROBOT

JOINTS = [f"arm_{i + 1}_joint" for i in range(7)]
POSES = 4


def start_standin(ros, name="arm_controller"):
    log = ros.tmp / f"{name}.log"
    with open(log, "ab") as handle:
        proc = subprocess.Popen([sys.executable, str(Path(__file__).with_name("jtc_standin.py")), str(ROBOT),
                                 ",".join(JOINTS)], env=ros.env, stdout=handle, stderr=subprocess.STDOUT,
                                start_new_session=True)
    ros.procs[name], ros.logs[name] = proc, log
    return proc


def test_session_on_a_joint_trajectory_controller(ros, tmp_path):
    from laser_calib.io.samples import load_samples
    from laser_calib.session.poses import load_poses
    from laser_calib.model.robot_file import load_robot
    start_standin(ros)
    out = tmp_path / "out"
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", f"poses:={POSES}",
              "-p", "span:=small", "-p", "estimate.mode:=none", "-p", "move.joint_speed:=2.0",
              "-p", f"joint_names:=[{','.join(JOINTS)}]",
              "-r", "joint_trajectory:=/arm_controller/joint_trajectory")
    assert ros.wait_exit("sequencer", 120) == 0, ros.log("sequencer")[-3000:]
    controller = ros.log("arm_controller")
    assert "rejected" not in controller, controller
    assert controller.count("accepted") == POSES
    robot = load_robot(ROBOT)
    poses = load_poses(out / "poses.csv", robot)
    samples = load_samples(out / "samples.csv", robot)
    # joint_states in the controller's order, with a gripper: mapped back to the robot's joints by name
    assert np.all(np.abs(samples.q - poses.q) < 0.003)   # settle.position_tolerance


def test_joint_names_missing_from_joint_states_is_one_line(ros, tmp_path):
    start_standin(ros)
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={tmp_path / 'out'}", "-p", "poses:=2",
              "-p", "estimate.mode:=none", "-p", "wait_timeout:=5.0",
              "-r", "joint_trajectory:=/arm_controller/joint_trajectory")
    assert ros.wait_exit("sequencer", 60) == 2
    lines = [line for line in ros.log("sequencer").splitlines() if line.strip()]
    # said at once (a WARN), the end after wait_timeout: another publisher's message is ignored, and
    # the arm's may come later
    assert "[sequencer]: joint_states has 8 joints" in lines[-1] and "give parameter joint_names" in lines[-1]
    assert "Traceback" not in ros.log("sequencer")
