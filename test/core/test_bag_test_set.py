"""estimate --bag takes a session bag's /test_samples (the held-out poses the sequencer measured
and never fitted) as its test set, as the session's own estimate did; --test given instead wins.
Before, an offline estimate from the bag had no held-out figures at all."""

import json

from laser_calib.cli.main import main
from laser_calib.io.samples import load_samples
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
