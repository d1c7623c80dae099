"""Bad input a new user met that was not one line naming the file (or was taken silently):
each case exits 2 with one 'laser-calib' line, the last on stderr, that names the file
and writes nothing."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from cli_status import exit_status
from laser_calib.io.samples import format_samples
from laser_calib.io.errors import InputError
from laser_calib.model.robot_file import dump_robot, load_robot, robot_to_dict, save_robot
from laser_calib.sim.simulation import bundled_robot, paper_session

ROBOT = bundled_robot("paper-4dof")
SESSION = paper_session("paper-4dof", 0, n_per_span=6)
SAMPLES = format_samples(SESSION.samples)


def _robot_yaml(edit=None) -> str:
    data = robot_to_dict(ROBOT)
    if edit is not None:
        edit(data)
    return yaml.safe_dump(data, sort_keys=False)


def _files(folder: Path, robot: str | None = None, samples: str | None = None) -> tuple[str, str]:
    (folder / "robot.yaml").write_text(dump_robot(ROBOT) if robot is None else robot)
    (folder / "samples.csv").write_text(SAMPLES if samples is None else samples)
    return str(folder / "robot.yaml"), str(folder / "samples.csv")


def _one_line(argv: list[str], capsys) -> str:
    """The command's exit status is 2 and its last stderr line the only 'laser-calib' one: returned."""
    code = exit_status(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert not any("Traceback" in line for line in err), err
    assert [line for line in err if line.startswith("laser-calib")] == err[-1:], err
    return err[-1]


def test_a_robot_whose_beams_miss_every_spot_is_named(tmp_path, capsys):
    """The last link's length written in millimetres (100, within the plausible lengths): every
    measured spot is refused as impossible. The line named neither the robot nor the samples."""
    robot = _robot_yaml(lambda r: r["joints"][3].__setitem__("a", 100.0))
    r, s = _files(tmp_path, robot)
    for command in ("estimate", "diagnose"):
        line = _one_line([command, "--robot", r, "--samples", s, "--out", str(tmp_path / "out")], capsys)
        assert f"laser-calib: {r}: no measured spot of {s}" in line, line
        assert not (tmp_path / "out").exists()


def test_the_keys_only_a_diagnosis_reads_are_checked_when_the_robot_file_is_read(tmp_path, capsys):
    """A negative or textual rated noise, an unknown sensor kind, limits that are no mapping: every
    command took them silently (simulate copied them into its robot files), and diagnose refused
    them only after the whole diagnosis, naming 'robot' instead of the file."""
    cases = {"spot_sigma": (-0.001, "spot_sigma: -0.001 m is not a plausible spot noise"),
             "joint_reading_sigma": ("small", "joint_reading_sigma: expected a number"),
             "sensor_kind": ("laser_tracker_x", "sensor_kind: expected one of"),
             "sensor_limits": ({"scale": -1.0}, "sensor_limits.scale: must be positive")}
    for key, (value, expected) in cases.items():
        r, s = _files(tmp_path, _robot_yaml(lambda data: data.__setitem__(key, value)))
        line = _one_line(["identify", "--robot", r, "--samples", s], capsys)
        assert line.startswith(f"laser-calib: {r}: {expected}"), line
    # valid values load
    r, s = _files(tmp_path, _robot_yaml(lambda data: data.update(
        spot_sigma=0.0005, joint_reading_sigma=0.001, sensor_kind="laser_tracker", sensor_limits={"scale": 1e-3})))
    assert exit_status(["identify", "--robot", r, "--samples", s]) == 0


def test_a_tip_column_naming_no_tip_names_the_file(tmp_path, capsys):
    """calibrate-poses with a 'tip' of 5 for a one-tip robot said 'pose 0: tip 5 is not one of
    0..0', naming no file."""
    robot = bundled_robot("paper-4dof")
    (tmp_path / "robot.yaml").write_text(dump_robot(robot))
    header = "pose,stamp,q1,q2,q3,q4,x,y,z,tip"
    rows = [f"{k},{k}.0,{0.1 * (k % 3)},{0.02 * k},{-0.1 * (k % 4)},{0.2},{1.0 + 0.01 * k},0.5,0.2,{5 if k == 3 else 0}"
            for k in range(12)]
    (tmp_path / "points.csv").write_text("\n".join([header, *rows]) + "\n")
    line = _one_line(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples",
                      str(tmp_path / "points.csv"), "--folds", "0", "--out", str(tmp_path / "out")], capsys)
    assert line.startswith(f"laser-calib: {tmp_path / 'points.csv'}: pose 3, field tip: 5 is not one of 0..0"), line
    assert not (tmp_path / "out").exists()


def test_plan_keeps_its_robot_file_and_says_a_failed_write(tmp_path, capsys):
    """plan --out naming the --robot file replaced the robot with the pose list, exit 0; a write
    that fails (a full disk) was a traceback, in plan and slm-calibrate alike."""
    r, _ = _files(tmp_path)
    before = Path(r).read_text()
    line = _one_line(["plan", "--robot", r, "--n", "5", "--candidates", "100", "--out", r], capsys)
    assert line.startswith(f"laser-calib: {r}: is the --robot file"), line
    assert Path(r).read_text() == before
    if Path("/dev/full").exists():  # Linux: every write fails with ENOSPC
        line = _one_line(["plan", "--robot", r, "--n", "5", "--candidates", "100", "--out", "/dev/full"], capsys)
        assert line == "laser-calib: /dev/full: cannot write (No space left on device)", line
        (tmp_path / "slm.csv").write_text("laser,distance,u,v\n1,0.5,0,0\n1,1.0,0.01,0.25\n1,1.5,0.02,0.5\n"
                                          "2,0.5,0,0\n2,1.0,0.01,-0.3\n2,1.5,0.02,-0.6\n")
        line = _one_line(["slm-calibrate", "--robot", r, "--measurements", str(tmp_path / "slm.csv"),
                          "--out", "/dev/full"], capsys)
        assert line == "laser-calib: /dev/full: cannot write (No space left on device)", line


def test_a_screen_calibration_that_maps_every_pixel_to_one_point_is_refused(tmp_path):
    """The spot detector's calibration file: a zero focal length, a last row of K of zeros or a
    zero homography loaded, and every pixel then mapped to the screen's (0, 0), spots that look
    measured; a Latin-1 byte escaped as UnicodeDecodeError."""
    import pytest
    from laser_calib.io.errors import InputError
    from laser_calib.vision.camera import calibration_to_dict, default_camera, load_calibration

    good = calibration_to_dict(default_camera().ideal_calibration())
    path = tmp_path / "calibration.yaml"
    path.write_text(yaml.safe_dump(good))
    assert load_calibration(path).width == good["image_width"]
    edits = {"fx 0": lambda d: d["camera_matrix"][0].__setitem__(0, 0.0),
             "last row 0": lambda d: d["camera_matrix"][2].__setitem__(2, 0.0),
             "homography 0": lambda d: d.__setitem__("homography", [[0.0] * 3, [0.0] * 3, [0.0, 0.0, 1.0]])}
    for name, edit in edits.items():
        data = yaml.safe_load(yaml.safe_dump(good))
        edit(data)
        path.write_text(yaml.safe_dump(data))
        with pytest.raises(InputError, match=str(path)):
            load_calibration(path)
    path.write_bytes(yaml.safe_dump(good).replace("image_width", "# caméra\nimage_width").encode("latin-1"))
    with pytest.raises(InputError, match="not UTF-8"):
        load_calibration(path)


def test_screen_calibrate_names_the_folder_without_board_views(tmp_path, capsys):
    """Blank images (or the two folders swapped) said 'laser-calib screen-calibrate: only 0 usable
    ChArUco views, need at least 4', naming neither folder."""
    import cv2
    import numpy as np

    for folder in ("board", "screen"):
        (tmp_path / folder).mkdir()
        for k in range(4):
            cv2.imwrite(str(tmp_path / folder / f"{k}.png"), np.full((48, 64, 3), 128, np.uint8))
    line = _one_line(["screen-calibrate", "--board-images", str(tmp_path / "board"), "--screen-images",
                      str(tmp_path / "screen"), "--out", str(tmp_path / "c.yaml")], capsys)
    assert line.startswith(f"laser-calib: {tmp_path / 'board'}: only 0 usable ChArUco views"), line
    assert not (tmp_path / "c.yaml").exists()


def test_a_robot_file_written_by_a_failed_fit_is_refused(tmp_path):
    # The failed fit's robot_calibrated.yaml carries its failure only as a comment: read back as a
    # nominal model by estimate, plan or simulate, it passed the failure on with exit 0.
    robot_file = tmp_path / "robot_calibrated.yaml"
    save_robot(ROBOT, robot_file, header="Calibrated by laser_calib (lm) from 60 poses.\n"
                                         "NO CALIBRATION: NOT CONVERGED after 50 iterations")
    with pytest.raises(InputError, match=r"robot_calibrated.yaml: line 2: written by a fit that is no "
                                         r"calibration \(NOT CONVERGED after 50 iterations\)"):
        load_robot(robot_file)
    save_robot(ROBOT, robot_file, header="Calibrated by laser_calib (lm) from 60 poses.")
    assert load_robot(robot_file).name == ROBOT.name
