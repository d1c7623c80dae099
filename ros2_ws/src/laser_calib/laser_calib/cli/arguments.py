"""Argument types of the command line: each checks one text and returns its
value, or raises argparse.ArgumentTypeError (the parser, OneLineParser, then
prints one line and exits with status 2); output folders written all or nothing
(staged_folder); warnings printed one line each; samples with nothing measured
refused."""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from laser_calib.estimation.failures import NoSpotToFit, is_failure
from laser_calib.estimation.identifiability import CHECK_UNITS
from laser_calib.io.errors import InputError
from laser_calib.io.read import parse_int, parse_number
from laser_calib.io.sensor_samples import POINT_COLUMNS, QUATERNION_COLUMNS
from laser_calib.measurement.noise_bounds import MAX_SIGMA_ANGLE, SIGMA_LENGTH, spot_sigma_problem
from laser_calib.session.folder import refuse_finished


class OneLineParser(argparse.ArgumentParser):
    """An argument error as one line on stderr, 'laser-calib estimate: argument --spot-sigma: ...',
    exit status 2, as for any bad input (argparse printed its whole usage block first, 4-13 lines
    before the one that says what is wrong); --help still shows the usage. Subparsers are made of
    their parser's class, so the main parser's is every command's."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: {message}\n")

    def parse_known_args(self, args=None, namespace=None):
        """As argparse's, refusing an option given twice: argparse keeps the last value silently,
        so `--compensator A --compensator B` applied B, and `--fix a --fix b` held b alone."""
        words = sys.argv[1:] if args is None else list(args)
        seen = set()
        for word in words[:words.index("--")] if "--" in words else words:
            action = self._option_string_actions.get(word.split("=", 1)[0]) if word.startswith("-") else None
            # a flag said twice says the same; an append action collects its repeats
            if action is None or action.nargs == 0 or isinstance(action, (argparse._AppendAction, argparse._CountAction)):
                continue
            if action in seen:
                self.error(f"argument {'/'.join(action.option_strings)}: given twice; give it once"
                           + (", with all its values" if action.nargs in ("*", "+") else ""))
            seen.add(action)
        return super().parse_known_args(args, namespace)


# Plausible noise levels (measurement.noise_bounds); a length tolerance is bounded like a noise
# level: 10 (mm typed as m) is no arm's tolerance.
MAX_SIGMA_DEG = math.degrees(MAX_SIGMA_ANGLE)


def _number(text: str, allow_zero: bool) -> float:
    try:
        value = parse_number(text, "")
    except InputError as exc:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r} ({exc.problem})") from None
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise argparse.ArgumentTypeError(f"expected a {'non-negative' if allow_zero else 'positive'} number, "
                                         f"got {text}")
    return value


def positive(text: str) -> float:
    return _number(text, allow_zero=False)


def non_negative(text: str) -> float:
    return _number(text, allow_zero=True)


def _length(text: str, what: str, low: float, high: float = SIGMA_LENGTH[1]) -> float:
    """A length in metres within low .. high (low 0: zero allowed)."""
    value = _number(text, allow_zero=low == 0)
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(f"{text} m is not a plausible {what} (expected {low:g} .. "
                                         f"{high:g} m; lengths are in metres)")
    return value


def sigma_length(text: str) -> float:
    """A noise standard deviation in metres."""
    return _length(text, "noise level", SIGMA_LENGTH[0])


def spot_sigma(text: str) -> float:
    """A spot's noise standard deviation on the screen in metres (measurement.noise_bounds)."""
    value = positive(text)
    problem = spot_sigma_problem(value)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return value


def tolerance_length(text: str) -> float:
    """A prior's length tolerance in metres: the same range as a noise level."""
    return _length(text, "tolerance", SIGMA_LENGTH[0])


def tolerance_angle_deg(text: str) -> float:
    """A prior's angle tolerance in degrees: beyond half a turn it says nothing of an angle."""
    value = positive(text)
    if value > 180:
        raise argparse.ArgumentTypeError(f"{text} deg is not a plausible tolerance (at most 180 deg; this option is "
                                         "in degrees)")
    return value


def noise_length(text: str) -> float:
    """A simulated noise half-width in metres (0: none)."""
    return _length(text, "noise level", 0.0)


def _joint_noise(text: str, limit: float, unit: str) -> float:
    """A joint noise in ``unit`` (0: none) up to limit, the same angle in either unit."""
    value = non_negative(text)
    if value > limit:
        raise argparse.ArgumentTypeError(f"{text} {unit} is not a plausible joint noise (at most {limit:.3g} {unit}; "
                                         f"this option is in {'radians' if unit == 'rad' else 'degrees'})")
    return value


def sigma_angle(text: str) -> float:
    """A joint noise standard deviation in radians (0: none)."""
    return _joint_noise(text, MAX_SIGMA_ANGLE, "rad")


def noise_angle_deg(text: str) -> float:
    """A simulated joint noise half-width in degrees (0: none), bounded as sigma_angle."""
    return _joint_noise(text, MAX_SIGMA_DEG, "deg")


def _integer(text: str, minimum: int) -> int:
    try:
        value = parse_int(text, "")
    except InputError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text[:40]!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"expected an integer of at least {minimum}, got {text}")
    return value


def non_negative_int(text: str) -> int:
    return _integer(text, 0)


def positive_int(text: str) -> int:
    return _integer(text, 1)


def span_poses(text: str) -> int:
    """Poses in each span of a simulated session: at least 2 (case 2 calibrates on half of each span and
    tests on the other half; with 1 its calibration set was empty, written as a header alone)."""
    return _integer(text, 2)


def fold_count(text: str) -> int:
    """Cross-validation folds: at least 2 (one fold leaves nothing to train on)."""
    return _integer(text, 2)


def readable_file(text: str) -> str:
    """An input file that exists and can be read (refused before any work, not after the progress line)."""
    path = Path(text)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    if not path.is_file() or not os.access(path, os.R_OK):
        raise argparse.ArgumentTypeError(f"{text}: {'a folder, not a file' if path.is_dir() else 'cannot be read'}")
    return text


def add_replay_arguments(parser: argparse.ArgumentParser) -> None:
    """The replay node's arguments (laser_calib_nodes.replay), which `laser-calib replay` takes
    too and hands on (replay_argv): one definition for both."""
    parser.add_argument("bag", help="session bag directory (rosbag2, MCAP)")
    parser.add_argument("--rate", type=positive, default=1.0, help="playback speed factor (default 1)")
    parser.add_argument("--topics", nargs="+", help="only these topics (default: all but motion commands)")
    parser.add_argument("--exclude", nargs="+", default=[], help="not these topics (each must be in the bag)")
    parser.add_argument("--wait-for", nargs="+", default=[], metavar="TOPIC",
                        help="start once each of these topics has a subscriber (without it, messages sent "
                             "while their topic had none are counted in a warning)")
    parser.add_argument("--wait-timeout", type=positive, default=30.0, help="for --wait-for, s (default 30)")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")


def replay_argv(args: argparse.Namespace) -> list[str]:
    """The replay node's command line for arguments parsed by add_replay_arguments."""
    argv = [args.bag, "--rate", repr(args.rate), "--wait-timeout", repr(args.wait_timeout)]
    for flag, topics in (("--topics", args.topics), ("--exclude", args.exclude), ("--wait-for", args.wait_for)):
        argv += [flag, *topics] if topics else []
    return argv + (["--quiet"] if args.quiet else [])


def add_robot_arguments(parser: argparse.ArgumentParser) -> None:
    """--robot (a robot YAML, or a URDF / xacro file with --base and --tip)."""
    parser.add_argument("--robot", required=True, help="robot YAML, or URDF / xacro (then --base and --tip)")
    parser.add_argument("--base", default=None, help="URDF link the chain starts from (the robot's frame {0})")
    parser.add_argument("--tip", nargs="+", default=None,
                        help="URDF link(s) measured: one tip, or several of a tree sharing joints")


def fraction(text: str) -> float:
    """A number strictly between 0 and 1."""
    value = _number(text, allow_zero=False)
    if value >= 1:
        raise argparse.ArgumentTypeError(f"expected a fraction between 0 and 1, got {text}")
    return value


# The fields a row leaves empty where its measurement was not seen, by Samples.kind.
MEASURED_FIELDS = {"spot": "spot", "point": ", ".join(POINT_COLUMNS),
                   "pose": ", ".join(POINT_COLUMNS + QUATERNION_COLUMNS)}


def require_measured(samples, source: str, problem: str | None = None) -> None:
    """One line naming the file when nothing in it is measured: nothing to fit or to judge.
    problem: what is wrong, by default 'no measured <spot, point or pose>'."""
    if not samples.seen.any():
        raise InputError(source, f"{problem or 'no measured ' + samples.kind} "
                                 f"(every {MEASURED_FIELDS[samples.kind]} field empty)")


def no_spot_to_fit(robot: str, samples: str, compensator: str | None = None) -> InputError:
    """NoSpotToFit as one line naming the robot file: the samples hold measured spots
    (require_measured), so the nominal model (with the compensator, if any) put every one
    out of reach, refused as impossible (its beam misses the screen, or lands far from it)."""
    return InputError(robot, f"no measured spot of {samples} to fit: at every one the nominal model's beam"
                             + (f" (compensated by {compensator})" if compensator else "")
                             + " misses the screen or lands far from the spot, and each was refused as impossible; "
                               f"{CHECK_UNITS}" + (" and the compensator" if compensator else ""))


# A fit that did not converge, or whose minimum dropped measurements: its files are written
# (nothing measured is lost, and they show where the fit went) but they are not a
# calibration, so a script must not take them for one (estimation/failures.py).
EXIT_NOT_A_CALIBRATION = 3


def print_warnings(warnings: list[str]) -> int:
    """One line each on stderr, a failed fit's an error line: on the console even when the
    command's results (stdout) go to a file or a pipe. The command's exit status:
    EXIT_NOT_A_CALIBRATION after such a fit, else 0."""
    for warning in warnings:
        print(f"{'error' if is_failure(warning) else 'warning'}: {warning}", file=sys.stderr)
    return EXIT_NOT_A_CALIBRATION if any(map(is_failure, warnings)) else 0


def print_notes(notes: list[str], label: str = "note") -> None:
    """One line each on stderr, as the warnings: on the console even when the command's
    results (stdout) go to a file or a pipe."""
    for note in notes:
        print(f"{label}: {note}", file=sys.stderr)


def _writable_ancestor(path: Path) -> Path:
    """The nearest existing folder at or above path's parent, which must be writable."""
    ancestor = path.absolute().parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir() or not os.access(ancestor, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"{path}: cannot write under {ancestor}")
    return ancestor


def out_folder(text: str) -> str:
    """An output folder: absent (created) or an existing folder, under a writable one."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} exists and is not a folder")
    _writable_ancestor(path)
    return text


def out_file(text: str) -> str:
    """An output file: not a folder, in an existing writable folder."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder; give the name of the file to write")
    if not path.absolute().parent.is_dir():
        raise argparse.ArgumentTypeError(f"{text}: the folder {path.absolute().parent} does not exist")
    _writable_ancestor(path)
    return text


@contextmanager
def staged_folder(out: str) -> Iterator[Path]:
    """A fresh folder beside ``out`` to write into. On success its files replace
    the same names in ``out`` (other files there are left and named, so it is
    clear what this run wrote), a subfolder as a whole (no file of an earlier
    run left in it, on stderr); on failure it is removed, so a failed run leaves no
    half-written folder."""
    target = Path(out)
    refuse_finished(target, "--out")
    try:
        target.absolute().parent.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f".{target.name}.partial-", dir=target.absolute().parent))
    except OSError as exc:
        raise InputError(out, f"cannot write ({exc.strerror or exc})") from None
    try:
        yield stage
        target.mkdir(exist_ok=True)
        written = sorted(p.name for p in stage.iterdir())
        for name in written:
            _replace(stage / name, target / name, stage)
    except OSError as exc:
        raise InputError(out, f"cannot write ({exc.strerror or exc})") from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    others = sorted(p.name for p in target.iterdir() if p.name not in written)
    if others:
        print_notes([f"{out}/ also holds files this run did not write (left as they were): "
                     + ", ".join(others[:6]) + (f" and {len(others) - 6} more" if len(others) > 6 else "")])


def _replace(new: Path, old: Path, stage: Path) -> None:
    """new in old's place; an old folder is first moved into the stage, which is removed after."""
    if old.is_dir() and not old.is_symlink():
        os.replace(old, Path(tempfile.mkdtemp(prefix=".replaced-", dir=stage)) / old.name)
    os.replace(new, old)
