"""The compensator file (diagnosis/compensator.py, docs/effects.md) as bad input: it is
checked whole when read, each problem one InputError naming the file and the key,
and where it meets a robot or model it was not made for, one InputError saying what
differs (the fuzz findings: tracebacks, numpy's and scikit-learn's words, a NaN
coefficient reported as "no measured spot to fit").

The files are edits of a valid compensator built here for the 4-DOF arm, as a
diagnosis would write it (two used targets, a joint offset and a link offset).
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from laser_calib.cli.main import main
from laser_calib.diagnosis.compensator import Compensator, load_compensator
from laser_calib.diagnosis.detector import Basis
from laser_calib.effects.effect_model import EffectModel
from laser_calib.io.errors import InputError
from laser_calib.io.samples import format_samples
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot_file import dump_robot
from laser_calib.sim.simulation import bundled_robot, paper_session

ROBOT = bundled_robot("paper-4dof")
SAMPLES = paper_session("paper-4dof", 0, n_per_span=6).samples


def _compensator(robot, q: np.ndarray) -> dict:
    """A valid compensator's JSON for ``robot`` (no effects), its basis from the readings q: every
    joint offset and d2 as targets, theta1 and d2 used."""
    basis = Basis.of(q, robot.n_joints)
    width = basis(q).shape[1]
    inputs = tuple(f"q{j + 1}" for j in range(robot.n_joints))
    targets = tuple(f"theta{j + 1}" for j in range(robot.n_joints)) + ("d2",)
    used = np.array([True] + [False] * (robot.n_joints - 1) + [True])
    return Compensator(inputs, targets, used, basis, np.full((int(used.sum()), width), 1e-4), 0.1,
                       tuple(robot.param_names), np.zeros(robot.n_params)).to_json()


VALID = _compensator(ROBOT, SAMPLES.q)


def _write(folder: Path, data: object, name: str = "c.json") -> Path:
    path = folder / name
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return path


def _edited(edit) -> dict:
    data = copy.deepcopy(VALID)
    edit(data)
    return data


def _set(key, value):
    return lambda d: d.__setitem__(key, value)


def _set_in(key, index, value):
    return lambda d: d[key].__setitem__(index, value)


def _cell(key, row, column, value):
    return lambda d: d[key][row].__setitem__(column, value)


# edit -> the start of the message after the file's name (the key) and a part of the problem
CASES = {
    "a JSON list": ("[1, 2, 3]", "not a compensator file", "expected a JSON object"),
    "a JSON string": ('"hello"', "not a compensator file", "expected a JSON object"),
    "JSON null": ("null", "not a compensator file", "expected a JSON object"),
    "not JSON": ("{version: 2", "not a compensator file", ""),
    "no knots": (lambda d: d.pop("knots"), "no key 'knots'", ""),
    "version 4": (_set("version", 4), "version", "expected one of 1, 2, 3"),
    "version true": (_set("version", True), "version", "expected one of 1, 2, 3"),
    "tensor a string": (_set("tensor", "yes"), "tensor", "expected true or false"),
    "tensor missing": (lambda d: d.pop("tensor"), "no key 'tensor'", ""),
    "inputs a string": (_set("inputs", "q1"), "inputs", "list of names"),
    "no inputs": (_set("inputs", []), "inputs", "empty"),
    "target x9": (_set_in("targets", 0, "x9"), "targets[0]", "'x9' is not a target"),
    "target theta0": (_set_in("targets", 1, "theta0"), "targets[1]", "not a target"),
    "mean of 2": (_set("mean", [0, 0]), "mean", "2 values, expected 4 (one per input)"),
    "mean a string": (_set_in("mean", 2, "0.5"), "mean[2]", "not a number ('0.5')"),
    "std zeros": (_set("std", [0, 0, 0, 0]), "std[0]", "expected above"),
    "std negative": (_set_in("std", 3, -1.0), "std[3]", "expected above"),
    "knots of one row": (_set("knots", [[0, 0, 0, 0]]), "knots", "1 row, expected at least 2"),
    "knots of 3 columns": (_set_in("knots", 1, [0, 0, 0]), "knots[1]", "3 values, expected 4"),
    "knots not increasing": (lambda d: d["knots"][2].__setitem__(1, d["knots"][1][1]), "knots[2][1]",
                             "is not above knots[1][1]"),
    "knot infinite": (_cell("knots", 0, 0, float("inf")), "knots[0][0]", "not a finite number (inf)"),
    "pair past the inputs": (_set("pairs", [[0, 7]]), "pairs[0][1]", "7 is not the index of a joint reading"),
    "pair of one": (_set("pairs", [[0]]), "pairs[0]", "expected a pair"),
    "pair of floats": (_set("pairs", [[0, 1.0]]), "pairs[0][1]", "not the index"),
    "used yes": (_set("used", "yes"), "used", "true/false"),
    "used numbers": (_set("used", [1, 0, 0, 0, 1]), "used", "true/false"),
    "used too short": (_set("used", [True, False]), "used", "2 values, expected 5 (one per target)"),
    "coef NaN": (_cell("coef", 0, 0, float("nan")), "coef[0][0]", "not a finite number (nan)"),
    "coef null": (_cell("coef", 1, 3, None), "coef[1][3]", "not a number (None)"),
    "coef huge integer": (_cell("coef", 1, 3, 10 ** 400), "coef[1][3]", "not a finite number"),
    "coef one row": (lambda d: d["coef"].pop(), "coef", "1 row, expected 2 (one row per used target)"),
    "coef short row": (lambda d: d["coef"][0].pop(), "coef[0]", "values, expected"),
    "size 0": (_set("size", 0), "size", "expected above 0"),
    "heldout_gain text": (_set("heldout_gain", "high"), "heldout_gain", "not a number"),
    # a gain is a share of the residual the compensator predicts held out: -5 was loaded and applied
    "heldout_gain negative": (_set("heldout_gain", -5), "heldout_gain", "-5, expected above 0 and at most 1"),
    "heldout_gain above 1": (_set("heldout_gain", 1.5), "heldout_gain", "expected above 0 and at most 1"),
    "model a list": (_set("model", []), "model", "expected an object"),
    "model without names": (lambda d: d["model"].pop("names"), "no key 'model.names'", ""),
    "model values short": (lambda d: d["model"]["values"].pop(), "model.values", "expected 21"),
    "model held a string": (lambda d: d["model"].update(held="d2"), "model.held", "expected a list of names"),
    "model held unknown": (lambda d: d["model"].update(held=["d9"]), "model.held", "'d9' is not one of model.names"),
    "version 1 with coef": (_set("version", 1), "no key 'coef_rad'", ""),
}


@pytest.mark.parametrize("name", list(CASES))
def test_each_problem_of_the_file_is_one_input_error_naming_file_and_key(name, tmp_path):
    edit, key, problem = CASES[name]
    with pytest.raises(InputError) as raised:
        load_compensator(_write(tmp_path, edit if isinstance(edit, str) else _edited(edit)))
    message = str(raised.value)
    assert message.startswith(f"{tmp_path / 'c.json'}: {key}"), message
    assert problem in message and "\n" not in message, message


def test_the_valid_file_and_its_version_1_form_load_and_predict(tmp_path):
    model = EffectModel(SpotModel(ROBOT, SAMPLES), ())
    compensator = load_compensator(_write(tmp_path, VALID))
    spots = compensator.predict(model)
    assert spots.shape == SAMPLES.spots.shape and np.isfinite(spots).all()
    old = _edited(lambda d: d.update(version=1, coef_rad=d.pop("coef")))
    assert np.array_equal(load_compensator(_write(tmp_path, old, "v1.json")).coef, compensator.coef)
    # version 2, from before the key tensor: a pair is the product of its readings
    two = _edited(lambda d: (d.update(version=2), d.pop("tensor")))
    assert np.array_equal(load_compensator(_write(tmp_path, two, "v2.json")).predict(model), spots)


def test_a_tensor_basis_round_trips_through_its_file(tmp_path):
    """A pair as the products of its splines (Basis.tensor): the file holds it, and the loaded
    compensator predicts what the one written did; its pair columns are not the product's."""
    plain = Basis.of(SAMPLES.q, ROBOT.n_joints)
    basis = Basis(plain.mean, plain.std, plain.knots, plain.pairs[:1], plain.size, tensor=True)
    width = basis(SAMPLES.q).shape[1]
    assert width == ROBOT.n_joints * basis.splines_per_input + basis.splines_per_input ** 2
    rng = np.random.default_rng(0)
    written = Compensator(tuple(f"q{j + 1}" for j in range(ROBOT.n_joints)), ("theta1",), np.array([True]), basis,
                          rng.normal(0, 1e-4, (1, width)), 0.1, tuple(ROBOT.param_names), np.zeros(ROBOT.n_params))
    written.save(tmp_path / "t.json")
    loaded = load_compensator(tmp_path / "t.json")
    model = EffectModel(SpotModel(ROBOT, SAMPLES), ())
    assert loaded.basis.tensor
    assert np.allclose(loaded.predict(model), written.predict(model), atol=1e-12)


def _estimate(folder: Path, data: object, robot=ROBOT, samples=SAMPLES) -> list[str]:
    (folder / "robot.yaml").write_text(dump_robot(robot))
    (folder / "samples.csv").write_text(format_samples(samples))
    return ["estimate", "--robot", str(folder / "robot.yaml"), "--samples", str(folder / "samples.csv"),
            "--out", str(folder / "out"), "--compensator", str(_write(folder, data))]


def _one_line(capsys, argv: list[str]) -> str:
    """The single error line of a run that must exit 2 and write nothing."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert not any("Traceback" in line or "Warning" in line for line in err), err
    assert [line for line in err if line.startswith("laser-calib")] == err[-1:], err
    return err[-1]


# the tester's files (fuzz findings, section 4): the line `laser-calib estimate` prints
FOUND = {
    "list": ("[1, 2, 3]", "c.json: not a compensator file"),
    "theta9": (_edited(_set_in("targets", 0, "theta9")),
               "c.json: targets[0]: 'theta9' is not a parameter of robot 'manipulator_4dof' (joints 1..4)"),
    "a9": (_edited(_set_in("targets", 4, "a9")), "c.json: targets[4]: 'a9' is not a parameter of robot"),
    "pairs": (_edited(_set("pairs", [[0, 7]])), "c.json: pairs[0][1]: 7 is not the index of a joint reading"),
    "mean": (_edited(_set("mean", [0, 0])), "c.json: mean: 2 values, expected 4 (one per input)"),
    "std": (_edited(_set("std", [0, 0, 0, 0])), "c.json: std[0]: 0, expected above"),
    "knots": (_edited(_set("knots", [[0, 0, 0, 0]])), "c.json: knots: 1 row, expected at least 2"),
    "used": (_edited(_set("used", "yes")), "c.json: used: expected a list of true/false"),
    "nan": (_edited(_cell("coef", 0, 0, float("nan"))), "c.json: coef[0][0]: not a finite number (nan)"),
    "overflow": (_edited(_set("mean", [1.7e308] * 4)), "c.json: its offsets overflow"),
}


@pytest.mark.parametrize("name", list(FOUND))
def test_estimate_with_a_bad_compensator_is_one_line_naming_the_file(name, tmp_path, capsys):
    data, expected = FOUND[name]
    line = _one_line(capsys, _estimate(tmp_path, data))
    assert line.startswith(f"laser-calib: {tmp_path}/"), line
    assert expected in line, line
    assert not (tmp_path / "out").exists()


def test_a_compensator_of_another_robot_says_which_model_it_was_made_for(tmp_path, capsys):
    arm7 = bundled_robot("paper-7dof")
    q7 = np.random.default_rng(0).uniform(arm7.q_min, arm7.q_max, (30, arm7.n_joints))
    line = _one_line(capsys, _estimate(tmp_path, _compensator(arm7, q7)))
    assert line == (f"laser-calib: {tmp_path / 'c.json'}: made for a {arm7.n_params}-parameter model, not this "
                    f"{ROBOT.n_params}-parameter one of robot '{ROBOT.name}' (only that one has a5, d5, alpha5, "
                    f"theta5 and {4 * (arm7.n_joints - ROBOT.n_joints) - 4} more)"), line


def test_offsets_for_a_robot_or_samples_without_what_it_follows_is_an_input_error(tmp_path):
    """The estimator node and the core API call offsets with their own robot and samples: the
    same checks, naming the file and key."""
    compensator = load_compensator(_write(tmp_path, _edited(_set_in("targets", 0, "theta9"))))
    with pytest.raises(InputError, match=r"c\.json: targets\[0\]: 'theta9' is not a parameter"):
        compensator.offsets(ROBOT, SAMPLES.q, SAMPLES.stamp, SAMPLES.extra)
    compensator = load_compensator(_write(tmp_path, _edited(_set_in("inputs", 3, "q9"))))
    with pytest.raises(InputError, match=r"c\.json: inputs\[3\]: 'q9' is not a column of the samples"):
        compensator.offsets(ROBOT, SAMPLES.q, SAMPLES.stamp, SAMPLES.extra)


KEYS = ["version", "inputs", "targets", "used", "mean", "std", "knots", "pairs", "size", "tensor", "coef",
        "heldout_gain", "model"]
JSON = st.recursive(st.none() | st.booleans() | st.integers(-10, 10) | st.integers() |
                    st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=8),
                    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=5), inner,
                                                                                max_size=3), max_leaves=8)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(key=st.sampled_from(KEYS), index=st.none() | st.integers(0, 5), inner=st.none() | st.integers(0, 40),
       value=JSON)
def test_any_edit_of_a_key_loads_and_applies_or_is_one_input_error(tmp_path_factory, key, index, inner, value):
    """A key, an element of it or an element of that replaced by any JSON value: the file loads and
    gives finite offsets on the arm's poses, or it raises InputError (one line), nothing else."""
    data = copy.deepcopy(VALID)
    node, at = data, key
    for step in (index, inner):
        child = node[at]
        if step is None or not isinstance(child, list) or step >= len(child):
            break
        node, at = child, step
    node[at] = value
    path = _write(tmp_path_factory.getbasetemp(), data, "fuzzed.json")
    try:
        compensator = load_compensator(path)
        dq, errors = compensator.offsets(ROBOT, SAMPLES.q, SAMPLES.stamp, SAMPLES.extra)
    except InputError as exc:
        assert str(exc).startswith(str(path)) and "\n" not in str(exc), str(exc)
        return
    assert np.isfinite(dq).all() and np.isfinite(errors).all()

