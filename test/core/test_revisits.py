"""Rows sharing a pose id are repeated visits (conventions.md); readings of one id far
apart are two poses under one id: a warning naming the file, pose and joint."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from laser_calib.cli.main import main
from laser_calib.io.revisits import REVISIT_SPREAD, revisit_warnings
from laser_calib.io.samples import load_samples, save_samples
from laser_calib.io.sensor_samples import load_sensor_samples, save_sensor_samples

JOINTS = ("q1", "q2", "q3")


def test_visits_within_the_settle_tolerance_are_one_pose():
    rng = np.random.default_rng(0)
    q = np.tile(rng.uniform(-1, 1, (4, 3)), (3, 1))
    q += rng.uniform(-0.003, 0.003, q.shape)  # each visit within the sequencer's settle tolerance of its goal
    assert revisit_warnings(np.tile(np.arange(4), 3), q, JOINTS, "s.csv") == []


def test_readings_of_one_id_far_apart_are_named_with_their_joint():
    q = np.zeros((4, 3))
    q[3, 2] = 3 * REVISIT_SPREAD
    warnings = revisit_warnings(np.array([0, 1, 2, 1]), q, JOINTS, "s.csv")
    assert len(warnings) == 1
    assert warnings[0].startswith("s.csv: a pose id repeated with different joint readings: pose 1 (q3 readings 0.06 "
                                  "apart)")


def test_unique_ids_give_no_warning():
    assert revisit_warnings(np.arange(3), np.arange(9.0).reshape(3, 3), JOINTS, "s.csv") == []


def test_estimate_prints_the_warning_and_still_fits(tmp_path, capsys):
    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--poses-per-span", "8", "--out", str(sim)]) == 0
    samples = load_samples(sim / "samples.csv")
    pose = samples.pose.copy()
    pose[5] = pose[3]  # another pose's row under pose 3's id
    save_samples(type(samples)(pose, samples.stamp, samples.q, samples.spots), tmp_path / "reused.csv")
    assert main(["estimate", "--robot", str(sim / "robot_nominal.yaml"), "--samples", str(tmp_path / "reused.csv"),
                 "--out", str(tmp_path / "out")]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "pose id" in line]
    assert len(lines) == 1 and lines[0].startswith(f"warning: {tmp_path / 'reused.csv'}: a pose id repeated with "
                                                   "different joint readings: pose 3 (q")


def test_diagnose_notes_the_reused_id(tmp_path, capsys):
    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--poses-per-span", "8", "--out", str(sim)]) == 0
    samples = load_samples(sim / "samples.csv")
    pose = samples.pose.copy()
    pose[5] = pose[3]
    save_samples(type(samples)(pose, samples.stamp, samples.q, samples.spots), tmp_path / "reused.csv")
    assert main(["diagnose", "--robot", str(sim / "robot_nominal.yaml"), "--samples", str(tmp_path / "reused.csv"),
                 "--folds", "2", "--max-effects", "0", "--out", str(tmp_path / "out")]) == 0
    assert any(line.startswith("note: samples: a pose id repeated with different joint readings: pose 3")
               for line in capsys.readouterr().out.splitlines())


def test_calibrate_poses_prints_the_warning_for_the_samples_and_the_test_file(tmp_path, capsys):
    data = Path(__file__).resolve().parents[2] / "data" / "real" / "positioner_2axis"
    assert main(["import-positioner", "--data", str(data), "--out", str(tmp_path)]) == 0
    samples = load_sensor_samples(tmp_path / "samples.csv")
    for name, reused, kept in (("cal.csv", 5, 3), ("test.csv", 8, 6)):  # another pose's row under kept's id
        pose = samples.pose.copy()
        pose[reused] = pose[kept]
        save_sensor_samples(replace(samples, pose=pose), tmp_path / name)
    assert main(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "cal.csv"),
                 "--test", str(tmp_path / "test.csv"), "--folds", "0", "--out", str(tmp_path / "out")]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "pose id" in line]
    assert [line.split(" (")[0] for line in lines] == [
        f"warning: {tmp_path / 'cal.csv'}: a pose id repeated with different joint readings: pose 3",
        f"warning: {tmp_path / 'test.csv'}: a pose id repeated with different joint readings: pose 6"]
    warnings = json.loads((tmp_path / "out" / "result.json").read_text())["warnings"]
    assert [w for w in warnings if "pose id" in w] == [line.removeprefix("warning: ") for line in lines]
