"""diagnose --bag reads a recorded session as estimate --bag does (cli/sample_sets.py): its /samples
are the poses to fit, its /test_samples the test set unless --test is given, each sample's joints
by its joint_names. Before, diagnose took CSVs only, and a session known by its bag had to be
exported first."""

import dataclasses
import json

import numpy as np
import pytest

from laser_calib.cli.main import main
from laser_calib.io.samples import load_samples, save_samples
from test_bag_joint_names import NAMES, simulated, write_bag  # noqa: F401 (the fixture)


def diagnosis(out):
    return json.loads((out / "diagnosis.json").read_text())


def stamped(samples, first):
    """The samples with the stamps write_bag gives them (one second apart from first + 1): the
    stamp is one of the diagnosis's covariates, so both sources must carry the same."""
    return dataclasses.replace(samples, stamp=first + 1.0 + np.arange(len(samples), dtype=float))


@pytest.fixture(scope="module")
def session(simulated, tmp_path_factory):
    """The same session as a bag (joints listed tip to base) and as the two CSVs."""
    out = tmp_path_factory.mktemp("session")
    cal = stamped(load_samples(simulated / "samples.csv"), 1000)
    test = stamped(load_samples(simulated / "case1_test.csv"), 1000 + len(cal))
    save_samples(cal, out / "cal.csv")
    save_samples(test, out / "test.csv")
    path = write_bag(out / "bag", cal, lambda k, q: (NAMES[::-1], q[::-1]), test)
    return simulated / "robot_nominal.yaml", path, out


def test_a_bag_is_diagnosed_as_its_csvs_with_its_test_poses(session, tmp_path, capsys):
    robot, path, csvs = session
    assert main(["diagnose", "--robot", str(robot), "--bag", str(path), "--out", str(tmp_path / "bag")]) in (0, 1)
    err = capsys.readouterr().err
    assert f"testing on {len(load_samples(csvs / 'test.csv'))}" in err
    assert main(["diagnose", "--robot", str(robot), "--samples", str(csvs / "cal.csv"), "--test",
                 str(csvs / "test.csv"), "--out", str(tmp_path / "csv")]) in (0, 1)
    from_bag, from_csv = diagnosis(tmp_path / "bag"), diagnosis(tmp_path / "csv")
    assert from_bag["inputs"]["samples"] == str(path) and from_bag["inputs"]["test"] == f"{path} /test_samples"
    for key in ("stages", "verdict", "evidence", "test_prediction", "effects"):
        assert from_bag[key] == from_csv[key], key
    assert all(stage["test"] is not None for stage in from_bag["stages"])


def test_a_given_test_file_wins_over_the_bags(session, tmp_path):
    robot, path, csvs = session
    other = stamped(load_samples(csvs / "test.csv"), 5000)
    save_samples(dataclasses.replace(other, q=other.q[::-1], spots=other.spots[::-1]), tmp_path / "other.csv")
    assert main(["diagnose", "--robot", str(robot), "--bag", str(path), "--test", str(tmp_path / "other.csv"),
                 "--out", str(tmp_path / "out")]) in (0, 1)
    assert diagnosis(tmp_path / "out")["inputs"]["test"] == str(tmp_path / "other.csv")


def test_joint_names_without_a_bag_is_one_line(session, tmp_path, capsys):
    robot, _, csvs = session
    assert main(["diagnose", "--robot", str(robot), "--samples", str(csvs / "cal.csv"), "--joint-names", *NAMES,
                 "--out", str(tmp_path / "refused")]) == 2
    assert capsys.readouterr().err == ("laser-calib: --joint-names: names the joints of a bag's samples: it applies "
                                       "to --bag only\n")
    assert not (tmp_path / "refused").exists()
