"""A partial session resumed with another robot than its robot.yaml is refused before
anything is measured: the sequencer (`ros2 run`), scripts/run-session's graph and
`ros2 launch` each say it in one line naming the folder and both robots (exit 2 for
the node and run-session). Compared are the models, so one length changed is refused
even under the same name; the session's robot, or its own robot.yaml, resumes."""

from __future__ import annotations

import sys

from ros_harness import ROBOT, ros2_missing

OTHER = ROBOT.parent / "manipulator_4dof.yaml"


def partial_session(tmp_path):
    from laser_calib.model.robot_file import load_robot
    from laser_calib.session.folder import SessionDir
    from laser_calib.session.poses import generate_poses
    robot = load_robot(ROBOT)
    session = SessionDir(tmp_path / "session")
    session.start(robot, generate_poses(robot, 5, "small", 0), {"robot": str(ROBOT)})
    return session.path


def error_lines(log: str) -> list[str]:
    assert "Traceback" not in log, log
    return [line for line in log.splitlines() if "error" in line.lower()]


def test_resume_with_another_robot_is_refused(ros, tmp_path):
    out = partial_session(tmp_path)
    changed = tmp_path / "changed.yaml"
    changed.write_text(ROBOT.read_text().replace("d: 0.", "d: 0.01", 1))
    for name, robot in (("other", OTHER), ("changed", changed)):
        ros.start(name, "-p", f"robot:={robot}", "-p", f"output_dir:={out}", node="sequencer")
        assert ros.wait_exit(name, 60) == 2, ros.log(name)
        lines = error_lines(ros.log(name))
        assert len(lines) == 1 and lines[0].startswith(f"error: {out}: "), ros.log(name)
        assert "humanoid_arm_7dof" in lines[0] and str(robot) in lines[0], lines[0]
    assert "another model (its 'joints' differs)" in lines[0]
    assert "is 'manipulator_4dof'" in error_lines(ros.log("other"))[0]
    # run-session's graph: refused before any node starts
    result = ros.run([sys.executable, "-m", "laser_calib_nodes.graph", f"output_dir:={out}", f"robot:={OTHER}"])
    assert result.returncode == 2, result
    assert result.stderr.startswith(f"run-session: {out}: ") and result.stderr.count("\n") == 1, result
    assert str(OTHER) in result.stderr and "'manipulator_4dof'" in result.stderr and not (out / "logs").exists()
    # the session's robot file, or the session's own robot.yaml: resumed (stopped here once it waits for the arm)
    for name, robot in (("same", ROBOT), ("own", out / "robot.yaml")):
        ros.start(name, "-p", f"robot:={robot}", "-p", f"output_dir:={out}", "-p", "wait_timeout:=1.0",
                  node="sequencer")
        assert ros.wait_exit(name, 60) == 3, ros.log(name)
        assert f"resuming {out}: 0 of 5 poses" in ros.log(name), ros.log(name)


def test_launch_resume_with_another_robot_is_refused_before_any_node_starts(ros, tmp_path):
    if ros2_missing():
        import pytest
        pytest.skip(ros2_missing())
    out = partial_session(tmp_path)
    ros.start_command("launch", ["ros2", "launch", "laser_calib_nodes", "session.launch.py", f"output_dir:={out}",
                                 f"robot:={OTHER}"])
    assert ros.wait_exit("launch", 60) != 0
    log = ros.log("launch")
    assert "process started" not in log and "Traceback" not in log, log
    errors = [line for line in log.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and str(out) in errors[0] and str(OTHER) in errors[0], log


def test_a_resumed_simulation_with_another_true_robot_is_refused(ros, tmp_path):
    """The sim arm_driver writes its true robot into the session (robot_true.yaml, the report's truth):
    resumed with other sim.errors it measured the remaining poses on another arm and overwrote the
    truth, unsaid. Now refused in one line, exit 2, the file kept; the same simulation runs on."""
    truth = tmp_path / "robot_true.yaml"
    args = ("-p", f"robot:={ROBOT}", "-p", f"sim.true_robot_out:={truth}")
    ros.start("first", *args, node="arm_driver")
    ros.wait_log("first", "publishing at", 60)
    written = truth.read_text()
    ros.stop("first")
    ros.start("other", *args, "-p", "sim.errors:=random", node="arm_driver")
    assert ros.wait_exit("other", 60) == 2, ros.log("other")
    lines = error_lines(ros.log("other"))
    assert lines[-1] == (f"error: sim.true_robot_out {truth} holds another true robot (the session's, resumed with "
                         "other sim.errors or sim.seed?): its poses were measured on that arm; give the session's "
                         "simulation or another output folder"), ros.log("other")
    assert truth.read_text() == written
    ros.start("same", *args, node="arm_driver")
    ros.wait_log("same", "publishing at", 60)
