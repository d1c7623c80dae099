"""A calibrated robot file fed back: what the first calibration could not determine stays held.

The tester's probe: estimate on 24 poses of the paper's 4-DOF arm holds d2 (parallel joint
axes: not separable from d1). Fed its own robot_calibrated.yaml, whose alpha1 is the fitted
1.26 deg, the second estimate found d1 and d2 "separable" by that tilt alone and wrote
d1 = +120 +- 57 mm, d2 = -120 +- 57 mm, and the test error rose. The file now says which
parameters were held (key ``held``), and a calibration from it holds them too.
"""

from __future__ import annotations

import json

import pytest
import yaml

from laser_calib.cli.main import main


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    """A simulated session and the first estimate from the nominal robot."""
    folder = tmp_path_factory.mktemp("round_trip")
    assert main(["simulate", "--case", "paper-4dof", "--seed", "5", "--out", str(folder / "sim")]) == 0
    assert main(["estimate", "--robot", str(folder / "sim" / "robot_nominal.yaml"), "--samples",
                 str(folder / "sim" / "case2_cal.csv"), "--out", str(folder / "first")]) == 0
    return folder


def errors(out) -> dict:
    return {e["name"]: e for e in json.loads((out / "result.json").read_text())["errors"]}


def test_the_calibrated_file_fed_back_needs_no_correction_and_holds_what_was_held(first, capsys):
    held = yaml.safe_load((first / "first" / "robot_calibrated.yaml").read_text())["held"]
    assert held == [name for name, e in errors(first / "first").items() if not e["identifiable"]] and "d2" in held
    capsys.readouterr()
    assert main(["estimate", "--robot", str(first / "first" / "robot_calibrated.yaml"), "--samples",
                 str(first / "sim" / "case2_cal.csv"), "--out", str(first / "second")]) == 0
    printed = capsys.readouterr().err
    assert f"held at nominal, as the calibration that wrote {first / 'first' / 'robot_calibrated.yaml'} held them" \
           in printed
    second = errors(first / "second")
    for name in held:
        assert second[name]["value"] is None and "could not determine" in second[name]["note"]
    # At the minimum already: every correction far inside its standard deviation (LM stops within 1e-10 of it).
    for name, e in second.items():
        if e["value"] is not None:
            assert abs(e["value"]) < 1e-3 * e["std"], (name, e)
    assert yaml.safe_load((first / "second" / "robot_calibrated.yaml").read_text())["held"] == held


@pytest.mark.parametrize("value, expected", [
    (["d9"], "held[0]: 'd9' is no parameter of robot 'manipulator_4dof'"),
    (["dd2"], "did you mean 'd2'?"),
    ("d2", "held: expected a list of parameter names"),
])
def test_a_wrong_held_key_is_one_line(first, capsys, value, expected):
    robot = first / "wrong.yaml"
    data = yaml.safe_load((first / "first" / "robot_calibrated.yaml").read_text())
    robot.write_text(yaml.safe_dump({**data, "held": value}))
    capsys.readouterr()
    assert main(["estimate", "--robot", str(robot), "--samples", str(first / "sim" / "case2_cal.csv"),
                 "--out", str(first / "wrong")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"laser-calib: {robot}: ") and expected in err[0], err
