"""A measured joint reading a little beyond its joint's limit (the arm settled against the stop,
a limit written rounded) is kept; one far beyond (degrees, another arm's file) is refused in
one line; a pose list the arm is sent to stays inside the limits exactly. Before, a reading
1e-9 rad past a limit refused the whole session with exit 2."""

from __future__ import annotations

import numpy as np
import pytest

from cli_status import exit_status
from laser_calib.io.errors import InputError
from laser_calib.io.samples import READING_SLACK, format_samples, load_samples
from laser_calib.model.robot_file import dump_robot
from laser_calib.session.poses import load_poses
from laser_calib.sim.simulation import bundled_robot, paper_session

ROBOT = bundled_robot("paper-4dof")
JOINT = 1  # q2: the 4-DOF arm's narrowest range, +-20 deg
TRAVEL = ROBOT.q_max[JOINT] - ROBOT.q_min[JOINT]


def _samples_past_the_limit(folder, fraction: float):
    samples = paper_session("paper-4dof", 0, n_per_span=6).samples
    samples.q[3, JOINT] = ROBOT.q_max[JOINT] + fraction * TRAVEL
    (folder / "robot.yaml").write_text(dump_robot(ROBOT))
    (folder / "samples.csv").write_text(format_samples(samples))
    return folder / "robot.yaml", folder / "samples.csv"


def test_a_reading_just_past_a_limit_is_kept(tmp_path):
    robot, samples = _samples_past_the_limit(tmp_path, READING_SLACK / 4)
    assert load_samples(samples, ROBOT).q[3, JOINT] > ROBOT.q_max[JOINT]
    assert exit_status(["estimate", "--robot", str(robot), "--samples", str(samples), "--out",
                        str(tmp_path / "out")]) == 0


def test_a_reading_far_past_a_limit_is_one_line(tmp_path):
    _, samples = _samples_past_the_limit(tmp_path, 4 * READING_SLACK)
    with pytest.raises(InputError, match=r"pose 3, field q2: .* rad outside the joint range .* by more than 1 % "
                                         r"of its travel"):
        load_samples(samples, ROBOT)


def test_a_pose_list_stays_inside_the_limits(tmp_path):
    q = np.zeros(ROBOT.n_joints)
    q[JOINT] = ROBOT.q_max[JOINT] + READING_SLACK / 4 * TRAVEL
    path = tmp_path / "poses.csv"
    path.write_text("pose," + ",".join(f"q{i + 1}" for i in range(ROBOT.n_joints)) + "\n0,"
                    + ",".join(repr(float(v)) for v in q) + "\n")
    with pytest.raises(InputError, match=r"pose 0, field q2: .* rad outside the joint range \[[^]]*\]$"):
        load_poses(path, ROBOT)


def test_one_joint_in_degrees_within_a_turn_is_named_as_degrees(tmp_path):
    """q2 (+-20 deg) written in degrees: its readings are under a turn, so the first refused one
    (a few degrees) did not look like degrees and the line gave no hint of the units."""
    samples = paper_session("paper-4dof", 0, n_per_span=6).samples
    samples.q[:, JOINT] = np.degrees(samples.q[:, JOINT])
    assert ROBOT.q_max[JOINT] < abs(samples.q[0, JOINT]) < 2 * np.pi   # the first refused reading
    (tmp_path / "samples.csv").write_text(format_samples(samples))
    with pytest.raises(InputError, match=r"field q2: .* this looks like degrees"):
        load_samples(tmp_path / "samples.csv", ROBOT)


def test_one_reading_past_a_limit_is_not_said_to_be_degrees(tmp_path):
    _, samples = _samples_past_the_limit(tmp_path, 4 * READING_SLACK)
    with pytest.raises(InputError) as refused:
        load_samples(samples, ROBOT)
    assert "degrees" not in str(refused.value)
