"""Pose lists (ROS-free): read (YAML or CSV), generate, add test poses, write.

One writer, format_poses, for every pose list the project writes: `laser-calib
plan`'s output and a session's poses.csv. Its CSV (pose,q1..qN[,test]) is what
load_poses reads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.io.read import csv_rows, finite_number, load_yaml, parse_int, parse_number, read_text
from laser_calib.io.samples import check_joint_range
from laser_calib.model.robot import Robot
from laser_calib.session.durable import write_durably
from laser_calib.sim.simulation import sample_poses

TEST_COLUMN = "test"


@dataclass(frozen=True)
class PoseSequence:
    """The steps of a session: pose ids (P,) (repeats share an id), joint goals (P,N) and
    test (P,) bool, True for a test pose (measured, never fitted: the held-out set)."""

    pose: np.ndarray
    q: np.ndarray
    test: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.test is None:
            object.__setattr__(self, "test", np.zeros(len(self.pose), dtype=bool))

    def __len__(self) -> int:
        return len(self.pose)


def load_poses(path: str | Path, robot: Robot) -> PoseSequence:
    """Pose list from YAML (``poses:`` list of [q1..qN] or {pose: id, q: [...]}) or
    CSV (header with q1..qN, optionally pose and test (0/1); other columns ignored)."""
    path = Path(path)
    text = read_text(path)
    test: list[bool] = []
    if path.suffix.lower() in (".yaml", ".yml"):
        ids, rows = _poses_from_yaml(text, str(path), robot)
    else:
        ids, rows, test = _poses_from_csv(text, str(path), robot)
    if not rows:
        raise InputError(str(path), "no poses")
    q = np.array(rows, dtype=float)
    check_joint_range(q, robot, str(path), np.array(ids), measured=False)
    _check_repeats(np.array(ids, dtype=int), q, str(path))
    return PoseSequence(np.array(ids, dtype=int), q, np.array(test, dtype=bool) if test else None)


def _check_repeats(ids: np.ndarray, q: np.ndarray, source: str) -> None:
    """A pose id given twice is a repeat of that pose (its spread measures the noise), so its rows
    must ask for the same joint positions: others were measured, and only the estimate's check of
    repeated readings said so afterwards (a pose list's ids renumbered by hand)."""
    values, counts = np.unique(ids, return_counts=True)
    for pose in values[counts > 1]:
        rows = q[ids == pose]
        spread = np.ptp(rows, axis=0)
        if spread.max() > 1e-9:
            joint = int(np.argmax(spread))
            raise InputError(f"{source}: pose {pose}", f"given {len(rows)} times with other joint positions (q{joint + 1} "
                             f"{spread[joint]:.3g} apart): a pose id names one pose, its rows are repeats of it")


def _check_row(values: Sequence, where: str, robot: Robot) -> list[float]:
    if not isinstance(values, (list, tuple)) or len(values) != robot.n_joints:
        count = len(values) if isinstance(values, (list, tuple)) else "not a list of"
        raise InputError(where, f"{count} joint positions, robot '{robot.name}' has {robot.n_joints}")
    return [finite_number(value, f"{where}, q{i + 1}") for i, value in enumerate(values)]


def _poses_from_yaml(text: str, source: str, robot: Robot) -> tuple[list[int], list[list[float]]]:
    data = load_yaml(text, source)
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


def _poses_from_csv(text: str, source: str, robot: Robot) -> tuple[list[int], list[list[float]], list[bool]]:
    lines = [row for row in csv_rows(text, source) if any(cell.strip() for cell in row)]
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
    test_col = header.index(TEST_COLUMN) if TEST_COLUMN in header else None
    ids, rows, test = [], [], []
    for r, row in enumerate(lines[1:]):
        line = r + 2
        if len(row) != len(header):
            raise InputError(f"{source}: line {line}", f"{len(row)} fields, header has {len(header)}")
        if pose_col is None:
            ids.append(r)
        else:
            ids.append(parse_int(row[pose_col], f"{source}: line {line}, field pose"))
        rows.append([parse_number(row[i], f"{source}: line {line}, field {name}") for name, i in zip(columns, index)])
        if test_col is not None:
            if row[test_col].strip() not in ("0", "1"):
                raise InputError(f"{source}: line {line}, field {TEST_COLUMN}",
                                 f"expected 0 or 1, got {row[test_col]!r}")
            test.append(row[test_col].strip() == "1")
    return ids, rows, test


def _sample(robot: Robot, count: int, rng: np.random.Generator, span: str, margin: float) -> np.ndarray:
    if not (math.isfinite(margin) and margin >= 0):  # below 0: spots planned off the screen, then unseen
        raise InputError("margin", f"must be >= 0 m, got {margin}")
    try:
        return sample_poses([robot], count, rng, span, margin)
    except RuntimeError as exc:
        raise InputError(f"robot '{robot.name}'", str(exc)) from None


def _check_seed(seed: int) -> None:
    if seed < 0:  # numpy's generators take none: a ValueError deep inside them
        raise InputError("seed", f"must be >= 0, got {seed}")


def _check_test_poses(count: int) -> None:
    if count < 0:
        raise InputError("test_poses", f"must be >= 0, got {count}")


def check_plan(count: int | None, span: str, seed: int, repeats: int = 0, test_poses: int = 0) -> None:
    """The pose plan's arguments as generate_poses and with_test_poses take them (count None:
    a pose file's plan, nothing generated), refused before a session starts (its folder, its nodes)."""
    if count is not None and count < 1:
        raise InputError("poses", f"need at least one pose, got {count}")
    if count is not None and span not in ("small", "whole"):
        raise InputError("span", f"expected 'small' or 'whole', got {span!r}")
    if repeats < 0:
        raise InputError("repeats", f"must be >= 0, got {repeats}")
    _check_test_poses(test_poses)
    _check_seed(seed)


def generate_poses(robot: Robot, count: int, span: str, seed: int, repeats: int = 0,
                   margin: float = 0.02) -> PoseSequence:
    """``count`` poses whose two beams hit the screen (laser_calib.sim.simulation.sample_poses,
    nominal model), span 'small' (+-10 deg) or 'whole' (workspace); then ``repeats``
    of them, evenly spread over the list, measured again at the end with their ids."""
    check_plan(count, span, seed, repeats)
    q = _sample(robot, count, np.random.default_rng(seed), span, margin)
    ids = np.arange(count)
    if repeats > 0:
        again = np.unique(np.linspace(0, count - 1, min(repeats, count)).round().astype(int))
        ids = np.concatenate([ids, again])
        q = np.vstack([q, q[again]])
    return PoseSequence(ids, q)


def with_test_poses(poses: PoseSequence, robot: Robot, count: int, seed: int, margin: float = 0.02) -> PoseSequence:
    """``poses`` followed by ``count`` test poses over the whole workspace, drawn from their
    own random stream (seed, 1) so that adding them leaves the fit poses as they were; ids
    continue after the largest id of ``poses``."""
    _check_test_poses(count)
    if count == 0:
        return poses
    _check_seed(seed)
    q = _sample(robot, count, np.random.default_rng([seed, 1]), "whole", margin)
    ids = int(poses.pose.max()) + 1 + np.arange(count)
    return PoseSequence(np.concatenate([poses.pose, ids]), np.vstack([poses.q, q]),
                        np.concatenate([poses.test, np.ones(count, dtype=bool)]))


def format_poses(q: np.ndarray, pose: np.ndarray | None = None, test: np.ndarray | None = None) -> str:
    """CSV text pose,q1..qN[,test] (rad, full precision), one row per pose in measuring
    order; q (P,N), pose (P,) ids (default 0..P-1), test (P,) bool (column only when given)."""
    pose = np.arange(len(q)) if pose is None else pose
    header = ["pose"] + [f"q{i + 1}" for i in range(q.shape[1])] + ([TEST_COLUMN] if test is not None else [])
    lines = [",".join(header)]
    for r in range(len(q)):
        cells = [str(int(pose[r]))] + [repr(float(v)) for v in q[r]]
        lines.append(",".join(cells + ([str(int(test[r]))] if test is not None else [])))
    return "\n".join(lines) + "\n"


def save_poses(poses: PoseSequence, path: Path) -> None:
    write_durably(path, format_poses(poses.q, poses.pose, poses.test if poses.test.any() else None))
