"""The one samples type of every sensor, and the spot samples CSV (conventions.md).

A spot, a point and a pose are measurement kinds of one Samples type: the
readings (pose ids, stamps, joints, covariates) are common, the measured block
is the kind's. The point and pose CSV is io/sensor_samples.py
(conventions-extended.md); both files keep their own format.
"""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.io.read import (csv_rows, integer_column, length_units, looks_numeric, number_column, parse_int,
                              parse_number, plain_table, read_text)
from laser_calib.io.spot_columns import check_spot_columns
from laser_calib.model.robot import LIMIT_TRAVEL, Robot

SPOT_COLUMNS = ("l1_y", "l1_z", "l2_y", "l2_z")
HEADER = "pose,stamp,q1..qN,l1_y,l1_z,l2_y,l2_z"
MAX_DISTANCE = 100.0  # m: a median target distance beyond it is a file in millimetres (a single outlier is not)


@dataclass(frozen=True)
class Samples:
    """Measured poses, one row per pose in measurement order, of one kind.

    pose (P,) int ids (repeated visits of a pose share its id); stamp (P,) s;
    q (P,N) joint readings in rad; extra: per-pose covariate columns, each (P,);
    labels: per-pose text columns (an operator, a fixture, a batch), each (P,) str
    ('' where empty), carried like the covariates and tested as categories.
    The measured block, NaN where not seen:
    - spot: spots (P,2,2) [pose, laser, (y,z)] in m on the screen;
    - point: position (P,3) of the marker in the sensor frame, m;
    - pose: position (P,3) and quaternion (P,4) (qw, qx, qy, qz) of the target
      in the sensor frame.
    warnings: what reading the file found that is no error but must be said (one line each).
    """

    pose: np.ndarray
    stamp: np.ndarray
    q: np.ndarray
    spots: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    position: np.ndarray | None = None
    quaternion: np.ndarray | None = None
    warnings: tuple[str, ...] = ()
    labels: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        # The fields of the other kinds stay None, so a mixed-up call fails here, not in a model.
        if (self.spots is None) == (self.position is None):
            raise ValueError("samples hold either spots or positions (point, pose), exactly one of them")
        if self.quaternion is not None and self.position is None:
            raise ValueError("a quaternion needs a position (pose samples)")
        if not isinstance(self.extra, dict):
            raise ValueError(f"extra must be a dict of covariate columns, got {type(self.extra).__name__}")
        if not isinstance(self.labels, dict):
            raise ValueError(f"labels must be a dict of text columns, got {type(self.labels).__name__}")
        width = {"spots": (2, 2), "position": (3,), "quaternion": (4,)}
        for name, shape in width.items():
            value = getattr(self, name)
            if value is not None and value.shape != (len(self.pose),) + shape:
                raise ValueError(f"{name} of {len(self.pose)} poses must be {(len(self.pose),) + shape}, "
                                 f"got {value.shape}")

    def __len__(self) -> int:
        return len(self.pose)

    @property
    def kind(self) -> str:
        """The measurement kind: 'spot', 'point' or 'pose'."""
        if self.spots is not None:
            return "spot"
        return "point" if self.quaternion is None else "pose"

    @property
    def n_joints(self) -> int:
        return self.q.shape[1]

    @property
    def seen(self) -> np.ndarray:
        """spot: (P,2) bool, laser j was seen at pose p; point, pose: (P,) bool,
        the sensor saw the target at pose p."""
        if self.spots is not None:
            return ~np.isnan(self.spots).any(axis=2)
        return ~np.isnan(self.position).any(axis=1)

    @property
    def measured(self) -> np.ndarray:
        """(P,K) the measured block of each row: spot l1_y, l1_z, l2_y, l2_z; point x, y, z;
        pose x, y, z, qw, qx, qy, qz (the CSV's columns); NaN where not seen."""
        if self.spots is not None:
            return self.spots.reshape(len(self), -1)
        return self.position if self.quaternion is None else np.hstack([self.position, self.quaternion])

    def without(self, units: np.ndarray) -> "Samples":
        """The same rows with the measured units (P,C) marked not seen (spots: (P,2);
        point, pose: (P,1)), as a fit leaves out what it refused."""
        if self.spots is not None:
            return replace(self, spots=np.where(units[..., None], np.nan, self.spots))
        poses = units.any(axis=1)[:, None]
        return replace(self, position=np.where(poses, np.nan, self.position),
                       quaternion=None if self.quaternion is None else np.where(poses, np.nan, self.quaternion))

    def subset(self, index) -> "Samples":
        """Rows selected by a boolean mask or index array (order preserved)."""
        rows = {f.name: getattr(self, f.name)[index] for f in fields(self)
                if isinstance(getattr(self, f.name), np.ndarray)}
        return replace(self, **rows, extra={k: v[index] for k, v in self.extra.items()},
                       labels={k: v[index] for k, v in self.labels.items()})


def reading_warnings(samples: Samples, test: Samples | None = None) -> list[str]:
    """What reading the calibration and test sets found (Samples.warnings: a bag's damaged segments
    skipped, joints the robot does not have), each once: a segment lost to both topics is one line."""
    return list(dict.fromkeys((*samples.warnings, *(test.warnings if test is not None else ()))))


def without_unmeasured_test(samples: Samples, test: Samples | None) -> tuple[Samples, Samples | None]:
    """A session's own test set (a bag's, the estimator's accumulated one) that measured nothing (the
    camera covered after the calibration poses) gives no held-out figure: dropped, and said among
    the calibration set's warnings. A test set given for the purpose (--test, a request's) is
    refused instead (cli.arguments.require_measured)."""
    if test is None or test.seen.any():
        return samples, test
    said = f"test: no {samples.kind} is measured in the {len(test)} test poses: there is no held-out figure"
    return replace(samples, warnings=(*samples.warnings, said)), None


def split_labels(header: list[str], rows: list[list[str]], first: int
                 ) -> tuple[list[str], list[list[str]], dict[str, np.ndarray]]:
    """The text columns among the columns from index ``first`` on (the covariates): a
    column none of whose fields is a number (an operator's name, a fixture's tag, notes
    never filled in) is a label column (P,) str; the header and rows without them. A
    column with numbers and text stays a covariate, whose first text field parse_table
    then names (a temperature logged as 'n/a' is a typo, not a category). Rows of another
    length are left as they are for parse_table to name."""
    if any(len(row) != len(header) for row in rows):
        return header, rows, {}
    text = [c for c in range(first, len(header)) if not any(looks_numeric(row[c]) for row in rows)]
    if not text:
        return header, rows, {}
    keep = [c for c in range(len(header)) if c not in text]
    labels = {header[c]: np.array([row[c].strip() for row in rows], dtype=str) for c in text}
    return [header[c] for c in keep], [[row[c] for c in keep] for row in rows], labels


def _header_error(source: str, problem: str) -> InputError:
    return InputError(f"{source}: header", problem)


def read_table(text: str, source: str, expected_header: str) -> tuple[list[str], list[list[str]], int]:
    """Header, data rows and joint count N of a 'pose,stamp,q1..qN,...' CSV."""
    rows = csv_rows(text, source)
    while rows and not any(cell.strip() for cell in rows[-1]):
        rows.pop()
    if not rows:
        raise InputError(source, f"empty file (expected a header row {expected_header})")
    header = [cell.strip() for cell in rows[0]]
    if len(header) > 1 and not header[-1] and all(len(row) == len(header) and not row[-1].strip() for row in rows):
        # a comma at the end of every line (a spreadsheet's export): no column
        header, rows = header[:-1], [row[:-1] for row in rows]
    if header[:2] != ["pose", "stamp"]:
        raise _header_error(source, f"must start with 'pose,stamp', got {','.join(header[:2])!r}")
    n_q = 0
    while 2 + n_q < len(header) and header[2 + n_q] == f"q{n_q + 1}":
        n_q += 1
    joints = [name for name in header[2:] if re.fullmatch(r"q\d+", name)]
    if n_q == 0 or joints != [f"q{i + 1}" for i in range(len(joints))]:  # q7,q6 said "expected l1_y,... after q5"
        found = f" (found {', '.join(joints)} in that order)" if joints else ""
        raise _header_error(source, f"missing joint columns q1..qN in order after 'stamp'{found}")
    if len(set(header)) != len(header):
        raise _header_error(source, "duplicate column names")
    return header, rows[1:], n_q


def parse_table(header: list[str], rows: list[list[str]], source: str,
                may_be_empty: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Pose ids (P,) and the other columns as numbers (P, C-1), NaN only where a
    column of ``may_be_empty`` is empty. One line for the first bad field; stamps
    (column 1) must increase."""
    if not rows:
        raise InputError(source, "no sample rows after the header")
    table = _columns(header, rows, may_be_empty)
    if table is not None:
        return table
    # some field is wrong: field by field, for the one line that names the first
    pose = np.empty(len(rows), dtype=int)
    values = np.full((len(rows), len(header) - 1), np.nan)
    for r, row in enumerate(rows):
        line = r + 2
        if len(row) != len(header):
            raise InputError(f"{source}: line {line}", f"{len(row)} fields, header has {len(header)}")
        pose[r] = parse_int(row[0], f"{source}: line {line}, field pose")
        for c, cell in enumerate(row[1:], start=1):
            name = header[c]
            cell = cell.strip()
            if cell == "":
                if name in may_be_empty:
                    continue  # not measured at this pose
                raise InputError(f"{source}: line {line}, field {name}", "empty")
            values[r, c - 1] = parse_number(cell, f"{source}: line {line}, field {name}")
        if r and values[r, 0] <= values[r - 1, 0]:
            if [cell.strip() for cell in row] == [cell.strip() for cell in rows[r - 1]]:  # a logger's line twice
                raise InputError(f"{source}: line {line}", f"a copy of line {line - 1}, every field equal (stamps "
                                                           "increase): delete one of them")
            raise InputError(f"{source}: line {line}, field stamp",
                             f"not increasing ({values[r, 0]} after {values[r - 1, 0]})")
    return pose, values


def _columns(header: list[str], rows: list[list[str]],
             may_be_empty: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray] | None:
    """parse_table's result column by column at C speed, or None when any check
    fails (the caller then finds and names the first bad field)."""
    if any(len(row) != len(header) for row in rows):
        return None
    columns = list(zip(*rows))
    pose = integer_column(columns[0])
    values = [number_column(cells, name in may_be_empty) for name, cells in zip(header[1:], columns[1:])]
    if pose is None or any(v is None for v in values) or not np.all(np.diff(values[0]) > 0):
        return None
    return pose, np.stack(values, axis=1)


def check_all_or_none(block: np.ndarray, source: str, where: str, problem: str) -> None:
    """Each row of block (P,K) is either all measured or all empty; else one line
    '<source>: line L<where>: <problem>'."""
    partial = np.isnan(block).any(axis=1) & ~np.isnan(block).all(axis=1)
    if partial.any():
        raise InputError(f"{source}: line {np.argmax(partial) + 2}{where}", problem)


def check_lasers(robot: Robot, where: str) -> None:
    """Refuse (InputError at ``where``) a robot without lasers for spot samples: its file may leave
    them out (an arm measured by another sensor), and the spots then have no model."""
    if not robot.lasers:
        raise InputError(where, f"spot samples need the robot's lasers, but robot '{robot.name}' has no "
                                "'lasers:' (add the 'slm:' and the two lasers' gamma, beta to its file)")


def parse_samples(text: str, source: str = "<samples>", robot: Robot | None = None) -> Samples:
    plain = plain_table(text)
    if plain is not None and [cell.strip() for cell in plain[0].split(",")][:2] != ["pose", "stamp"]:
        plain = None  # the header is wrong: read_table names it as for any file
    header, rows, n_q = read_table(text if plain is None else plain[0], source, HEADER)
    spot_cols = tuple(header[2 + n_q:6 + n_q])
    if spot_cols != SPOT_COLUMNS:
        missing = [c for c in SPOT_COLUMNS if c not in header]
        what = f"missing column {missing[0]}" if missing else f"expected {','.join(SPOT_COLUMNS)} after q{n_q}"
        raise _header_error(source, what)
    check_joint_count(n_q, robot, source)
    if robot is not None:
        check_lasers(robot, source)
    labels: dict[str, np.ndarray] = {}
    if plain is not None and plain[1].shape[1] == len(header) and np.all(np.diff(plain[1][:, 1]) > 0):
        pose, values = plain[1][:, 0].astype(int), plain[1][:, 1:]
    else:
        if plain is not None:  # the header line alone was read: the whole file, field by field
            header, rows, n_q = read_table(text, source, HEADER)
        header, rows, labels = split_labels(header, rows, 6 + n_q)
        pose, values = parse_table(header, rows, source, SPOT_COLUMNS)
    n = len(pose)
    spots = values[:, 1 + n_q:5 + n_q].reshape(n, 2, 2)
    for j in range(2):
        check_all_or_none(spots[:, j], source, f", laser {j + 1}",
                          f"only one of the spot coordinates l{j + 1}_y, l{j + 1}_z is given")
    q = values[:, 1:1 + n_q]
    if robot is not None:
        check_joint_range(q, robot, source, pose)
        check_spot_units(spots, robot, source)
        check_spot_columns(robot, q, spots, source)
    extra = {name: values[:, 5 + n_q + i] for i, name in enumerate(header[6 + n_q:])}
    check_extra_columns(list(extra) + list(labels), n_q, robot, source)
    return Samples(pose, values[:, 0], q, spots, extra, labels=labels)


def check_extra_columns(names: list[str], n_q: int, robot: Robot | None, source: str) -> None:
    """One line for a column after the measured ones that is named like measured data: the
    covariates there (temperature, ...) are free names, but q5 after a 4-joint arm's spots is a
    bigger arm's log and l3_y a third laser's spot, which would otherwise be taken as covariates;
    move2, step2 and torque2 are the diagnosis's own inputs, which a covariate would be taken for."""
    for name in names:
        if not name:
            raise _header_error(source, "a column without a name after the measured columns (a covariate needs one)")
        if re.fullmatch(r"q\d+", name):
            joints = f"robot '{robot.name}' has {robot.n_joints} joints" if robot is not None else f"q1..q{n_q} come first"
            raise _header_error(source, f"column {name} after the measured columns: joint readings are q1..q{n_q}, "
                                        f"right after stamp ({joints})")
        if re.fullmatch(r"l\d+_[yz]", name):
            raise _header_error(source, f"column {name}: the laser module has two lasers, whose spots are "
                                        f"{','.join(SPOT_COLUMNS)}")
        if re.fullmatch(r"(move|step|torque)\d+", name):
            # the diagnosis names its own inputs so: a covariate of that name would be taken for one of them
            raise _header_error(source, f"column {name}: the diagnosis's name of a joint's last move direction "
                                        "(move), size (step) or gravity torque (torque); name the covariate otherwise")


def check_distance_units(position: np.ndarray, where: str) -> None:
    """One line when positions (P,3) are in millimetres (or centimetres): their median distance from the sensor."""
    distance = np.linalg.norm(position, axis=1)
    median = np.nanmedian(distance) if np.isfinite(distance).any() else 0.0
    if median > MAX_DISTANCE:
        raise InputError(where, f"median distance {median:.4g} m from the sensor: positions are in "
                                f"metres (these look like {length_units(median, MAX_DISTANCE)})")


def check_spot_units(spots: np.ndarray, robot: Robot, where: str) -> None:
    """One line when every measured spot (P,2,2) lies outside the robot's screen: spots in
    millimetres (or centimetres). A few spots outside are outliers, which the estimator refuses per pose."""
    half = np.array([robot.screen.half_y, robot.screen.half_z])
    seen = ~np.isnan(spots).any(axis=2)
    outside = seen & (np.abs(np.nan_to_num(spots)) > half).any(axis=2)
    if outside.any() and outside.sum() == seen.sum():
        units = length_units(float(np.median(np.abs(spots[seen]))), float(half.max()))
        raise InputError(where, f"every spot lies outside the screen (half sizes {half[0]:g}, {half[1]:g} m): spot "
                                f"coordinates are in metres (these look like {units})")


def check_joint_count(n_q: int, robot: Robot | None, source: str) -> None:
    """One line when the file's q1..qN do not match the robot's readings (named for a URDF robot)."""
    if robot is not None and n_q != robot.n_joints:
        names = (f": q1{f'..q{robot.n_joints} are' if robot.n_joints > 1 else ' is'} {', '.join(robot.joint_names)}"
                 if robot.chain is not None else "")
        raise _header_error(source, f"{n_q} joint column{'s' * (n_q != 1)} but robot '{robot.name}' has "
                                    f"{robot.n_joints} joint{'s' * (robot.n_joints != 1)}{names}")


# A measured reading may lie a little beyond its joint's limit: the arm settled against the stop,
# the encoder's last count, or a limit written rounded in the robot file. The check is there to
# catch readings that are not this robot's (degrees, another arm's file), which miss the range by
# far; refusing a whole session for a reading 0.1 deg past a limit would lose what was measured.
READING_SLACK = 0.01  # fraction of the joint's travel


def check_joint_range(q: np.ndarray, robot: Robot, source: str, pose: np.ndarray | None = None,
                      measured: bool = True) -> None:
    """One line for the first joint value outside [min, max] of its joint: beyond it by more
    than READING_SLACK of the joint's travel for measured readings, at all for commanded poses
    (measured=False: a pose list the arm is sent to)."""
    travel = robot.q_max - robot.q_min
    slack = (READING_SLACK * travel if measured else 0.0) + 1e-9
    outside = (q < robot.q_min - slack) | (q > robot.q_max + slack)
    if outside.any():
        r, i = np.argwhere(outside)[0]
        label = f"pose {pose[r]}" if pose is not None else f"row {r}"
        # degrees: beyond a turn, or mostly outside and all inside read as degrees (+-20 deg: 12 deg is under a turn)
        inside = np.abs(np.radians(q[:, i]) - (robot.q_min[i] + robot.q_max[i]) / 2) <= (travel / 2 + slack)[i]
        degrees = abs(q[r, i]) > 2 * math.pi + 0.5 or outside[:, i].sum() > max(1, len(q) / 2) and inside.all()
        hint = ((f" (a prismatic joint's readings are in metres; this looks like {length_units(q[r, i], LIMIT_TRAVEL)})"
                 if abs(q[r, i]) > LIMIT_TRAVEL else "") if robot.prismatic[i]
                else " (readings are in radians; this looks like degrees)" if degrees else "")
        joint = f" ({robot.joint_names[i]})" if robot.chain is not None else ""
        beyond = f" by more than {READING_SLACK * 100:g} % of its travel" if measured else ""
        unit = "m" if robot.prismatic[i] else "rad"
        raise InputError(f"{source}: {label}, field q{i + 1}{joint}", f"{q[r, i]:.6g} {unit} outside the joint "
                         f"range [{robot.q_min[i]:.6g}, {robot.q_max[i]:.6g}]" + beyond + hint)


def load_samples(path: str | Path, robot: Robot | None = None) -> Samples:
    return parse_samples(read_text(path), str(Path(path)), robot)


def format_samples(samples: Samples) -> str:
    if samples.kind != "spot":
        raise ValueError(f"the spot samples CSV holds spots, not {samples.kind} samples (io/sensor_samples.py)")
    n_q = samples.n_joints
    header = (["pose", "stamp"] + [f"q{i + 1}" for i in range(n_q)] + list(SPOT_COLUMNS) + list(samples.extra)
              + list(samples.labels))
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    for r in range(len(samples)):
        writer.writerow(sample_row(samples, r))
    return out.getvalue()


def sample_row(samples: Samples, r: int) -> list[str]:
    """One CSV row; full float precision (repr) so files round-trip exactly."""
    spots = [("" if math.isnan(v) else repr(float(v))) for v in samples.spots[r].ravel()]
    return ([str(int(samples.pose[r])), repr(float(samples.stamp[r]))]
            + [repr(float(v)) for v in samples.q[r]] + spots + covariate_cells(samples, r))


def covariate_cells(samples: Samples, r: int) -> list[str]:
    """Row r's covariate columns (full precision) and then its text columns, as the header lists them."""
    return ([repr(float(values[r])) for values in samples.extra.values()]
            + [str(text[r]) for text in samples.labels.values()])


def save_samples(samples: Samples, path: str | Path) -> None:
    Path(path).write_text(format_samples(samples))
