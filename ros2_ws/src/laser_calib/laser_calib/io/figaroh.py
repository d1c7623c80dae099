"""FIGAROH's calibration CSV (figaroh-examples), read as it is: no converter.

    x1,y1,z1[,phix1,phiy1,phiz1][,x2,y2,z2...],<joint name>,<joint name>,...

One row per pose. x{k}, y{k}, z{k}: marker k's position in the measurement
frame (m); phix{k}, phiy{k}, phiz{k}: its orientation as roll-pitch-yaw,
R = Rz(phiz) Ry(phiy) Rx(phix) (rad), as FIGAROH composes it. Marker k is
measured on the robot's tip k (``--tip``, in order). The joint columns are
matched to the robot's readings by their URDF names; the chain does not model
the others: one warning names those whose readings move (a joint beyond the
tip, or one the URDF marks fixed), a still one (a held gripper) goes unsaid.
Poses are numbered by row; with K markers a row gives K samples (pose ids
K r + k, a ``tip`` column), and the row number is their stamp: the file holds
no time (ROW_ORDER_AS_TIME). A row whose marker fields are empty did not see
that marker.
"""

from __future__ import annotations

import re

import numpy as np
from scipy.spatial.transform import Rotation

from laser_calib.io.errors import InputError
from laser_calib.io.read import csv_rows
from laser_calib.io.revisits import REVISIT_SPREAD
from laser_calib.io.samples import Samples, check_all_or_none, check_distance_units, check_joint_range, parse_table
from laser_calib.model.robot import Robot

POSITION, ROTATION = ("x", "y", "z"), ("phix", "phiy", "phiz")
_MARKER = re.compile(r"(x|y|z|phix|phiy|phiz)(\d+)")
MAX_ANGLE = 2 * np.pi + 0.5  # rad: a roll, pitch or yaw beyond it is in degrees
# said where time matters (a chronological split, a drift): the file has none, the parser numbers the rows
ROW_ORDER_AS_TIME = ("a FIGAROH file holds no time stamps: its rows are taken as measured in file order (stamp = row "
                     "number), which the chronological split and a drift in time follow")


def is_figaroh(text: str) -> bool:
    """A FIGAROH file: its header starts with marker 1's x (ours with pose,stamp)."""
    first = text.lstrip("\ufeff").split("\n", 1)[0].split(",", 1)[0].strip()
    return first == "x1"


def _markers(header: list[str], source: str) -> tuple[int, bool]:
    """Number of markers K and whether they carry an orientation (all or none do)."""
    count = 0
    while f"x{count + 1}" in header:
        count += 1
    rotations = set()
    for k in range(1, count + 1):
        missing = [f"{c}{k}" for c in POSITION if f"{c}{k}" not in header]
        if missing:
            raise InputError(f"{source}: header", f"missing column {missing[0]} (marker {k})")
        given = [f"{c}{k}" in header for c in ROTATION]
        if any(given) and not all(given):
            raise InputError(f"{source}: header", f"marker {k}: an orientation needs all of "
                                                  f"{', '.join(c + str(k) for c in ROTATION)}")
        rotations.add(all(given))
    if len(rotations) > 1:
        raise InputError(f"{source}: header", "some markers have an orientation (phix..phiz) and some do not")
    return count, rotations == {True}


def parse_figaroh(text: str, source: str, robot: Robot | None) -> Samples:
    if robot is None or robot.chain is None:
        raise InputError(source, "a FIGAROH calibration file names its joints as the URDF does: give the robot as "
                                 "--robot FILE.urdf --base LINK --tip LINK")
    rows = [row for row in csv_rows(text.lstrip("\ufeff"), source) if any(cell.strip() for cell in row)]
    header = [cell.strip() for cell in rows[0]]
    if len(set(header)) != len(header):
        raise InputError(f"{source}: header", "duplicate column names")
    count, oriented = _markers(header, source)
    tips = len(robot.chain.tips)
    if count != tips:
        raise InputError(f"{source}: header", f"{count} markers (x1..x{count}) but {tips} tip link(s) "
                                              f"({', '.join(robot.chain.tip_links)}): give one --tip per marker")
    missing = [name for name in robot.joint_names if name not in header]
    if missing:
        # the columns that name no joint of the robot: a misspelt name is among them
        unknown = [c for c in header if not _MARKER.fullmatch(c) and c not in robot.joint_names]
        raise InputError(f"{source}: header", f"no column for joint '{missing[0]}' (the robot's joints: "
                                              f"{', '.join(robot.joint_names)}"
                                              + (f"; columns that name none of them: {', '.join(unknown)}" if unknown
                                                 else "") + ")")
    measured = tuple(c for c in header if _MARKER.fullmatch(c))
    # pose and stamp by row, so that the shared parser names a bad field by its line
    pose, values = parse_table(["pose", "stamp"] + header, [[str(r), str(r)] + row for r, row in
                                                          enumerate(rows[1:])], source, measured)
    column = {name: values[:, 1 + i] for i, name in enumerate(header)}
    q = np.stack([column[name] for name in robot.joint_names], axis=1)
    check_joint_range(q, robot, source, pose)
    warnings = _unmodelled_joints({name: v for name, v in column.items() if not _MARKER.fullmatch(name)}, robot, source)
    blocks = []
    for k in range(1, count + 1):
        names = [f"{c}{k}" for c in POSITION + (ROTATION if oriented else ())]
        block = np.stack([column[name] for name in names], axis=1)
        check_all_or_none(block, source, f", marker {k}", f"only some of {','.join(names)} are given")
        blocks.append(block)
    block = np.stack(blocks, axis=1).reshape(-1, len(names))  # (P K, 3 or 6): row r's marker k at K r + k
    angles = block[:, 3:]
    if oriented and np.nanmax(np.abs(angles), initial=0.0) > MAX_ANGLE:
        raise InputError(f"{source}: fields phix..phiz", f"{np.nanmax(np.abs(angles)):.4g} rad: angles are in "
                                                         "radians (these look like degrees)")
    check_distance_units(block[:, :3], f"{source}: fields x,y,z")
    n = len(block)
    quaternion = None
    if oriented:
        quaternion = np.full((n, 4), np.nan)
        seen = ~np.isnan(angles).any(axis=1)
        quaternion[seen] = Rotation.from_euler("xyz", angles[seen]).as_quat(scalar_first=True)
    extra = {"tip": np.tile(np.arange(count, dtype=float), len(q))} if count > 1 else {}
    return Samples(np.arange(n), np.arange(n, dtype=float), np.repeat(q, count, axis=0), extra=extra,
                   position=block[:, :3], quaternion=quaternion, warnings=warnings)


def _unmodelled_joints(columns: dict[str, np.ndarray], robot: Robot, source: str) -> tuple[str, ...]:
    """One line naming the joint columns (name -> readings (P,)) the URDF chain neither reads nor
    drives (mimic) whose readings move: over REVISIT_SPREAD, which one pose's visits stay within."""
    fixed = {joint.name for joint in robot.chain.joints if not joint.movable}
    modelled = set(robot.joint_names) | {joint.name for joint in robot.chain.joints if joint.movable}
    moving = [f"{name} (reads {v.min():.3g} .. {v.max():.3g}; "
              f"{'the URDF marks it fixed' if name in fixed else 'off the chain: check --tip'})"
              for name, v in columns.items() if name not in modelled and np.ptp(v) > REVISIT_SPREAD]
    if not moving:
        return ()
    one = len(moving) == 1
    return (f"{source}: joint column{'' if one else 's'} {', '.join(moving)} move{'s' if one else ''} in these data "
            f"but the chain {robot.chain.base} -> {', '.join(robot.chain.tip_links)} does not read "
            f"{'it' if one else 'them'}: {'its' if one else 'their'} motion is not modelled",)
