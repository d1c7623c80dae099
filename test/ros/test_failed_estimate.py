"""A session whose fit is no calibration (the robot file the fit uses marks a revolute joint
prismatic; the simulated arm is the right one): the sequencer writes the files, says so,
and ends with status 4, whether it estimates in its own process or through the
estimator's Estimate service (which fits with its own robot file), and with its diagnosis, which
starts from the failed fit and refuses the robot file: said beside the failure (it was exit 2, as
for bad input, the failure unsaid)."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from ros_harness import ROOT

ROBOT = ROOT / "config" / "robots" / "manipulator_4dof.yaml"
# a contrast no spot reaches (a rendered spot's smoothed contrast is 25-70 DN), below the 255 of an 8-bit
# image, which the detector refuses as a threshold nothing can reach: the lasers as if off
NO_SPOT = 254.0


@pytest.mark.parametrize("mode, diagnose", [("local", False), ("service", False), ("local", True)])
def test_a_fit_that_is_no_calibration_ends_the_session_with_status_4(ros, tmp_path, mode, diagnose):
    from laser_calib.model.robot_file import load_robot, save_robot
    robot = load_robot(ROBOT)
    joints = list(robot.joints)
    joints[3] = replace(joints[3], prismatic=True)
    wrong = tmp_path / "prismatic.yaml"
    save_robot(replace(robot, joints=tuple(joints)), wrong)
    out = tmp_path / "out"
    out.mkdir()
    ros.start("estimator", "-p", f"robot:={wrong if mode == 'service' else ROBOT}")
    ros.start("arm_driver", "-p", f"robot:={ROBOT}", "-p", "sim.joint_speed:=4.0")
    ros.start("camera_sim")
    ros.start("spot_detector")
    ros.start("sequencer", "-p", f"robot:={wrong}", "-p", f"output_dir:={out}", "-p", "poses:=16",
              "-p", "span:=whole", "-p", "seed:=5", "-p", f"estimate.mode:={mode}",
              "-p", f"estimate.diagnose:={str(diagnose).lower()}")
    code = ros.wait_exit("sequencer", 240)
    log = ros.log("sequencer")
    assert code == 4, log[-3000:]
    assert "estimate failed: " in log and f"its files are in {out}" in log and "Traceback" not in log, log[-3000:]
    assert "NO CALIBRATION" in (out / "robot_calibrated.yaml").read_text()
    # its refusal here ('diagnosis skipped: robot: the nominal model's beams meet the screen at ...'), or its verdict
    assert ("; diagnosis" in log) == diagnose, log[-3000:]
    if mode == "local":  # its files name the session's files it fitted, as `laser-calib estimate` names its inputs
        assert json.loads((out / "result.json").read_text())["inputs"] == {
            "robot": str(out / "robot.yaml"), "samples": str(out / "samples.csv"),
            "test": None, "compensator": None}


# The small plans of two failure paths (3 and 4 poses of the 4-DOF arm) give no more values than errors:
# the sequencer refuses such a plan at its start unless the estimate has the prior (enough_poses).
def test_poses_whose_spots_are_not_seen_are_warned_of_and_kept(ros, tmp_path):
    """A detector threshold no spot reaches: each pose's line is a WARN naming the lasers not
    seen (it was INFO, '0/2 spots seen', easy to miss while the arm moves on), so is the session's
    summary line, and every pose is still written as measured; the estimate then has no spot to
    fit and says so."""
    out = tmp_path / "out"
    ros.start("arm_driver", "-p", f"robot:={ROBOT}", "-p", "sim.joint_speed:=4.0")
    ros.start("camera_sim")
    ros.start("spot_detector", "-p", f"min_peak_dn:={NO_SPOT}")
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "poses:=3",
              "-p", "test_poses:=0", "-p", "seed:=5", "-p", "estimate.mode:=local",
              "-p", "estimate.diagnose:=false", "-p", "estimate.prior:=true")
    code = ros.wait_exit("sequencer", 240)
    log = ros.log("sequencer")
    assert code == 2 and "Traceback" not in log, log[-3000:]
    warned = [line for line in log.splitlines() if "[WARN]" in line and "0/2 spots seen" in line]
    assert len(warned) == 3 and all("laser 1 and laser 2 not seen" in line for line in warned), log[-3000:]
    assert "[WARN]" in log and "all 3 poses measured;" in log and "; 6 of 6 spots of the poses to fit were not seen" \
        in log, log[-3000:]
    assert len((out / "samples.csv").read_text().strip().splitlines()) == 1 + 3


def test_a_pose_that_fails_is_named_as_its_progress_line_would(ros, tmp_path):
    """The camera stops after two poses: the third fails with exit 3, named 'pose 3/N (id ...)' as
    the progress lines count (it said 'pose 2 (step 3)' after 'pose 2/N (id 1) measured', so the
    user took the second pose for the failed one); the two measured poses are kept."""
    import re
    out = tmp_path / "out"
    ros.start("arm_driver", "-p", f"robot:={ROBOT}", "-p", "sim.joint_speed:=4.0")
    ros.start("camera_sim")
    ros.start("spot_detector")
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "poses:=6",
              "-p", "test_poses:=0", "-p", "estimate.mode:=none", "-p", "frame_timeout:=3.0")
    ros.wait_log("sequencer", " measured in ", 240, count=2)
    ros.stop("camera_sim")
    assert ros.wait_exit("sequencer", 120) == 3, ros.log("sequencer")[-3000:]
    log = ros.log("sequencer")
    measured = re.findall(r"pose (\d+)/6 \(id \d+\) measured in", log)
    failed = re.findall(r"pose (\d+)/6 \(id \d+\): fewer than 3 spot frames", log)
    assert failed == [str(len(measured) + 1)], log[-3000:]
    assert len((out / "samples.csv").read_text().strip().splitlines()) == 1 + len(measured)


def test_a_run_whose_first_poses_see_no_spot_ends_early_and_keeps_them(ros, tmp_path):
    """Lasers off (a threshold no spot reaches): the session measured every pose before it failed.
    Now this run's first unseen_limit poses without a spot end it, one line, exit 2, the poses kept."""
    out = tmp_path / "out"
    ros.start("arm_driver", "-p", f"robot:={ROBOT}", "-p", "sim.joint_speed:=4.0")
    ros.start("camera_sim")
    ros.start("spot_detector", "-p", f"min_peak_dn:={NO_SPOT}")
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "poses:=6",
              "-p", "test_poses:=0", "-p", "seed:=5", "-p", "estimate.mode:=local", "-p", "unseen_limit:=2")
    code = ros.wait_exit("sequencer", 240)
    log = ros.log("sequencer")
    assert code == 2 and "Traceback" not in log, log[-3000:]
    assert "no spot seen in this run's first 2 poses" in log and "unseen_limit:=0" in log, log[-3000:]
    assert len((out / "samples.csv").read_text().strip().splitlines()) == 1 + 2  # the header and the 2 poses


def test_an_estimator_that_dies_before_answering_ends_the_session_with_status_3(ros, tmp_path):
    """The estimator is killed (SIGKILL: a crash) while the last pose is measured, so the sequencer's
    request is never answered. The sequencer waited its whole estimate.timeout (600 s) before it said
    so; now it sees the service leave the graph (the estimator's DDS lease, about 20 s) and ends with
    status 3 at once, naming where the measured poses are kept."""
    import os
    import signal
    import time
    out = tmp_path / "out"
    ros.start("estimator", "-p", f"robot:={ROBOT}")
    ros.start("arm_driver", "-p", f"robot:={ROBOT}", "-p", "sim.joint_speed:=4.0")
    ros.start("camera_sim")
    ros.start("spot_detector")
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "poses:=4",
              "-p", "test_poses:=0", "-p", "seed:=5", "-p", "estimate.mode:=service",
              "-p", "estimate.diagnose:=false", "-p", "estimate.prior:=true")
    ros.wait_log("sequencer", " measured in ", 240, count=3)
    os.killpg(ros.procs["estimator"].pid, signal.SIGKILL)
    killed = time.monotonic()
    code = ros.wait_exit("sequencer", 120)
    log = ros.log("sequencer")
    assert code == 3 and "Traceback" not in log, log[-3000:]
    assert "went away before answering" in log and f"the data are in {out}" in log, log[-3000:]
    assert time.monotonic() - killed < 90, log[-3000:]  # the lease, not the 600 s timeout
    assert len((out / "samples.csv").read_text().strip().splitlines()) == 1 + 4


def test_a_plan_too_small_for_its_estimate_is_refused_before_the_first_pose(ros, tmp_path):
    """4 poses of the 4-DOF arm: 16 spot values for the 16 errors they determine. The session was
    measured in full, then the estimate refused it, and a resume could not add poses (the plan of a
    partial session is fixed by what was measured). Now the sequencer refuses the plan at its
    start, one line, exit 2, before any pose (no arm needed); estimate.prior:=true or
    estimate.mode:=none take such a plan (the small plans above)."""
    out = tmp_path / "out"
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "poses:=4",
              "-p", "test_poses:=2")
    assert ros.wait_exit("sequencer", 60) == 2, ros.log("sequencer")[-2000:]
    lines = [line for line in ros.log("sequencer").splitlines() if line.strip()]
    assert lines[-1] == ("error: the plan's 4 poses give 16 spot values for the 16 errors they determine: as many "
                         "fit exactly, and the estimate after the last pose would refuse them; plan more poses "
                         "(poses:=6 or more), or estimate.prior:=true, or estimate.mode:=none"), lines[-3:]
    assert not (out / "samples.csv").exists()

