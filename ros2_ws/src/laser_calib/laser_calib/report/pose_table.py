"""The per-pose residual CSV every command writes beside its result:

    set,pose,stamp,<columns...>

one row per measured pose, in measurement order within each set
('calibration', 'test'); SI units in the column names (_m, _rad); an empty
field where the figure does not apply (not seen, not in that split); what
the fit did with a calibration spot in its laser's _fit column, with a point
or pose sample in 'fit' (fit_status).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from laser_calib.io.samples import Samples


ROWS_AT_ONCE = 10000  # rows formatted at a time: the text of 10^5 poses is never held as Python strings


def format_pose_table(sets: dict[str, tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]]) -> str:
    """sets: name -> (pose (P,), stamp (P,), {column: (P,) values}); the header
    holds every set's columns, a set without a column leaves it empty."""
    out = io.StringIO()
    write_pose_table(sets, out)
    return out.getvalue()


def write_pose_table(sets: dict[str, tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]], out) -> None:
    """format_pose_table's text written to the text stream ``out``, ROWS_AT_ONCE rows at a time."""
    columns = list(dict.fromkeys(name for _, _, table in sets.values() for name in table))
    csv.writer(out, lineterminator="\n").writerow(["set", "pose", "stamp"] + columns)
    for set_name, (pose, stamp, table) in sets.items():
        for start in range(0, len(pose), ROWS_AT_ONCE):
            rows = slice(start, start + ROWS_AT_ONCE)
            # column by column (one type test per column, not one per cell); no field needs CSV quoting
            cells = [[str(int(v)) for v in np.asarray(pose[rows]).tolist()],
                     list(map(repr, np.asarray(stamp[rows], float).tolist()))]
            cells += [_cells(None if table.get(c) is None else table[c][rows], len(cells[0])) for c in columns]
            out.write("".join(f"{set_name},{line}\n" for line in map(",".join, zip(*cells))))


def _cells(values: np.ndarray | None, n_rows: int) -> list[str]:
    """One column's fields: integer columns (fold indices) as integers, floats at full precision (repr), NaN empty."""
    if values is None:
        return [""] * n_rows
    if values.dtype.kind == "U":  # words (a spot's status): no field needs CSV quoting
        return values.tolist()
    if np.issubdtype(values.dtype, np.integer):
        return [str(v) for v in values.tolist()]
    values = values.astype(float)
    cells = list(map(repr, values.tolist()))
    for i in np.flatnonzero(np.isnan(values)).tolist():
        cells[i] = ""
    return cells


def save_pose_table(sets: dict[str, tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]], path: str | Path) -> None:
    with open(path, "w", newline="") as out:
        write_pose_table(sets, out)


def spot_columns(samples: Samples, calibrated: np.ndarray, nominal: np.ndarray) -> dict[str, np.ndarray]:
    """Per-pose columns (P,) of laser spot samples, per laser j: the residual
    measured - predicted (y, z) of the calibration and its length, and the
    length for the nominal model; calibrated, nominal: the predicted spots
    (P,2,2) (report.calibration.SetEvaluation); m, NaN where not seen."""
    columns = {}
    for label, predicted in (("", calibrated), ("nominal_", nominal)):
        residual = samples.spots - predicted                                  # (P,2,2)
        for j in range(residual.shape[1]):
            if not label:
                columns[f"l{j + 1}_dy_m"], columns[f"l{j + 1}_dz_m"] = residual[:, j].T
            columns[f"{label}l{j + 1}_distance_m"] = np.linalg.norm(residual[:, j], axis=1)
    return columns


NOT_FITTED = ("rejected", "refused")  # the fit_status words of values measured but not fitted


def fit_status(seen: np.ndarray, rejected, refused) -> np.ndarray:
    """(P,C) what the fit did with each measured value of a calibration set (a
    laser's spot, C = 2; a point or pose sample, C = 1; seen (P,C) bool):
    'fitted', 'rejected' (an outlier of the robust rule; rejected: (pose index,
    channel) pairs) or 'refused' (physically impossible, before the fit;
    refused: (pose index, channel, reason)), empty where not seen."""
    status = np.where(seen, "fitted", "").astype("U8")  # room for the longest word
    for p, c in rejected:
        status[p, c] = "rejected"
    for p, c, _ in refused:
        status[p, c] = "refused"
    return status


def spot_status(status: np.ndarray) -> dict[str, np.ndarray]:
    """Per-pose columns (P,) l{j}_fit of a calibration set's laser spots from
    their fit_status (P,2): what residuals.csv holds of every spot."""
    return {f"l{j + 1}_fit": status[:, j] for j in range(status.shape[1])}
