"""The estimator's 'stream' input takes each joint's reading by its name in joint_states, as
the sequencer does: a joint_state_broadcaster lists the joints in its own order and may list
more (a gripper). Before, the estimator took the positions in the message's order: readings
in another order went to the wrong joints without a word, and one more joint had every
message refused."""

from __future__ import annotations

from ros_harness import ROBOT

POSES = 12


def test_stream_joints_are_taken_by_name(ros):
    ros.start("estimator", "-p", f"robot:={ROBOT}", "-p", "input:=stream", "-p", "markers:=false")
    ros.wait_log("estimator", "input 'stream'", 60)
    for layout in ("robot", "reversed", "gripper"):
        assert ros.client("reset")["success"]
        got = ros.client("stream", str(ROBOT), layout, str(POSES))
        # exact spots of the nominal robot: the online EKF finds no error when every reading is its joint's
        assert got["sample_count"] == POSES, (layout, got, ros.log("estimator")[-2000:])
        assert got["largest_error"] < 1e-6, (layout, got)
    log = ros.log("estimator")
    assert "ignored" not in log and "Traceback" not in log, log


def test_stream_names_a_missing_joint_once(ros):
    ros.start("estimator", "-p", f"robot:={ROBOT}", "-p", "input:=stream", "-p", "markers:=false",
              "-p", "joint_names:=[j1, j2, j3, j4, j5, j6, j7]")
    ros.wait_log("estimator", "input 'stream'", 60)
    # every joint_states refused: the estimator never counts a pose, so 2 s of quiet suffice
    got = ros.client("stream", str(ROBOT), "robot", "3", "2")
    assert got["sample_count"] == 0
    errors = [line for line in ros.log("estimator").splitlines() if "joint_states ignored" in line]
    assert len(errors) == 1 and "joint 'j1' (parameter joint_names) is not in joint_states" in errors[0], errors
    assert ros.stop("estimator") == 0
