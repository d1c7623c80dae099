"""Point and pose samples CSV (conventions-extended.md), one row per measured pose.

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
from pathlib import Path

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.io.figaroh import is_figaroh, parse_figaroh
from laser_calib.io.quaternion_order import check_quaternion_order
from laser_calib.io.read import read_text
from laser_calib.model.robot import Robot
from laser_calib.io.samples import (Samples, check_all_or_none, check_distance_units, check_extra_columns,
                                    check_joint_count, check_joint_range, covariate_cells, parse_table, read_table,
                                    split_labels)

POINT_COLUMNS = ("x", "y", "z")
QUATERNION_COLUMNS = ("qw", "qx", "qy", "qz")
QUATERNION_TOLERANCE = 1e-3  # |norm - 1| accepted (rounding in files); normalised on use


# The one samples type (io/samples.py) under the name point and pose callers use.
SensorSamples = Samples


def _columns(kind: str) -> tuple[str, ...]:
    return POINT_COLUMNS + (QUATERNION_COLUMNS if kind == "pose" else ())


def parse_sensor_samples(text: str, source: str = "<samples>", robot: Robot | None = None) -> Samples:
    header, rows, n_q = read_table(text, source, "pose,stamp,q1..qN,x,y,z[,qw,qx,qy,qz]")
    if tuple(header[2 + n_q:5 + n_q]) != POINT_COLUMNS:
        raise InputError(f"{source}: header", f"expected x,y,z after q{n_q}")
    kind = "pose" if tuple(header[5 + n_q:9 + n_q]) == QUATERNION_COLUMNS else "point"
    partial = [c for c in QUATERNION_COLUMNS if c in header]
    if kind == "point" and partial:
        missing = [c for c in QUATERNION_COLUMNS if c not in header]
        what = f"missing column {missing[0]}" if missing else f"expected {','.join(QUATERNION_COLUMNS)} after z"
        raise InputError(f"{source}: header", f"{what} (an orientation needs all of qw,qx,qy,qz)")
    measured = _columns(kind)
    check_joint_count(n_q, robot, source)
    header, rows, labels = split_labels(header, rows, 2 + n_q + len(measured))
    pose, values = parse_table(header, rows, source, measured)
    block = values[:, 1 + n_q:1 + n_q + len(measured)]
    check_all_or_none(block, source, "", f"only some of {','.join(measured)} are given")
    if kind == "pose":
        norm = np.linalg.norm(block[:, 3:], axis=1)
        bad = np.isfinite(norm) & (np.abs(norm - 1) > QUATERNION_TOLERANCE)
        if bad.any():
            r = int(np.argmax(bad))
            raise InputError(f"{source}: line {r + 2}, fields qw..qz", f"quaternion norm {norm[r]:.6g} is not 1")
    q = values[:, 1:1 + n_q]
    if robot is not None:
        check_joint_range(q, robot, source, pose)
    position = values[:, 1 + n_q:4 + n_q]
    check_distance_units(position, f"{source}: fields x,y,z")
    quaternion = values[:, 4 + n_q:8 + n_q] if kind == "pose" else None
    extra = {name: values[:, 1 + n_q + len(measured) + i]
             for i, name in enumerate(header[2 + n_q + len(measured):])}
    check_extra_columns(list(extra) + list(labels), n_q, robot, source)
    return Samples(pose, values[:, 0], q, extra=extra, position=position, quaternion=quaternion, labels=labels)


def load_sensor_samples(path: str | Path, robot: Robot | None = None) -> Samples:
    """Our samples CSV, or FIGAROH's calibration CSV (header x1,y1,z1,...: io/figaroh.py)."""
    text, source = read_text(path), str(Path(path))
    samples = parse_figaroh(text, source, robot) if is_figaroh(text) else parse_sensor_samples(text, source, robot)
    if robot is not None:
        check_tips(samples, robot, source)
        check_quaternion_order(samples, robot, source)
    return samples


def check_tips(samples: Samples, robot: Robot, source: str) -> None:
    """The ``tip`` column (which of the robot's tips a row measures, 0, 1, ...; required for a
    tree of several tips) as one line naming the file: the sensor model checks it too, but
    knows no file."""
    n_tips = 1 if robot.chain is None else len(robot.chain.tips)
    if "tip" not in samples.extra:
        if n_tips > 1:
            raise InputError(f"{source}: header", f"no column 'tip' (0..{n_tips - 1}): the robot has {n_tips} tips, "
                                                  "and each row must say which one it measures")
        return
    tips = samples.extra["tip"]
    bad = np.flatnonzero(~np.isin(tips, np.arange(n_tips)))
    if len(bad):
        raise InputError(f"{source}: pose {int(samples.pose[bad[0]])}, field tip",
                         f"{tips[bad[0]]:g} is not one of 0..{n_tips - 1} (the tips in the order of --tip)")


def format_sensor_samples(samples: Samples) -> str:
    """CSV text; floats at full precision (repr) so files round-trip exactly."""
    if samples.kind == "spot":
        raise ValueError("the sensor samples CSV holds point or pose samples, not spots (io/samples.py)")
    header = (["pose", "stamp"] + [f"q{i + 1}" for i in range(samples.n_joints)] + list(_columns(samples.kind))
              + list(samples.extra) + list(samples.labels))
    measured = samples.measured
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    for r in range(len(samples)):
        writer.writerow([str(int(samples.pose[r])), repr(float(samples.stamp[r]))]
                        + [repr(float(v)) for v in samples.q[r]]
                        + ["" if math.isnan(v) else repr(float(v)) for v in measured[r]]
                        + covariate_cells(samples, r))
    return out.getvalue()


def save_sensor_samples(samples: Samples, path: str | Path) -> None:
    Path(path).write_text(format_sensor_samples(samples))
