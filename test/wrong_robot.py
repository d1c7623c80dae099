"""A robot file that does not describe the robot its data came from: the paper's 4-DOF arm
simulated, its joint 4 (revolute in the data) marked prismatic in the file. The fit then
moves beams off the screen to drop them: NOT A CALIBRATION (estimation/failures.py)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from laser_calib.cli.main import main
from laser_calib.model.robot_file import load_robot, save_robot


def prismatic_mismatch(folder: Path, poses_per_span: int = 8) -> tuple[Path, Path]:
    """The simulation's folder (2 poses_per_span poses) and the wrong robot file, both written under folder."""
    sim, wrong = folder / "sim", folder / "prismatic.yaml"
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--poses-per-span", str(poses_per_span),
                 "--out", str(sim)]) == 0
    robot = load_robot(sim / "robot_nominal.yaml")
    joints = list(robot.joints)
    joints[3] = replace(joints[3], prismatic=True)
    save_robot(replace(robot, joints=tuple(joints)), wrong)
    return sim, wrong
