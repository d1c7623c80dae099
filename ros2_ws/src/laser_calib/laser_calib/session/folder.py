"""A measurement session on disk (ROS-free): pose list, samples CSV, bag, resume.

Session directory:

    session.yaml        what was started (robot, pose source, parameters) and its state
    robot.yaml          the nominal robot model used (copy)
    poses.csv           the pose sequence (pose,q1..qN), fixed at the first start
    samples.csv         the samples (conventions.md), one row appended per measured pose
    bag/                rosbag2 MCAP bag in closed segments (io.bag_writer.SegmentedBagWriter)
    .recording/         the segment being written (lost in a crash: the pose in progress)
    report.md, result.json, robot_calibrated.yaml (+ PNGs)   at the end

Resume: the bag is the journal. The k-th /samples message of the bag is the
k-th step of the pose sequence; a step counts as done once the segment holding
its sample is closed. On resume, samples.csv is rewritten from the bag when the
two differ (a crash between closing the segment and appending the row), and the
sequence continues at step k.
"""

from __future__ import annotations

import csv
import io
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import yaml

from laser_calib.io.errors import InputError
from laser_calib.model.robot import Robot
from laser_calib.model.robot_file import load_robot, save_robot
from laser_calib.io.samples import (Samples, check_joint_range, format_samples, load_samples, parse_number,
                                      sample_row)
from laser_calib.sim.simulation import sample_poses

from laser_calib.io import bag

SESSION_FILE = "session.yaml"
POSES_FILE = "poses.csv"
SAMPLES_FILE = "samples.csv"
ROBOT_FILE = "robot.yaml"
BAG_DIR = "bag"
WORK_DIR = ".recording"


@dataclass(frozen=True)
class PoseSequence:
    """The steps of a session: pose ids (P,) (repeats share an id) and joint goals (P,N)."""

    pose: np.ndarray
    q: np.ndarray

    def __len__(self) -> int:
        return len(self.pose)


# ---- pose lists -----------------------------------------------------------------

def load_poses(path: str | Path, robot: Robot) -> PoseSequence:
    """Pose list from YAML (``poses:`` list of [q1..qN] or {pose: id, q: [...]}) or
    CSV (header with q1..qN and optionally pose; other columns ignored)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(str(path), f"cannot read ({exc.strerror})") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        ids, rows = _poses_from_yaml(text, str(path), robot)
    else:
        ids, rows = _poses_from_csv(text, str(path), robot)
    if not rows:
        raise InputError(str(path), "no poses")
    q = np.array(rows, dtype=float)
    check_joint_range(q, robot, str(path), np.array(ids))
    return PoseSequence(np.array(ids, dtype=int), q)


def _check_row(values: Sequence, where: str, robot: Robot) -> list[float]:
    if not isinstance(values, (list, tuple)) or len(values) != robot.n_joints:
        count = len(values) if isinstance(values, (list, tuple)) else "not a list of"
        raise InputError(where, f"{count} joint positions, robot '{robot.name}' has {robot.n_joints}")
    out = []
    for i, value in enumerate(values):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(f"{where}, q{i + 1}", f"expected a finite number (rad), got {value!r}")
        out.append(float(value))
    return out


def _poses_from_yaml(text: str, source: str, robot: Robot) -> tuple[list[int], list[list[float]]]:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise InputError(f"{source}: line {mark.line + 1}" if mark else source, "not valid YAML") from None
    if isinstance(data, dict):
        if "poses" not in data:
            raise InputError(source, "missing key 'poses'")
        data = data["poses"]
    if not isinstance(data, list):
        raise InputError(f"{source}: poses", "expected a list of poses")
    ids, rows = [], []
    for k, entry in enumerate(data):
        where = f"{source}: poses[{k}]"
        if isinstance(entry, dict):
            if "q" not in entry:
                raise InputError(where, "missing key 'q'")
            pose = entry.get("pose", k)
            if isinstance(pose, bool) or not isinstance(pose, int):
                raise InputError(f"{where}, pose", f"expected an integer id, got {pose!r}")
            ids.append(pose)
            rows.append(_check_row(entry["q"], where, robot))
        else:
            ids.append(k)
            rows.append(_check_row(entry, where, robot))
    return ids, rows


def _poses_from_csv(text: str, source: str, robot: Robot) -> tuple[list[int], list[list[float]]]:
    lines = [row for row in csv.reader(io.StringIO(text)) if any(cell.strip() for cell in row)]
    if not lines:
        raise InputError(source, "empty file")
    header = [cell.strip() for cell in lines[0]]
    columns = [f"q{i + 1}" for i in range(robot.n_joints)]
    missing = [c for c in columns if c not in header]
    if missing:
        raise InputError(f"{source}: header", f"missing column {missing[0]} (robot '{robot.name}' has "
                                              f"{robot.n_joints} joints)")
    index = [header.index(c) for c in columns]
    pose_col = header.index("pose") if "pose" in header else None
    ids, rows = [], []
    for r, row in enumerate(lines[1:]):
        line = r + 2
        if len(row) != len(header):
            raise InputError(f"{source}: line {line}", f"{len(row)} fields, header has {len(header)}")
        if pose_col is None:
            ids.append(r)
        else:
            try:
                ids.append(int(row[pose_col]))
            except ValueError:
                raise InputError(f"{source}: line {line}, field pose", f"not an integer: {row[pose_col]!r}") from None
        rows.append([parse_number(row[i], f"{source}: line {line}, field {name}") for name, i in zip(columns, index)])
    return ids, rows


def generate_poses(robot: Robot, count: int, span: str, seed: int, repeats: int = 0,
                   margin: float = 0.02) -> PoseSequence:
    """``count`` poses whose two beams hit the screen (laser_calib.sim.simulation.sample_poses,
    nominal model), span 'small' (+-10 deg) or 'whole' (workspace); then ``repeats``
    of them, evenly spread over the list, measured again at the end with their ids."""
    if count < 1:
        raise InputError("poses", f"need at least one pose, got {count}")
    if span not in ("small", "whole"):
        raise InputError("span", f"expected 'small' or 'whole', got {span!r}")
    try:
        q = sample_poses([robot], count, np.random.default_rng(seed), span, margin)
    except RuntimeError as exc:
        raise InputError(f"robot '{robot.name}'", str(exc)) from None
    ids = np.arange(count)
    if repeats > 0:
        again = np.unique(np.linspace(0, count - 1, min(repeats, count)).round().astype(int))
        ids = np.concatenate([ids, again])
        q = np.vstack([q, q[again]])
    return PoseSequence(ids, q)


def save_poses(poses: PoseSequence, path: Path) -> None:
    n = poses.q.shape[1]
    lines = [",".join(["pose"] + [f"q{i + 1}" for i in range(n)])]
    lines += [",".join([str(int(p))] + [repr(float(v)) for v in q]) for p, q in zip(poses.pose, poses.q)]
    _write_durably(path, "\n".join(lines) + "\n")


def _write_durably(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as handle:
        handle.write(text)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


# ---- the session directory ----------------------------------------------------------

class SessionDir:
    """A session directory being measured (see the module docstring)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    @property
    def bag_dir(self) -> Path:
        return self.path / BAG_DIR

    @property
    def work_dir(self) -> Path:
        return self.path / WORK_DIR

    def state(self) -> str:
        """'new' (nothing there), 'partial' (started, not finished), 'finished'."""
        info = self.info()
        if info is None:
            return "new"
        return "finished" if info.get("state") == "finished" else "partial"

    def info(self) -> dict | None:
        path = self.path / SESSION_FILE
        if not path.exists():
            return None
        try:
            data = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError):
            raise InputError(str(path), "unreadable session file") from None
        return data if isinstance(data, dict) else {}

    def set_info(self, **updates) -> None:
        data = self.info() or {}
        data.update(updates)
        _write_durably(self.path / SESSION_FILE, yaml.safe_dump(data, sort_keys=False))

    def start(self, robot: Robot, poses: PoseSequence, info: dict) -> None:
        """A new session: robot copy, pose list, empty samples file."""
        self.path.mkdir(parents=True, exist_ok=True)
        leftovers = [p.name for p in self.path.iterdir() if p.name in (SAMPLES_FILE, BAG_DIR, POSES_FILE)]
        if leftovers:
            raise InputError(str(self.path), f"holds {leftovers[0]} but no {SESSION_FILE}: not a session "
                                             "directory to resume; choose an empty output directory")
        save_robot(robot, self.path / ROBOT_FILE, header="Nominal robot model of this session.")
        save_poses(poses, self.path / POSES_FILE)
        empty = Samples(np.zeros(0, int), np.zeros(0), np.zeros((0, robot.n_joints)), np.zeros((0, 2, 2)))
        _write_durably(self.path / SAMPLES_FILE, format_samples(empty))
        self.set_info(state="running", started=time.strftime("%Y-%m-%dT%H:%M:%S%z"), steps=len(poses), **info)

    def load_for_resume(self) -> tuple[Robot, PoseSequence]:
        robot = load_robot(self.path / ROBOT_FILE)
        poses = load_poses(self.path / POSES_FILE, robot)
        return robot, poses

    def completed(self, robot: Robot, poses: PoseSequence) -> Samples | None:
        """The samples of the completed steps, from the bag (the journal); samples.csv
        is made to agree with them. None when nothing was completed yet."""
        done = None
        if (self.bag_dir / bag.METADATA).exists():
            try:
                done = bag.read_samples(self.bag_dir)
            except InputError as exc:
                if "holds no samples" not in str(exc) and "no topic" not in str(exc):
                    raise
        if done is None:
            empty = Samples(np.zeros(0, int), np.zeros(0), np.zeros((0, robot.n_joints)), np.zeros((0, 2, 2)))
            self._rewrite_samples_if_needed(empty)
            return None
        if len(done) > len(poses):
            raise InputError(str(self.bag_dir), f"{len(done)} samples but the pose list has {len(poses)} steps")
        expected = poses.pose[:len(done)]
        if not np.array_equal(done.pose, expected):
            k = int(np.argmax(done.pose != expected))
            raise InputError(str(self.bag_dir), f"sample {k + 1} is pose {done.pose[k]}, the pose list says "
                                                f"{expected[k]}: the bag does not belong to this pose list")
        self._rewrite_samples_if_needed(done)
        return done

    def _rewrite_samples_if_needed(self, done: Samples) -> None:
        path = self.path / SAMPLES_FILE
        try:
            current = load_samples(path) if path.exists() else None
        except InputError:
            current = None  # torn last line, or only the header: rewritten below
        if current is not None and len(current) == len(done) and np.array_equal(current.pose, done.pose) \
                and np.array_equal(current.stamp, done.stamp):
            return
        _write_durably(path, format_samples(done))

    def append_sample(self, samples: Samples, index: int = 0) -> None:
        """Append one row (row ``index`` of ``samples``) to samples.csv, flushed to disk."""
        line = ",".join(sample_row(samples, index)) + "\n"
        with open(self.path / SAMPLES_FILE, "a") as handle:
            handle.write(line)
            handle.flush()
            os.fsync(handle.fileno())

    def samples(self, robot: Robot) -> Samples:
        return load_samples(self.path / SAMPLES_FILE, robot)


class Progress:
    """Pose k of n and the time left, from the mean time per pose measured in this run."""

    def __init__(self, total: int, done: int, clock=time.monotonic):
        self.total = total
        self.done = done
        self.clock = clock
        self.start = clock()
        self.started_at = done

    def step(self) -> None:
        self.done += 1

    def seconds_left(self) -> float:
        measured = self.done - self.started_at
        if measured <= 0:
            return math.nan
        return (self.clock() - self.start) / measured * (self.total - self.done)

    def line(self) -> str:
        left = self.seconds_left()
        eta = "?" if math.isnan(left) else _duration(left)
        return f"{self.done}/{self.total} poses done, about {eta} left"


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    return f"{seconds // 60} min {seconds % 60:02d} s"
