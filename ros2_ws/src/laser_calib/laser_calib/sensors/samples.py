"""Samples of a point or pose sensor (CSV), one row per measured pose.

    pose,stamp,q1,...,qN,x,y,z[,qw,qx,qy,qz][,extra columns...]

x, y, z: the marker (point sensor) or target origin (pose sensor) in the sensor
frame, m; qw..qz: the target's orientation in the sensor frame (unit
quaternion). All measurement fields of a row empty: not seen at that pose.
pose, stamp, q and extra columns mean what they mean in the spot samples
(conventions.md): rows in measurement order, stamps increasing.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..model import Robot
from ..samples_file import check_joint_range

POINT_COLUMNS = ("x", "y", "z")
QUATERNION_COLUMNS = ("qw", "qx", "qy", "qz")
QUATERNION_TOLERANCE = 1e-3  # |norm - 1| accepted (rounding in files); normalised on use


@dataclass(frozen=True)
class SensorSamples:
    """pose (P,) ids; stamp (P,) s; q (P,N) joint readings, rad; position (P,3)
    in m and quaternion (P,4) (qw, qx, qy, qz) or None for a point sensor, both
    in the sensor frame and NaN where not seen; extra: per-pose covariates (P,)."""

    pose: np.ndarray
    stamp: np.ndarray
    q: np.ndarray
    position: np.ndarray
    quaternion: np.ndarray | None
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.pose)

    @property
    def n_joints(self) -> int:
        return self.q.shape[1]

    @property
    def kind(self) -> str:
        return "point" if self.quaternion is None else "pose"

    @property
    def seen(self) -> np.ndarray:
        """(P,) bool: the sensor saw the target at that pose."""
        return ~np.isnan(self.position).any(axis=1)

    def subset(self, index) -> "SensorSamples":
        """Rows selected by a boolean mask or index array (order preserved)."""
        quaternion = None if self.quaternion is None else self.quaternion[index]
        return SensorSamples(self.pose[index], self.stamp[index], self.q[index], self.position[index], quaternion,
                             {k: v[index] for k, v in self.extra.items()})


def _columns(kind: str) -> tuple[str, ...]:
    return POINT_COLUMNS + (QUATERNION_COLUMNS if kind == "pose" else ())


def parse_sensor_samples(text: str, source: str = "<samples>", robot: Robot | None = None) -> SensorSamples:
    rows = list(csv.reader(io.StringIO(text)))
    while rows and not any(cell.strip() for cell in rows[-1]):
        rows.pop()
    if not rows:
        raise InputError(source, "empty file (expected a header row pose,stamp,q1..qN,x,y,z[,qw,qx,qy,qz])")
    header = [cell.strip() for cell in rows[0]]
    if header[:2] != ["pose", "stamp"]:
        raise InputError(f"{source}: header", f"must start with 'pose,stamp', got {','.join(header[:2])!r}")
    n_q = 0
    while 2 + n_q < len(header) and header[2 + n_q] == f"q{n_q + 1}":
        n_q += 1
    if n_q == 0:
        raise InputError(f"{source}: header", "missing joint columns q1..qN after 'stamp'")
    if tuple(header[2 + n_q:5 + n_q]) != POINT_COLUMNS:
        raise InputError(f"{source}: header", f"expected x,y,z after q{n_q}")
    kind = "pose" if tuple(header[5 + n_q:9 + n_q]) == QUATERNION_COLUMNS else "point"
    measured = _columns(kind)
    if robot is not None and n_q != robot.n_joints:
        raise InputError(f"{source}: header", f"{n_q} joint columns but robot '{robot.name}' has {robot.n_joints}")
    if len(set(header)) != len(header):
        raise InputError(f"{source}: header", "duplicate column names")
    extra_names = header[2 + n_q + len(measured):]

    n = len(rows) - 1
    if n == 0:
        raise InputError(source, "no sample rows after the header")
    pose = np.empty(n, dtype=int)
    values = np.full((n, len(header) - 1), np.nan)
    for r, row in enumerate(rows[1:]):
        line = r + 2
        if len(row) != len(header):
            raise InputError(f"{source}: line {line}", f"{len(row)} fields, header has {len(header)}")
        try:
            pose[r] = int(row[0])
        except ValueError:
            raise InputError(f"{source}: line {line}, field pose", f"not an integer: {row[0]!r}") from None
        for c, cell in enumerate(row[1:], start=1):
            cell = cell.strip()
            if cell == "" and header[c] in measured:
                continue  # not seen; checked per row below
            try:
                value = float(cell)
            except ValueError:
                what = "empty" if cell == "" else f"not a number: {cell!r}"
                raise InputError(f"{source}: line {line}, field {header[c]}", what) from None
            if not math.isfinite(value):
                raise InputError(f"{source}: line {line}, field {header[c]}", f"not finite ({cell})")
            values[r, c - 1] = value
        block = values[r, 1 + n_q:1 + n_q + len(measured)]
        if np.isnan(block).any() and not np.isnan(block).all():
            raise InputError(f"{source}: line {line}", f"only some of {','.join(measured)} are given")
        if kind == "pose" and not np.isnan(block).any() and abs(np.linalg.norm(block[3:]) - 1) > QUATERNION_TOLERANCE:
            raise InputError(f"{source}: line {line}, fields qw..qz",
                             f"quaternion norm {np.linalg.norm(block[3:]):.6g} is not 1")
        if r and values[r, 0] <= values[r - 1, 0]:
            raise InputError(f"{source}: line {line}, field stamp",
                             f"not increasing ({values[r, 0]} after {values[r - 1, 0]})")
    q = values[:, 1:1 + n_q]
    if robot is not None:
        check_joint_range(q, robot, source, pose)
    position = values[:, 1 + n_q:4 + n_q]
    quaternion = values[:, 4 + n_q:8 + n_q] if kind == "pose" else None
    extra = {name: values[:, 1 + n_q + len(measured) + i] for i, name in enumerate(extra_names)}
    return SensorSamples(pose, values[:, 0], q, position, quaternion, extra)


def load_sensor_samples(path: str | Path, robot: Robot | None = None) -> SensorSamples:
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise InputError(str(path), f"cannot read ({exc.strerror})") from None
    return parse_sensor_samples(text, str(path), robot)


def format_sensor_samples(samples: SensorSamples) -> str:
    """CSV text; floats at full precision (repr) so files round-trip exactly."""
    header = (["pose", "stamp"] + [f"q{i + 1}" for i in range(samples.n_joints)] + list(_columns(samples.kind))
              + list(samples.extra))
    measured = samples.position if samples.quaternion is None else np.hstack([samples.position, samples.quaternion])
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    for r in range(len(samples)):
        writer.writerow([str(int(samples.pose[r])), repr(float(samples.stamp[r]))]
                        + [repr(float(v)) for v in samples.q[r]]
                        + ["" if math.isnan(v) else repr(float(v)) for v in measured[r]]
                        + [repr(float(samples.extra[k][r])) for k in samples.extra])
    return out.getvalue()


def save_sensor_samples(samples: SensorSamples, path: str | Path) -> None:
    Path(path).write_text(format_sensor_samples(samples))
