"""The real two-axis positioner data: import, round trips, the chain, the calibration."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from laser_calib.cli import main as cli
from laser_calib.io.positioner import BASE_IN_WORLD, read_positioner
from laser_calib.model.robot_file import load_robot
from laser_calib.measurement.frames import robot_frames
from laser_calib.estimation.sensor_fit import SensorFitOptions, calibrate, pose_errors
from laser_calib.measurement.chain import chain_names, target_in_sensor
from laser_calib.measurement.rotations import quaternion_to_matrix
from laser_calib.io.sensor_samples import load_sensor_samples

DATA = Path(__file__).resolve().parents[2] / "data" / "real" / "positioner_2axis"


@pytest.fixture
def run():
    """The command line's entry point (exit status, one line on bad input)."""
    return cli.main


@pytest.fixture(scope="module")
def data():
    return read_positioner(DATA)


def test_import_reads_every_observation_in_time_order(data):
    robot, samples = data
    raw = yaml.safe_load((DATA / "measurements.yaml").read_text())
    assert len(samples) == len(raw) == 205 and samples.kind == "pose"
    assert np.all(np.diff(samples.stamp) > 0)
    for row in (0, 100, 204):
        entry = raw[str(int(samples.stamp[row]))]
        assert list(samples.q[row]) == entry["target_joints"]
        assert list(samples.position[row]) == [entry["pose"][k] for k in "xyz"]
        assert list(samples.quaternion[row]) == [entry["pose"][k] for k in ("qw", "qx", "qy", "qz")]
    assert robot.convention == "standard" and robot.lasers == () and robot.n_joints == 2
    assert [(j.d, j.theta0, j.a, j.alpha) for j in robot.joints] == [(0.0, 0.0, 0.0, -math.pi / 2),
                                                                      (-0.475, -math.pi / 2, 0.0, 0.0)]


def _transform(rotation, translation):
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, translation
    return m


def test_chain_matches_the_source_model_written_out(data):
    """inv(sensor) · base · DH1 · DH2 · target, with 4x4 matrices, as the source computes it."""
    robot, samples = data
    frames = robot_frames(robot)
    state = target_in_sensor(robot, frames, samples.q, np.zeros(len(chain_names(robot))))

    def dh(d, theta, r, alpha):  # the source's DHTransform: Trans(z,d) Rot(z,theta) Trans(x,r) Rot(x,alpha)
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        return np.array([[ct, -st * ca, st * sa, r * ct], [st, ct * ca, -ct * sa, r * st], [0, sa, ca, d],
                         [0, 0, 0, 1]])
    sensor = _transform(frames["sensor"].rotation, frames["sensor"].translation)
    target = _transform(frames["target"].rotation, frames["target"].translation)
    base = _transform(quaternion_to_matrix(np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0])),
                      [2.2, 0.0, 1.6])
    assert np.allclose(base[:3, :3], BASE_IN_WORLD.rotation)
    for p in (0, 57, 204):
        q1, q2 = samples.q[p]
        m = np.linalg.inv(sensor) @ base @ dh(0, q1, 0, -math.pi / 2) @ dh(-0.475, q2 - math.pi / 2, 0, 0) @ target
        assert np.allclose(state.position[p], m[:3, 3], atol=1e-12)
        assert np.allclose(state.rotation[p], m[:3, :3], atol=1e-12)


def test_import_command_round_trips_exactly(data, run, tmp_path, capsys):
    assert run(["import-positioner", "--data", str(DATA), "--out", str(tmp_path)]) == 0
    robot, samples = data
    back_robot = load_robot(tmp_path / "robot.yaml")
    back = load_sensor_samples(tmp_path / "samples.csv", back_robot)
    assert back_robot == robot
    for a, b in ((back.q, samples.q), (back.stamp, samples.stamp), (back.position, samples.position),
                 (back.quaternion, samples.quaternion), (back.pose, samples.pose)):
        assert np.array_equal(a, b)
    assert "205 pose measurements" in capsys.readouterr().out


def test_calibration_beats_the_published_figure_in_and_out_of_sample(data, run, tmp_path):
    robot, samples = data
    fit = calibrate(robot, samples, SensorFitOptions())
    after, _ = pose_errors(fit.model, fit.estimate.values)
    nominal, _ = pose_errors(fit.model, fit.nominal.values)
    assert np.mean(after) < np.mean(nominal) < 1e-3          # published: 1.74 mm after, 3.82 mm nominal
    assert {"d1", "theta1", "a2", "d2", "alpha2", "theta2"} <= set(fit.absorbed)
    fitted = [n for n, free in zip(robot.param_names, fit.estimate.identifiable) if free]
    assert fitted == ["a1", "alpha1"]                        # the two joint axes' distance and angle
    assert run(["calibrate-poses", "--robot", str(DATA.parent / "none.yaml"), "--samples", "x", "--out",
                str(tmp_path)]) == 2
    shutil.copy(DATA / "pose_initial_guesses.yaml", tmp_path / "pose_initial_guesses.yaml")
    (tmp_path / "measurements.yaml").write_text("'1.0': {target_joints: [0.1], pose: {x: 0}}\n")
    assert run(["import-positioner", "--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 2


def test_calibrate_poses_command_writes_result_and_calibrated_robot(run, tmp_path, capsys):
    assert run(["import-positioner", "--data", str(DATA), "--out", str(tmp_path)]) == 0
    out = tmp_path / "cal"
    assert run(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples",
                str(tmp_path / "samples.csv"), "--folds", "3", "--out", str(out)]) == 0
    result = json.loads((out / "result.json").read_text())
    assert result["heldout"]["position_mm"]["mean"] < 1.0 and result["insample"]["position_mm"]["mean"] < 1.0
    assert [p["name"] for p in result["parameters"] if p["value"] is not None][:2] == ["a1", "alpha1"]
    notes = {p["name"]: p.get("note", "") for p in result["parameters"]}
    # d1 moves the first axis along itself, as the sensor's frame does: held, and said to be the frames'
    assert notes["d1"].startswith("carried by the frames: not separable from sensor_")
    calibrated = load_robot(out / "robot_calibrated.yaml")
    assert calibrated.joints[0].a == pytest.approx(result["parameters"][0]["value"])
    assert "held-out" in capsys.readouterr().out
    assert run(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples",
                str(tmp_path / "samples.csv"), "--fix", "nope", "--out", str(out)]) == 2
    assert "cannot fix unknown parameter 'nope'" in capsys.readouterr().err
    # a parameter --fix holds is said to be the user's, not 'held' as one the robot file held
    assert run(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples",
                str(tmp_path / "samples.csv"), "--folds", "0", "--fix", "a1", "--out", str(out)]) == 0
    a1 = json.loads((out / "result.json").read_text())["parameters"][0]
    assert a1["name"] == "a1" and a1["value"] is None and a1["note"] == "held at nominal: --fix"


def test_calibrate_poses_of_one_pose_copied_onto_every_row_is_too_few_values(run, tmp_path, capsys):
    """Every row a copy of the first: 'D-H errors fitted: none', 0.000 mm held out, exit 0. The copies
    are counted as the row they copy: too few values, one line naming the file."""
    assert run(["import-positioner", "--data", str(DATA), "--out", str(tmp_path)]) == 0
    lines = (tmp_path / "samples.csv").read_text().splitlines()
    first = lines[1].split(",")
    copies = [lines[0]] + [",".join(line.split(",")[:2] + first[2:]) for line in lines[1:]]
    (tmp_path / "copies.csv").write_text("\n".join(copies) + "\n")
    capsys.readouterr()
    assert run(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "copies.csv"),
                "--out", str(tmp_path / "cal")]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'copies.csv'}: 6 measured values (not counting {len(lines) - 2} rows that copy another row " \
           "exactly) reach only 6 of the model's" in err, err
    assert not (tmp_path / "cal").exists()


def test_calibrate_poses_writes_no_stale_effects(run, tmp_path, capsys):
    """A robot file's effects are not fitted by calibrate-poses: it says so, and the
    calibrated robot does not carry their old values (fitted with another geometry)."""
    assert run(["import-positioner", "--data", str(DATA), "--out", str(tmp_path)]) == 0
    robot_file = tmp_path / "robot.yaml"
    data = yaml.safe_load(robot_file.read_text())
    data["effects"] = [{"type": "periodic", "joint": 1, "c1": 1e-3, "s1": 0.0, "c2": 0.0, "s2": 0.0}]
    robot_file.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    assert run(["calibrate-poses", "--robot", str(robot_file), "--samples", str(tmp_path / "samples.csv"),
                "--folds", "0", "--out", str(out)]) == 0
    assert f"warning: {robot_file}: its effects (1) are not fitted by calibrate-poses" in capsys.readouterr().err
    assert "effects" not in yaml.safe_load((out / "robot_calibrated.yaml").read_text())


def test_calibrate_poses_diagnose_runs_the_diagnosis_engine(run, tmp_path, capsys, monkeypatch):
    """--diagnose: the engine of diagnosis.py on the pose data; the sensor scale first, no spot effects."""
    from laser_calib.diagnosis import sensor_data
    summary = sensor_data.diagnosis_summary

    def noted(*args, **kwargs):  # these data give the diagnosis nothing to note: one added, to see where it goes
        result = summary(*args, **kwargs)
        return {**result, "notes": [*result["notes"], "a note of the diagnosis"]}
    monkeypatch.setattr(sensor_data, "diagnosis_summary", noted)
    assert run(["import-positioner", "--data", str(DATA), "--out", str(tmp_path)]) == 0
    out = tmp_path / "diag"
    assert run(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples",
                str(tmp_path / "samples.csv"), "--folds", "3", "--diagnose", "--out", str(out)]) == 0
    diagnosis = json.loads((out / "result.json").read_text())["diagnosis"]
    assert diagnosis["stages"][1]["model"] == "geometric + sensor scale"
    assert diagnosis["joints"] == {"q1": "q1", "q2": "q2"}   # a D-H robot's joints are its readings' numbers
    assert diagnosis["stages"][-1]["heldout_mean_mm"] < diagnosis["stages"][0]["heldout_mean_mm"] < 1.74
    labels = {r["label"] for ranking in diagnosis["selection"] for r in ranking}
    assert labels and not any(label.startswith(("screen_shape", "camera_distortion")) for label in labels)
    # The figure of the whole procedure, the selection repeated inside each of the 3 folds: the
    # effects still beat the geometric model held out; it is the one the console gives first.
    assert len(diagnosis["nested_choices"]) == 3
    assert 0 < diagnosis["heldout_nested_mean_mm"] < diagnosis["stages"][0]["heldout_mean_mm"]
    captured = capsys.readouterr()
    printed = captured.out
    # the notes on stderr with the warnings: seen when the results go to a file
    assert "diagnosis note: a note of the diagnosis" in captured.err.splitlines() and "note" not in printed
    assert diagnosis["verdict"] in ("explained", "structure remains") and "verdict" in printed
    assert f"held-out mean {diagnosis['heldout_nested_mean_mm']:.3f} mm with the selection inside the folds" in printed
    # The calibrated robot file is the geometric model: it says the effects chosen are not in it (the
    # tester found it byte-identical to a run without --diagnose, nothing saying so).
    chosen = diagnosis["stages"][-1]["model"]
    assert f"the effects --diagnose chose ({chosen}) are in result.json, not here" in \
        (out / "robot_calibrated.yaml").read_text().replace("\n# ", " ")
    assert "its effects are in result.json, not in the calibrated robot file" in printed


def test_a_reading_in_degrees_is_refused_at_the_import(run, tmp_path, capsys):
    """The tester's edit: one target joint reading typed in degrees. The import wrote it as good
    samples and only calibrate-poses refused it; now the import names it."""
    shutil.copy(DATA / "pose_initial_guesses.yaml", tmp_path / "pose_initial_guesses.yaml")
    text = (DATA / "measurements.yaml").read_text()
    assert text.count("  - -0.5229825973510742\n") > 1
    (tmp_path / "measurements.yaml").write_text(text.replace("  - -0.5229825973510742\n", "  - -29.96\n", 1))
    assert run(["import-positioner", "--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "measurements.yaml (in time order): pose 0, field q1" in err and "looks like degrees" in err, err
    assert not (tmp_path / "o").exists()


def test_a_guess_in_millimetres_is_refused_at_the_import(run, tmp_path, capsys):
    """The tester's edit: the camera guess's x typed in millimetres (2200 for 2.2 m), which the
    import took as a sensor 2.2 km away; now the D-H lengths' units rule names the key."""
    shutil.copy(DATA / "measurements.yaml", tmp_path / "measurements.yaml")
    text = (DATA / "pose_initial_guesses.yaml").read_text()
    assert "  x: 2.2\n" in text
    (tmp_path / "pose_initial_guesses.yaml").write_text(text.replace("  x: 2.2\n", "  x: 2200\n", 1))
    assert run(["import-positioner", "--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert ("pose_initial_guesses.yaml: camera_mount_to_camera_guess.x: 2200 m is not a plausible length: lengths "
            "are in metres (this looks like millimetres or centimetres)") in err, err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("file, old, new, expected", [
    ("pose_initial_guesses.yaml", "camera_mount_to_camera_guess:", "camera_mount_to_camera_gess:",
     "pose_initial_guesses.yaml: unknown key 'camera_mount_to_camera_gess'; did you mean 'camera_mount_to_camera_guess'?"),
    ("pose_initial_guesses.yaml", "  qw: 1.0\n", "  w: 1.0\n  qw: 1.0\n",
     "pose_initial_guesses.yaml: camera_mount_to_camera_guess: unknown key 'w'"),
    ("measurements.yaml", "  camera_joints: []\n", "  camera_joints: []\n  target_joint_velocities: [0.0, 0.0]\n",
     "measurements.yaml: 1593701755: unknown key 'target_joint_velocities'; did you mean 'target_joints'?"),
    # not finite: written into samples.csv as nan with exit 0, refused only by the next command
    ("measurements.yaml", "'1593701755':", "'nan':", "measurements.yaml: nan: key is not a time stamp in seconds "
                                                     "(not finite: 'nan')"),
    ("measurements.yaml", "  - -0.5229825973510742\n", "  - .nan\n", ".target_joints[0]: not finite (nan)"),
    # a stamp in milliseconds was read as seconds: year 52,000, every drift rate 1000 times too small
    ("measurements.yaml", "'1593701755':", "'1593701755000':", "measurements.yaml: 1593701755000: key is not a time "
                                                               "stamp in seconds (this looks like milliseconds"),
])
def test_an_unknown_key_is_refused_at_the_import(run, tmp_path, capsys, file, old, new, expected):
    """A misspelt or unexpected key in the source files was dropped without a word (the tester's
    probe); each is now one line naming the file, the entry and the nearest known key. So is a
    value that is no number."""
    for name in ("pose_initial_guesses.yaml", "measurements.yaml"):
        text = (DATA / name).read_text()
        if name == file:
            assert old in text
            text = text.replace(old, new, 1)
        (tmp_path / name).write_text(text)
    assert run(["import-positioner", "--data", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert expected in err and "Traceback" not in err, err
    assert not (tmp_path / "o").exists()
