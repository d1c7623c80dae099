"""Bad options and inputs of the commands the first bad-input pass left out
(render-calibration-images, screen-calibrate, slm-calibrate, identify, --seed,
noise and tolerance sizes): one line on stderr naming the option or file, exit
status 2, no traceback, nothing half-written; the plausible values still pass."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from cli_status import exit_status
from laser_calib.cli import vision as vision_cli
from laser_calib.cli.main import build_parser
from laser_calib.io.samples import format_samples
from laser_calib.model.robot_file import dump_robot, robot_to_dict
from laser_calib.sim.simulation import bundled_robot, paper_session

ROBOT = bundled_robot("paper-4dof")
SESSION = paper_session("paper-4dof", 0, n_per_span=6)
# the bundled robot's lasers (gamma -27.8 and 31.1 deg, beta about 1 deg) within a degree or two
SLM_ROWS = "1,0.5,0.01,0.25\n1,1.0,0.02,0.5\n1,1.5,0.03,0.75\n2,0.5,0.01,-0.3\n2,1.0,0.02,-0.6\n2,1.5,0.03,-0.9\n"


def _files(folder: Path, spots: np.ndarray | None = None) -> tuple[str, str]:
    """robot.yaml and samples.csv (with the given spots instead of the simulated ones)."""
    samples = SESSION.samples
    if spots is not None:
        samples = type(samples)(samples.pose, samples.stamp, samples.q, spots)
    (folder / "robot.yaml").write_text(dump_robot(ROBOT))
    (folder / "samples.csv").write_text(format_samples(samples))
    return str(folder / "robot.yaml"), str(folder / "samples.csv")


def _no_spots(folder: Path, command: str) -> list[str]:
    robot, samples = _files(folder, np.full_like(SESSION.samples.spots, np.nan))
    out = ["--out", str(folder / "out")] if command == "estimate" else []
    return [command, "--robot", robot, "--samples", samples, *out]


def _estimate(folder: Path, *extra: str) -> list[str]:
    robot, samples = _files(folder)
    return ["estimate", "--robot", robot, "--samples", samples, "--out", str(folder / "out"), *extra]


def _simulate(folder: Path, *extra: str) -> list[str]:
    return ["simulate", "--case", "paper-4dof", "--out", str(folder / "out"), *extra]


def _render(folder: Path, out: str | None = None, *extra: str) -> list[str]:
    return ["render-calibration-images", "--out", out or str(folder / "out"), "--board-views", "1",
            "--screen-views", "1", *extra]


def _screen(folder: Path, out: str) -> list[str]:
    """Empty image folders: a checked --out is refused before any image is looked for."""
    (folder / "empty").mkdir()
    return ["screen-calibrate", "--board-images", str(folder / "empty"), "--screen-images", str(folder / "empty"),
            "--out", out]


def _slm(folder: Path, rows: str = SLM_ROWS, robot: str | None = None) -> list[str]:
    (folder / "robot.yaml").write_text(dump_robot(ROBOT) if robot is None else robot)
    (folder / "slm.csv").write_text("laser,distance,u,v\n" + rows)
    return ["slm-calibrate", "--robot", str(folder / "robot.yaml"), "--measurements", str(folder / "slm.csv"),
            "--out", str(folder / "out")]


def _without_slm() -> str:
    data = robot_to_dict(ROBOT)
    del data["slm"], data["lasers"]
    return yaml.safe_dump(data, sort_keys=False)


def _taken(folder: Path) -> str:
    (folder / "taken").write_text("x")
    return str(folder / "taken")


MM_ROWS = SLM_ROWS.replace("1,0.5,", "1,500,").replace("1,1.0,", "1,1000,").replace("1,1.5,", "1,1500,")

CASES = {
    "render --out is a file": (lambda d: _render(d, _taken(d)), "--out"),
    "render --out unwritable": (lambda d: _render(d, "/proc/x/y"), "/proc"),
    "render --seed -1": (lambda d: _render(d, None, "--seed", "-1"), "--seed"),
    "screen-calibrate --out is a folder": (lambda d: _screen(d, str(d)), "--out"),
    "screen-calibrate --out unwritable": (lambda d: _screen(d, "/proc/x/y.yaml"), "/proc"),
    "slm distances in millimetres": (lambda d: _slm(d, MM_ROWS), "slm.csv: line 2, field distance"),
    "slm robot without slm": (lambda d: _slm(d, "not even a header", _without_slm()), "robot.yaml"),
    "identify with every spot missing": (lambda d: _no_spots(d, "identify"), "samples.csv: no measured spot"),
    "estimate with every spot missing": (lambda d: _no_spots(d, "estimate"), "samples.csv: no measured spot"),
    "simulate --seed -1": (lambda d: _simulate(d, "--seed", "-1"), "--seed"),
    "simulate --spot-noise 2 (m)": (lambda d: _simulate(d, "--spot-noise", "2"), "--spot-noise"),
    "simulate --joint-noise-deg 1000": (lambda d: _simulate(d, "--joint-noise-deg", "1000"), "--joint-noise-deg"),
    # 0.1 deg typed as radians: 5.7 deg weighed every pose by a noise its spots did not show (exit 0)
    "estimate --joint-sigma 0.1 (deg)": (lambda d: _estimate(d, "--joint-sigma", "0.1"),
                                         "--joint-sigma: 0.1 rad is not a plausible joint noise (at most 0.035 rad"),
    "estimate --prior-length 10 (m)": (lambda d: _estimate(d, "--prior-length", "10"), "--prior-length"),
    # a tolerance of almost three turns: taken as given, a prior that says nothing
    "estimate --prior-angle-deg 1000": (lambda d: _estimate(d, "--prior-angle-deg", "1000"),
                                        "--prior-angle-deg: 1000 deg is not a plausible tolerance"),
    # 0.5 mm typed as metres: accepted as a camera's noise of half a metre (under the 1 m of every noise level)
    "estimate --spot-sigma 0.5 (m)": (lambda d: _estimate(d, "--spot-sigma", "0.5"), "--spot-sigma: 0.5 m is not a "
                                                                                       "plausible spot noise"),
    "slm-calibrate --spot-sigma 0.5 (m)": (lambda d: [*_slm(d), "--spot-sigma", "0.5"], "--spot-sigma: 0.5 m"),
    "identify --spot-sigma 0.5 (m)": (lambda d: [*_no_spots(d, "identify"), "--spot-sigma", "0.5"], "--spot-sigma"),
    "plan --spot-sigma 0.5 (m)": (lambda d: ["plan", "--robot", _files(d)[0], "--n", "5", "--out", str(d / "out"),
                                             "--spot-sigma", "0.5"], "--spot-sigma: 0.5 m"),
    "diagnose --spot-sigma 0.5 (m)": (lambda d: ["diagnose", "--robot", _files(d)[0], "--samples", _files(d)[1],
                                                 "--out", str(d / "out"), "--spot-sigma", "0.5"], "--spot-sigma: 0.5 m"),
    # degrees typed as radians: taken as a joint-reading noise of 30 rad
    "diagnose --joint-sigma 30 (deg)": (lambda d: ["diagnose", "--robot", _files(d)[0], "--samples", _files(d)[1],
                                                   "--out", str(d / "out"), "--joint-sigma", "30"],
                                        "--joint-sigma: 30 rad is not a plausible joint noise"),
    # the robot file's rated noise in millimetres: the estimated noise was tested against half a metre,
    # so a joint error the noise estimate took in was never evidence of structure
    "robot file spot_sigma 0.5 (m)": (lambda d: _diagnose_rated(d, "spot_sigma", 0.5),
                                      "robot.yaml: spot_sigma: 0.5 m is not a plausible spot noise"),
    "robot file joint_reading_sigma 2 (deg)": (lambda d: _diagnose_rated(d, "joint_reading_sigma", 2),
                                               "robot.yaml: joint_reading_sigma: 2 rad is not a plausible "
                                               "joint-reading noise"),
}


def _diagnose_rated(folder: Path, key: str, value: float) -> list[str]:
    """diagnose with a robot file whose rated noise ``key`` is ``value``."""
    robot, samples = _files(folder)
    (folder / "robot.yaml").write_text(yaml.safe_dump({**robot_to_dict(ROBOT), key: value}, sort_keys=False))
    return ["diagnose", "--robot", robot, "--samples", samples, "--out", str(folder / "out")]


@pytest.mark.parametrize("name", list(CASES))
def test_bad_option_is_one_line_and_exit_2(name, tmp_path, capsys):
    make, expected = CASES[name]
    code = exit_status(make(tmp_path))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, (name, err)
    assert not any("Traceback" in line for line in err)
    assert [line for line in err if line.startswith("laser-calib")] == err[-1:], err
    assert expected in err[-1], err[-1]
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.partial-*"))


def test_slm_millimetres_are_named_as_such(tmp_path, capsys):
    assert exit_status(_slm(tmp_path, MM_ROWS)) == 2
    err = capsys.readouterr().err
    assert "500 m" in err and "looks like millimetres" in err


def test_plausible_sizes_and_seeds_are_accepted():
    args = build_parser().parse_args(["simulate", "--case", "paper-4dof", "--out", "o", "--seed", "0",
                                      "--spot-noise", "0", "--joint-noise-deg", "0"])
    assert (args.seed, args.spot_noise, args.joint_noise_deg) == (0, 0.0, 0.0)
    args = build_parser().parse_args(["simulate", "--case", "paper-4dof", "--out", "o", "--spot-noise", "0.5",
                                      "--joint-noise-deg", "2"])
    assert (args.spot_noise, args.joint_noise_deg) == (0.5, 2.0)
    args = build_parser().parse_args(["estimate", "--robot", "r", "--samples", "s", "--out", "o",
                                      "--prior-length", "0.01"])
    assert args.prior_length == 0.01
    # a spot sigma up to 50 mm passes; other lengths keep the 1 m bound (a position sensor's noise, a tolerance)
    assert build_parser().parse_args(["slm-calibrate", "--robot", "r", "--measurements", "m", "--out", "o",
                                      "--spot-sigma", "0.05"]).spot_sigma == 0.05
    args = build_parser().parse_args(["calibrate-poses", "--robot", "r", "--samples", "s", "--out", "o",
                                      "--sigma", "0.5", "--frame-prior-length", "0.5"])
    assert (args.sigma, args.frame_prior_length) == (0.5, 0.5)
    assert build_parser().parse_args(["render-calibration-images", "--out", "o", "--seed", "7"]).seed == 7


def test_slm_in_metres_still_calibrates(tmp_path):
    assert exit_status(_slm(tmp_path)) == 0 and (tmp_path / "out").is_file()


@pytest.fixture
def blank_frames(monkeypatch):
    """Tiny blank frames instead of rendered ones: these tests are about the folders, not the images."""
    blank = np.zeros((4, 4, 3), np.uint8)
    monkeypatch.setattr(vision_cli, "render_board_frame", lambda *_, **__: blank)
    monkeypatch.setattr(vision_cli, "render_fiducial_frame", lambda *_, **__: blank)


def test_a_render_that_fails_midway_leaves_no_folder(tmp_path, monkeypatch, capsys, blank_frames):
    """The disk fills after the first image: one line naming --out's folder, and no board/ left."""
    written = []
    real = vision_cli.cv2.imwrite

    def filling(path, image):
        if written:
            raise OSError(28, "No space left on device")
        written.append(path)
        return real(path, image)
    monkeypatch.setattr(vision_cli.cv2, "imwrite", filling)
    assert exit_status(_render(tmp_path)) == 2
    assert capsys.readouterr().err.strip().endswith("out: cannot write (No space left on device)")
    assert written and not (tmp_path / "out").exists() and not list(tmp_path.glob(".out.partial-*"))


def test_a_second_render_replaces_the_image_folders(tmp_path, blank_frames):
    """A smaller second run must not leave the first run's extra views behind: screen-calibrate
    reads every image of the folder."""
    assert exit_status(["render-calibration-images", "--out", str(tmp_path / "out"), "--board-views", "2",
                 "--screen-views", "1"]) == 0
    assert exit_status(_render(tmp_path)) == 0
    assert sorted(p.name for p in (tmp_path / "out" / "board").iterdir()) == ["board_000.png"]


ARGUMENT_ERRORS = {
    "estimate --spot-sigma -1": (["estimate", "--robot", "R", "--samples", "S", "--spot-sigma", "-1", "--out", "X"],
                                 "laser-calib estimate: argument --spot-sigma: expected a positive number, got -1"),
    "estimate --bag and --samples": (["estimate", "--bag", "B", "--samples", "S"],
                                     "laser-calib estimate: argument --samples: not allowed with argument --bag"),
    "calibrate-poses --chronological 1.5": (["calibrate-poses", "--robot", "R", "--samples", "S", "--out", "X",
                                             "--chronological", "1.5"],
                                            "laser-calib calibrate-poses: argument --chronological: expected a "
                                            "fraction between 0 and 1, got 1.5"),
    "plan --out in no folder": (["plan", "--robot", "R", "--n", "3", "--out", "/nonexistent-folder/x.csv"],
                                "laser-calib plan: argument --out: /nonexistent-folder/x.csv: the folder "
                                "/nonexistent-folder does not exist"),
    "diagnose without --out": (["diagnose", "--robot", "R", "--samples", "S"],
                               "laser-calib diagnose: the following arguments are required: --out"),
    "no command": ([], "laser-calib: the following arguments are required: command"),
    # argparse kept the last: the second compensator was applied, the first dropped without a word
    "estimate --compensator twice": (["estimate", "--robot", "R", "--samples", "S", "--out", "X", "--compensator",
                                      "A", "--compensator=B"],
                                     "laser-calib estimate: argument --compensator: given twice; give it once"),
    # argparse kept the last list: only b was held
    "calibrate-poses --fix twice": (["calibrate-poses", "--robot", "R", "--samples", "S", "--out", "X", "--fix", "a",
                                     "--fix", "b"], "laser-calib calibrate-poses: argument --fix: given twice; give "
                                                    "it once, with all its values"),
    # an empty --fix was taken as "hold nothing"
    "estimate --fix without names": (["estimate", "--robot", "R", "--samples", "S", "--out", "X", "--fix"],
                                     "laser-calib estimate: argument --fix: expected at least one argument"),
}


@pytest.mark.parametrize("name", list(ARGUMENT_ERRORS))
def test_an_argument_error_is_one_line_without_the_usage(name, capsys):
    """argparse printed its usage block (4-13 lines) before the line saying what is wrong: now
    that line alone, naming the command and the argument, as any bad input."""
    argv, expected = ARGUMENT_ERRORS[name]
    assert exit_status(argv) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [expected] and captured.out == ""


def test_help_still_shows_the_usage(capsys):
    assert exit_status(["estimate", "--help"]) == 0
    assert capsys.readouterr().out.startswith("usage: laser-calib estimate [-h] --robot ROBOT")
