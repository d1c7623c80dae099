"""The nodes take the arm's URDF from /robot_description, as robot_state_publisher
publishes it (std_msgs/String, reliable + transient local, depth 1; a stand-in
keeps that contract, robot_state_publisher itself is not installed here): the
estimator started with `ros2 run` estimates a session with the URDF robot; a
node whose description never comes says so once and exits 2."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import yaml

from ros_harness import PARAMS, ROOT, ros2_missing

DATA = ROOT / "test" / "core" / "data"
URDF = DATA / "paper_arm_7dof.urdf"
PUBLISHER = Path(__file__).resolve().parent / "description_publisher.py"
DH_ROBOT = ROOT / "config" / "robots" / "humanoid_arm_7dof.yaml"


def lasers_file(tmp_path: Path) -> Path:
    """The robot file beside a /robot_description: base, tip and the paper arm's lasers, no urdf:."""
    data = yaml.safe_load(DH_ROBOT.read_text())
    path = tmp_path / "lasers.yaml"
    path.write_text(yaml.safe_dump({"base": "link0", "tip": "link7_theta",
                                    **{k: data[k] for k in ("slm", "lasers", "screen") if k in data}}))
    return path


def test_estimator_estimates_with_the_robot_of_robot_description(ros, tmp_path):
    reason = ros2_missing()
    if reason:
        pytest.skip(reason)
    from laser_calib.cli.main import main
    from laser_calib.io.samples import load_samples, save_samples
    from laser_calib.model.robot_file import load_robot, robot_from_dict

    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-7dof", "--seed", "0", "--out", str(sim)]) == 0
    lasers = lasers_file(tmp_path)
    urdf_robot = load_robot(lasers, description=URDF.read_text())
    ros.start_command("robot_state_publisher", [sys.executable, str(PUBLISHER), str(URDF)])
    ros.start_command("estimator", ["ros2", "run", "laser_calib_nodes", "estimator", "--ros-args",
                                    "--params-file", str(PARAMS), "-p", f"robot:={lasers}",
                                    "-p", "robot_description_topic:=/robot_description"])
    # one gross outlier (pose 7, laser 1, 50 mm off): the service's default request is the
    # robust fit of the command line and the sequencer, which rejects and lists it
    samples = load_samples(sim / "case3_cal.csv")
    samples.spots[7, 0, 0] += 0.050
    save_samples(samples, tmp_path / "with_outlier.csv")
    out = ros.client("estimate-csv", str(tmp_path / "with_outlier.csv"))
    assert out["success"], out["message"]
    result = json.loads(out["result_json"])
    assert result["robust"] and {"pose": 7, "laser": 1} in result["rejected_spots"], result["rejected_spots"]
    # the URDF robot's parameters (7 per joint placement, then the SLM's), not the D-H file's
    assert out["names"] == list(urdf_robot.param_names)
    assert out["sample_count"] == 60
    assert all(after < before / 10 for before, after in zip(out["before_mean"], out["after_mean"]))
    assert "with the URDF of /robot_description" in result["inputs"]["robot"]
    calibrated = robot_from_dict(yaml.safe_load(out["calibrated_robot_yaml"]))
    assert calibrated.chain is not None and calibrated.chain.tip_links == ("link7_theta",)
    log = ros.log("estimator")
    assert log.count("waiting up to 30 s for the robot description on /robot_description") == 1, log
    # the launch files take the argument
    shown = ros.run(["ros2", "launch", "laser_calib_nodes", "session.launch.py", "--show-args"], timeout=90)
    assert "'robot_description_topic'" in shown.stdout, shown
    assert ros.stop("estimator") == 0
    assert "Traceback" not in ros.log("estimator")


def test_a_description_that_never_comes_is_one_line_and_exit_2(ros, tmp_path):
    ros.start("estimator", "-p", f"robot:={lasers_file(tmp_path)}", "-p", "robot_description_topic:=/nobody",
              "-p", "robot_description_timeout:=2.0")
    assert ros.wait_exit("estimator", 60) == 2
    log = ros.log("estimator")
    assert log.count("waiting up to 2 s for the robot description on /nobody") == 1, log
    assert "error: no robot description on /nobody within 2 s" in log, log
    assert "Traceback" not in log, log
