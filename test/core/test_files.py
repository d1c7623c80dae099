"""Robot YAML and samples CSV: exact round trips, and one clear line (exit 2) per bad input."""

import numpy as np
import pytest

from laser_calib.cli.main import main
from laser_calib.model.robot_file import dump_robot, load_robot, save_robot
from laser_calib.io.errors import InputError
from laser_calib.io.samples import load_samples, save_samples
from laser_calib.sim.simulation import bundled_robot, paper_session


def test_robot_round_trip(tmp_path):
    robot = bundled_robot("paper-4dof").with_errors(np.linspace(-0.01, 0.01, 21))
    save_robot(robot, tmp_path / "r.yaml", header="test")
    assert load_robot(tmp_path / "r.yaml") == robot


def test_samples_round_trip_keeps_missing_spots_and_extra_columns(tmp_path):
    session = paper_session("paper-4dof", 1)
    samples = session.samples
    spots = samples.spots.copy()
    spots[3, 1] = np.nan
    from dataclasses import replace
    samples = replace(samples, spots=spots, extra={"temperature_c": np.linspace(20, 25, len(samples))})
    save_samples(samples, tmp_path / "s.csv")
    back = load_samples(tmp_path / "s.csv", session.nominal)
    assert np.array_equal(back.q, samples.q) and np.array_equal(back.stamp, samples.stamp)
    assert np.array_equal(np.isnan(back.spots), np.isnan(samples.spots))
    assert np.array_equal(back.spots[~np.isnan(back.spots)], samples.spots[~np.isnan(samples.spots)])
    assert np.array_equal(back.extra["temperature_c"], samples.extra["temperature_c"])
    assert not back.seen[3, 1] and back.seen[3, 0]


def test_text_columns_are_carried_as_labels(tmp_path):
    """conventions.md: any further column is a per-pose covariate, carried through every
    step. A column of text (an operator, a fixture, notes never filled in) was refused
    ('not a number'); it is read as labels, kept by a subset, written back as it was, and
    the point and pose files read it alike. A column of numbers with some text is still a
    covariate with a typo: refused, naming the field."""
    from laser_calib.io.sensor_samples import parse_sensor_samples
    session = paper_session("paper-4dof", 1)
    save_samples(session.samples, tmp_path / "s.csv")
    lines = (tmp_path / "s.csv").read_text().splitlines()
    n = len(lines) - 1
    operators = ["anna" if r % 3 else "Bo, night shift" for r in range(n)]
    rows = [f"{line},{20 + r * 0.01:.2f},\"{operators[r]}\"," for r, line in enumerate(lines[1:])]
    (tmp_path / "labelled.csv").write_text("\n".join([lines[0] + ",temperature_c,operator,notes"] + rows) + "\n")
    samples = load_samples(tmp_path / "labelled.csv", session.nominal)
    assert list(samples.extra) == ["temperature_c"] and sorted(samples.labels) == ["notes", "operator"]
    assert samples.labels["operator"].tolist() == operators and set(samples.labels["notes"]) == {""}
    assert samples.subset(np.arange(1, 4)).labels["operator"].tolist() == operators[1:4]
    save_samples(samples, tmp_path / "again.csv")
    back = load_samples(tmp_path / "again.csv", session.nominal)
    assert back.labels["operator"].tolist() == operators and np.array_equal(back.q, samples.q)
    point = parse_sensor_samples("pose,stamp,q1,x,y,z,fixture\n0,0.0,0.1,1.0,0.2,0.3,A\n1,1.0,0.2,1.1,0.2,0.3,B\n")
    assert point.labels["fixture"].tolist() == ["A", "B"] and not point.extra

    logged = [f"{line},{'n/a' if r == 3 else 21.5}" for r, line in enumerate(lines[1:])]
    (tmp_path / "mixed.csv").write_text("\n".join([lines[0] + ",temperature_c"] + logged) + "\n")
    with pytest.raises(InputError, match="line 5, field temperature_c: not a number: 'n/a'"):
        load_samples(tmp_path / "mixed.csv", session.nominal)


GOOD_HEADER = "pose,stamp,q1,q2,q3,q4,l1_y,l1_z,l2_y,l2_z"
GOOD_ROW = "0,0.0,0.0,0.0,0.0,0.0,0.1,0.2,0.3,0.4"

BAD_SAMPLES = {
    "missing_column": ("pose,stamp,q1,q2,q3,q4,l1_y,l1_z,l2_y\n0,0,0,0,0,0,0,0,0\n", "header: missing column l2_z"),
    "no_header": (GOOD_ROW + "\n", "header: must start with 'pose,stamp'"),
    "wrong_joint_count": ("pose,stamp,q1,q2,q3,l1_y,l1_z,l2_y,l2_z\n0,0,0,0,0,0,0,0,0\n",
                          "3 joint columns but robot 'manipulator_4dof' has 4 joints"),
    "non_numeric": (GOOD_HEADER + "\n0,0.0,0.0,abc,0.0,0.0,0.1,0.2,0.3,0.4\n", "line 2, field q2: not a number: 'abc'"),
    "nan": (GOOD_HEADER + "\n0,0.0,0.0,0.0,0.0,0.0,nan,0.2,0.3,0.4\n", "line 2, field l1_y: not finite"),
    "inf": (GOOD_HEADER + "\n0,0.0,0.0,0.0,inf,0.0,0.1,0.2,0.3,0.4\n", "line 2, field q3: not finite"),
    "stamps": (GOOD_HEADER + "\n" + GOOD_ROW + "\n1,0.0,0.0,0.0,0.0,0.0,0.1,0.2,0.3,0.4\n",
               "line 3, field stamp: not increasing"),
    # a logger's line written twice, stamp and all: which line to delete is named, not a stamp
    "copied_line": (GOOD_HEADER + "\n" + GOOD_ROW + "\n" + GOOD_ROW + " \n",
                    "line 3: a copy of line 2, every field equal (stamps increase): delete one of them"),
    "range": (GOOD_HEADER + "\n7,0.0,0.9,0.0,0.0,0.0,0.1,0.2,0.3,0.4\n", "pose 7, field q1: 0.9 rad outside"),
    "half_spot": (GOOD_HEADER + "\n0,0.0,0.0,0.0,0.0,0.0,0.1,,0.3,0.4\n", "line 2, laser 1: only one"),
    "short_row": (GOOD_HEADER + "\n0,0.0,0.0\n", "line 2: 3 fields, header has 10"),
    "empty": ("", "empty file"),
}


@pytest.mark.parametrize("name", sorted(BAD_SAMPLES))
def test_bad_samples_give_one_line_and_exit_2(tmp_path, capsys, name):
    text, expected = BAD_SAMPLES[name]
    path = tmp_path / f"{name}.csv"
    path.write_text(text)
    robot = tmp_path / "robot.yaml"
    save_robot(bundled_robot("paper-4dof"), robot)
    code = main(["estimate", "--robot", str(robot), "--samples", str(path), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and str(path) in err and expected in err, err


BAD_ROBOTS = {
    "missing_key": (lambda t: t.replace("name: manipulator_4dof\n", ""), "missing key 'name'"),
    "joint_key_missing": (lambda t: t.replace("{a: -0.365, ", "{", 1), "joints[0] (joint 1): missing key 'a'"),
    "wrong_type": (lambda t: t.replace("d: 0.69", "d: high", 1), "joints[0] (joint 1).d: expected a number, got str"),
    "lasers": (lambda t: t.replace("  - {gamma: 0.5422737986, beta: 0.0143116999}\n", ""), "exactly two lasers"),
    "yaml": (lambda t: t + "joints: [\n", "not valid YAML"),
    "convention": (lambda t: t + "convention: weird\n", "convention: expected one of paper, standard"),
}


@pytest.mark.parametrize("name", sorted(BAD_ROBOTS))
def test_bad_robot_files_give_one_line_and_exit_2(tmp_path, capsys, name):
    edit, expected = BAD_ROBOTS[name]
    from importlib import resources
    text = (resources.files("laser_calib") / "model" / "robots" / "manipulator_4dof.yaml").read_text()
    path = tmp_path / "robot.yaml"
    path.write_text(edit(text))
    samples = tmp_path / "s.csv"
    samples.write_text(GOOD_HEADER + "\n" + GOOD_ROW + "\n")
    code = main(["estimate", "--robot", str(path), "--samples", str(samples), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and expected in err, err


def test_dump_is_readable_yaml_with_one_joint_per_line():
    text = dump_robot(bundled_robot("paper-7dof"))
    assert text.count("- {a:") == 7
