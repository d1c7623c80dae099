"""Rows sharing a pose id are repeated visits (conventions.md); readings of one id far
apart are two poses under one id: a warning naming the file, pose and joint. A row
equal to another in readings and measured values is a copy, and a test pose at a
calibration pose's readings is that pose again (the same measurement, or a revisit):
one warning line each, on the console and in the result's warnings."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from laser_calib.cli.main import main
from laser_calib.io.revisits import REVISIT_SPREAD, copy_warnings, heldout_repeat_warnings, revisit_warnings
from laser_calib.io.samples import Samples, load_samples, save_samples
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
    lines = [line for line in capsys.readouterr().err.splitlines() if "pose id" in line]
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
    assert any(line.startswith(f"note: {tmp_path / 'reused.csv'}: a pose id repeated with different joint readings: "
                               "pose 3")
               for line in capsys.readouterr().err.splitlines())


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
    lines = [line for line in capsys.readouterr().err.splitlines() if "pose id" in line]
    assert [line.split(" (")[0] for line in lines] == [
        f"warning: {tmp_path / 'cal.csv'}: a pose id repeated with different joint readings: pose 3",
        f"warning: {tmp_path / 'test.csv'}: a pose id repeated with different joint readings: pose 6"]
    warnings = json.loads((tmp_path / "out" / "result.json").read_text())["warnings"]
    assert [w for w in warnings if "pose id" in w] == [line.removeprefix("warning: ") for line in lines]


def _spots(n_rows: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-0.5, 0.5, (n_rows, 2, 2))


def _samples(q: np.ndarray, spots: np.ndarray, pose=None) -> Samples:
    return Samples(np.arange(len(q)) if pose is None else np.asarray(pose), np.arange(len(q), dtype=float), q, spots)


def test_copied_rows_are_named_with_the_rows_they_copy():
    q = np.random.default_rng(1).uniform(-1, 1, (4, 3))
    spots = _spots(4)
    spots[2, 1] = np.nan  # laser 2 unseen: a copy of the row copies that too
    rows = [0, 1, 2, 3, 2, 0]  # rows 5 and 6 are rows 3 and 1 again, stamps differing
    warnings = copy_warnings(_samples(q[rows], spots[rows], rows), "s.csv")
    assert warnings == [warnings[0]] and warnings[0].startswith(
        "s.csv: 2 of 6 rows repeat an earlier row's joint readings and spots exactly: row 5 = row 3 (pose 2), "
        "row 6 = row 1 (pose 0); no sensor measures twice without noise")


def test_visits_with_new_spots_or_nothing_seen_are_not_copies():
    q = np.tile(np.random.default_rng(1).uniform(-1, 1, (2, 3)), (2, 1))  # readings equal to the encoder count
    spots = _spots(4)  # each visit's own spots
    assert copy_warnings(_samples(q, spots, [0, 1, 0, 1]), "s.csv") == []
    spots[[1, 3]] = np.nan  # two visits of pose 1 that saw nothing: nothing was measured twice
    assert copy_warnings(_samples(q, spots, [0, 1, 0, 1]), "s.csv") == []


def test_point_and_pose_copies_are_found_as_spot_copies():
    q = np.random.default_rng(2).uniform(-1, 1, (3, 2))[[0, 1, 1]]
    position = np.random.default_rng(3).normal(size=(3, 3))[[0, 1, 1]]
    point = Samples(np.arange(3), np.arange(3.0), q, position=position)
    assert copy_warnings(point, "p.csv")[0].startswith("p.csv: 1 of 3 rows repeat an earlier row's joint readings "
                                                       "and measured positions exactly: row 3 = row 2 (pose 2);")


@pytest.mark.parametrize("new, same, said", [
    (0, 4, "4 of 5 test poses repeat a calibration pose of cal.csv (joint readings within 0.02 rad, m if prismatic): "
           "4 with identical spots, the same measurements the fit was given (the test figures over them are "
           "in-sample figures, not held-out ones)"),
    (3, 0, "3 of 5 test poses repeat a calibration pose of cal.csv (joint readings within 0.02 rad, m if prismatic): "
           "3 with new spots, revisits (held out from the fit's measurements but not from its poses"),
    (1, 2, "3 of 5 test poses repeat a calibration pose of cal.csv (joint readings within 0.02 rad, m if prismatic): "
           "2 with identical spots"),
], ids=["the same measurements", "revisits", "both"])
def test_test_poses_at_calibration_poses_are_counted_same_or_revisited(new, same, said):
    rng = np.random.default_rng(4)
    calibration = _samples(rng.uniform(-1, 1, (8, 3)), _spots(8))
    q, spots = rng.uniform(-1, 1, (5, 3)), _spots(5, 1)  # the test set's own poses
    q[:same], spots[:same] = calibration.q[:same], calibration.spots[:same]
    revisited = slice(same, same + new)
    q[revisited] = calibration.q[4:4 + new] + rng.uniform(-0.003, 0.003, (new, 3))  # within the settle tolerance
    warnings = heldout_repeat_warnings(calibration, _samples(q, spots), "cal.csv", "test.csv")
    assert len(warnings) == 1 and warnings[0].startswith(f"test.csv: {said}")
    assert ("with new spots" in warnings[0]) == bool(new)


def test_test_poses_away_from_the_calibration_poses_give_no_warning():
    q = np.random.default_rng(5).uniform(-1, 1, (6, 3))
    near = q[3:] + 2 * REVISIT_SPREAD  # each joint just beyond a revisit's spread
    assert heldout_repeat_warnings(_samples(q[:3], _spots(3)), _samples(near, _spots(3, 1)), "c", "t") == []


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--poses-per-span", "8", "--out",
                 str(folder)]) == 0
    samples = load_samples(folder / "samples.csv")
    every = np.repeat(np.arange(len(samples)), 2)  # a logger writing each sample twice, stamps differing
    save_samples(replace(samples.subset(every), stamp=np.arange(len(every)) * 0.5), folder / "doubled.csv")
    again = replace(samples, spots=samples.spots + np.random.default_rng(6).normal(0, 1e-3, samples.spots.shape))
    save_samples(again, folder / "revisited.csv")  # every pose measured anew
    return folder


def _warnings(lines: list[str], prefix: str) -> list[str]:
    """The lines (prefix removed) of copied rows and of test poses repeating calibration poses."""
    return [line.removeprefix(prefix) for line in lines
            if line.startswith(prefix) and ("rows repeat an earlier row" in line or "test poses repeat" in line)]


@pytest.mark.parametrize("test, said", [
    ("samples.csv", "16 of 16 test poses repeat a calibration pose of {samples} (joint readings within 0.02 rad, m if "
                    "prismatic): 16 with identical spots, the same measurements the fit was given"),
    ("revisited.csv", "16 of 16 test poses repeat a calibration pose of {samples} (joint readings within 0.02 rad, m "
                      "if prismatic): 16 with new spots, revisits"),
], ids=["the calibration file", "revisits"])
def test_estimate_says_when_the_test_set_repeats_the_calibration(sim, tmp_path, capsys, test, said):
    samples = sim / "samples.csv"
    assert main(["estimate", "--robot", str(sim / "robot_nominal.yaml"), "--samples", str(samples),
                 "--test", str(sim / test), "--out", str(tmp_path / "out")]) == 0
    lines = _warnings(capsys.readouterr().err.splitlines(), "warning: ")
    assert len(lines) == 1 and lines[0].startswith(f"{sim / test}: " + said.format(samples=samples))
    assert lines == _warnings(json.loads((tmp_path / "out" / "result.json").read_text())["warnings"], "")


def test_estimate_says_the_rows_a_logger_wrote_twice(sim, tmp_path, capsys):
    doubled = sim / "doubled.csv"
    assert main(["estimate", "--robot", str(sim / "robot_nominal.yaml"), "--samples", str(doubled),
                 "--out", str(tmp_path / "out")]) == 0
    lines = _warnings(capsys.readouterr().err.splitlines(), "warning: ")
    assert len(lines) == 1 and lines[0].startswith(
        f"{doubled}: 16 of 32 rows repeat an earlier row's joint readings and spots exactly: row 2 = row 1 (pose 0), "
        "row 4 = row 3 (pose 1)")
    assert "counted twice in every figure over them (a fit's std understated, the ISO 9283 repeatability RP" in lines[0]
    assert lines == _warnings(json.loads((tmp_path / "out" / "result.json").read_text())["warnings"], "")


def test_diagnose_notes_copies_and_a_test_set_of_calibration_poses(sim, tmp_path, capsys):
    doubled = sim / "doubled.csv"  # every repeated pose without scatter: the level is not tested, no division by 0
    assert main(["diagnose", "--robot", str(sim / "robot_nominal.yaml"), "--samples", str(doubled), "--test",
                 str(sim / "samples.csv"), "--folds", "2", "--max-effects", "0", "--out", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()  # the notes on stderr with the warnings, the results on stdout
    out = captured.err
    assert "note:" not in captured.out
    lines = _warnings(out.splitlines(), "note: ")
    assert [line.split(":")[0] for line in lines] == [str(doubled), str(sim / "samples.csv")]
    assert lines[1].startswith(f"{sim / 'samples.csv'}: 16 of 16 test poses repeat a calibration pose of {doubled}")
    assert lines == _warnings(json.loads((tmp_path / "out" / "diagnosis.json").read_text())["notes"], "")
    assert "repeated poses without any scatter (copied rows?)" in captured.out  # the verdict's evidence


def test_calibrate_poses_says_copies_and_a_test_set_of_calibration_poses(tmp_path, capsys):
    data = Path(__file__).resolve().parents[2] / "data" / "real" / "positioner_2axis"
    assert main(["import-positioner", "--data", str(data), "--out", str(tmp_path)]) == 0
    samples = load_sensor_samples(tmp_path / "samples.csv")
    rows = np.r_[np.arange(len(samples)), 7]  # the 8th sample written again at the end
    save_sensor_samples(replace(samples.subset(rows), stamp=np.r_[samples.stamp, samples.stamp[-1] + 1]),
                        tmp_path / "cal.csv")
    assert main(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "cal.csv"),
                 "--test", str(tmp_path / "samples.csv"), "--folds", "0", "--out", str(tmp_path / "out")]) == 0
    lines = _warnings(capsys.readouterr().err.splitlines(), "warning: ")
    assert [line.split("; ")[0] for line in lines] == [
        f"{tmp_path / 'cal.csv'}: 1 of 206 rows repeat an earlier row's joint readings and measured poses exactly: "
        f"row 206 = row 8 (pose {samples.pose[7]})",
        f"{tmp_path / 'samples.csv'}: 205 of 205 test poses repeat a calibration pose of {tmp_path / 'cal.csv'} "
        "(joint readings within 0.02 rad, m if prismatic): 205 with identical measured poses, the same measurements "
        "the fit was given (the test figures over them are in-sample figures, not held-out ones)"]
    assert lines == _warnings(json.loads((tmp_path / "out" / "result.json").read_text())["warnings"], "")
