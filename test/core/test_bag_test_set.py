"""estimate --bag takes a session bag's /test_samples (the held-out poses the sequencer measured
and never fitted) as its test set, as the session's own estimate did; --test given instead wins.
Before, an offline estimate from the bag had no held-out figures at all."""

import json
from dataclasses import replace

import numpy as np

from laser_calib.cli.main import main
from laser_calib.io.samples import load_samples, save_samples
from test_bag_joint_names import NAMES, simulated, write_bag  # noqa: F401 (the fixture)


def result(out):
    return json.loads((out / "result.json").read_text())


def test_the_bags_test_samples_are_the_test_set(simulated, tmp_path, capsys):
    robot = str(simulated / "robot_nominal.yaml")
    cal, test = load_samples(simulated / "case1_cal.csv"), load_samples(simulated / "case1_test.csv")
    path = write_bag(tmp_path / "bag", cal, lambda k, q: (NAMES, q), test)
    assert main(["estimate", "--robot", robot, "--bag", str(path), "--out", str(tmp_path / "bag_out")]) == 0
    assert f"tested on {len(test)} poses of {path} /test_samples" in capsys.readouterr().err
    assert main(["estimate", "--robot", robot, "--samples", str(simulated / "case1_cal.csv"), "--test",
                 str(simulated / "case1_test.csv"), "--out", str(tmp_path / "csv_out")]) == 0
    from_bag, from_csv = result(tmp_path / "bag_out"), result(tmp_path / "csv_out")
    assert from_bag["spot_error"]["test"] == from_csv["spot_error"]["test"]
    assert from_bag["errors"] == from_csv["errors"]
    # --test given: that file is the test set, not the bag's
    other = str(simulated / "case2_test.csv")
    assert main(["estimate", "--robot", robot, "--bag", str(path), "--test", other, "--out",
                 str(tmp_path / "given_out")]) == 0
    assert main(["estimate", "--robot", robot, "--samples", str(simulated / "case1_cal.csv"), "--test", other,
                 "--out", str(tmp_path / "other_out")]) == 0
    assert result(tmp_path / "given_out")["spot_error"]["test"] == result(tmp_path / "other_out")["spot_error"]["test"]
    assert result(tmp_path / "given_out")["spot_error"]["test"] != from_csv["spot_error"]["test"]


def test_a_session_whose_test_poses_saw_no_spot_is_calibrated_and_says_so(simulated, tmp_path, capsys):
    """A session's test poses that saw nothing (the camera covered after the calibration poses) were
    refused as an empty --test file is: `estimate --bag` and `diagnose --bag` could not use that bag
    at all. The test set is dropped and the missing held-out figure said (kept, diagnose's summary
    failed on its empty figures); a --test file measuring nothing is still bad input."""
    robot = str(simulated / "robot_nominal.yaml")
    cal, test = load_samples(simulated / "case1_cal.csv"), load_samples(simulated / "case1_test.csv")
    unseen = replace(test, spots=np.full_like(test.spots, np.nan))
    path = write_bag(tmp_path / "bag", cal, lambda k, q: (NAMES, q), unseen)
    assert main(["estimate", "--robot", robot, "--bag", str(path), "--out", str(tmp_path / "out")]) == 0
    assert f"test: no spot is measured in the {len(test)} test poses: there is no held-out figure" in (
        capsys.readouterr().err)
    assert result(tmp_path / "out")["errors"] == result_of_csv(simulated, tmp_path)["errors"]
    assert main(["diagnose", "--robot", robot, "--bag", str(path), "--out", str(tmp_path / "diagnosed")]) == 0
    assert "test: no spot is measured" in capsys.readouterr().err
    empty = tmp_path / "unseen.csv"
    save_samples(unseen, empty)
    assert main(["estimate", "--robot", robot, "--samples", str(simulated / "case1_cal.csv"), "--test", str(empty),
                 "--out", str(tmp_path / "refused")]) == 2
    assert "no spot is measured in the test set" in capsys.readouterr().err


def result_of_csv(simulated, tmp_path):
    assert main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"), "--samples",
                 str(simulated / "case1_cal.csv"), "--out", str(tmp_path / "csv_out")]) == 0
    return result(tmp_path / "csv_out")
