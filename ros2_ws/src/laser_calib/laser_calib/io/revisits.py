"""Repeated visits of a pose (rows sharing a pose id, conventions.md) checked for
agreement: their joint readings must name one pose, else a warning.

The sequencer records a visit once every reading is within its settle tolerance
(0.003 rad, session/settle.py) of the pose's goal, so two visits of one goal read
at most 0.006 rad apart; encoder noise is smaller still (a count of a 4096-count
encoder is 0.0015 rad; the simulator's default joint disturbance +-0.0017 rad).
Readings of one id over REVISIT_SPREAD apart are two poses under one id (an
export that reused ids, a typo): the fit takes each row at its own readings, but
ISO 9283 accuracy and repeatability group the rows by id as one pose.

A row whose joint readings and measured values (spots, positions) equal another's
exactly is a copy, not a visit: readings may repeat to the encoder count, but a
camera or tracker never measures twice without noise (a logger writing a sample
twice). Copies are warned of, not dropped: they count twice in a fit (its std
understated) and bring a zero scatter to the repeatability figures. Values not
seen (NaN) are equal to each other; a row with nothing measured adds nothing.

A test pose within REVISIT_SPREAD of a calibration pose is that pose again: with
identical measured values it is the same measurement the fit was given (its test
error is no held-out error); measured anew it is a revisit, held out from the
fit's noise but not from its poses (repeatability, ISO 9283 style, not the error
at poses the fit never saw). Either is said in one line, the count of each given.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from laser_calib.io.samples import Samples

REVISIT_SPREAD = 0.02  # rad (m for a prismatic joint): over 3x the widest spread of honest visits
LISTED = 5             # poses named in the warning line
MEASURED = {"spot": "spots", "point": "measured positions", "pose": "measured poses"}


def repeat_warnings(samples: Samples, test: Samples | None, joints: tuple[str, ...], sources: dict) -> list[str]:
    """The warnings of rows that repeat: revisit_warnings and copy_warnings of the calibration
    samples and the test set, then heldout_repeat_warnings; each set named by its file in
    ``sources`` (keys 'samples', 'test'), else by the key."""
    names = [str(sources.get(key) or key) for key in ("samples", "test")]
    said = []
    for s, where in zip((samples, test), names):
        if s is not None:
            said += revisit_warnings(s.pose, s.q, joints, where) + copy_warnings(s, where)
    return said + ([] if test is None else heldout_repeat_warnings(samples, test, *names))


def revisit_warnings(pose: np.ndarray, q: np.ndarray, joints: tuple[str, ...], where: str) -> list[str]:
    """One warning naming ``where`` and the pose ids (P,) whose rows' joint readings q (P,N)
    differ by more than REVISIT_SPREAD, each with its joint of largest spread."""
    ids, row_id = np.unique(pose, return_inverse=True)
    if len(ids) == len(pose):
        return []
    highest = np.full((len(ids), q.shape[1]), -np.inf)
    lowest = np.full((len(ids), q.shape[1]), np.inf)
    np.maximum.at(highest, row_id, q)
    np.minimum.at(lowest, row_id, q)
    spread = highest - lowest                                   # (K,N) per pose id and joint
    apart = np.flatnonzero(spread.max(axis=1) > REVISIT_SPREAD)
    if not len(apart):
        return []
    named = [f"pose {ids[k]} ({joints[int(np.argmax(spread[k]))]} readings {spread[k].max():.3g} apart)"
             for k in apart[:LISTED]]
    more = f" and {len(apart) - LISTED} more" if len(apart) > LISTED else ""
    ids_text = "a pose id" if len(apart) == 1 else f"{len(apart)} pose ids"
    return [f"{where}: {ids_text} repeated with different joint readings: {', '.join(named)}{more}; repeated "
            f"visits of one pose read within {REVISIT_SPREAD:g} rad (m if prismatic), so these rows are different "
            "poses under one id (each is fitted at its own readings, but the ISO 9283 figures take them as one pose)"]


def _row_keys(samples: Samples) -> np.ndarray:
    """(P,) one key per row of its joint readings and measured values, equal exactly when
    the rows' values are (NaN equal to NaN, -0 to 0)."""
    values = np.hstack([samples.q, samples.measured]) + 0.0
    values[np.isnan(values)] = np.nan  # one bit pattern for every NaN
    return np.ascontiguousarray(values).view(np.dtype((np.void, values.itemsize * values.shape[1]))).ravel()


def _measured(samples: Samples) -> np.ndarray:
    """(P,) bool: something was measured in the row."""
    return samples.seen.reshape(len(samples), -1).any(axis=1)


def originals(samples: Samples) -> np.ndarray:
    """(P,) per row the index of the first row whose readings and measured values it equals exactly
    (its own index when none before it does)."""
    _, first, group = np.unique(_row_keys(samples), return_index=True, return_inverse=True)
    return first[group]


def copied(samples: Samples, original: np.ndarray | None = None) -> np.ndarray:
    """(P,) bool: the row measures something and copies an earlier row exactly (module docstring);
    ``original``: originals(samples), when the caller has them."""
    original = originals(samples) if original is None else original
    return _measured(samples) & (original != np.arange(len(samples)))


def copy_warnings(samples: Samples, where: str) -> list[str]:
    """One warning naming ``where`` and the first rows (counted from 1 after the header) whose
    readings and measured values equal an earlier row's exactly (module docstring)."""
    original = originals(samples)
    copies = np.flatnonzero(copied(samples, original))
    if not len(copies):
        return []
    named = [f"row {r + 1} = row {original[r] + 1} (pose {samples.pose[r]})" for r in copies[:LISTED]]
    more = f" and {len(copies) - LISTED} more" if len(copies) > LISTED else ""
    return [f"{where}: {len(copies)} of {len(samples)} rows repeat an earlier row's joint readings and "
            f"{MEASURED[samples.kind]} exactly: {', '.join(named)}{more}; no sensor measures twice without noise, so "
            "these are copies (a logger writing a sample twice?), counted twice in every figure over them (a fit's "
            "std understated, the ISO 9283 repeatability RP pulled toward 0)"]


def heldout_repeat_warnings(calibration: Samples, test: Samples, where_calibration: str, where_test: str) -> list[str]:
    """One warning naming both files when measured test poses read within REVISIT_SPREAD of a
    calibration pose, with how many are the same measurement and how many revisits (module docstring)."""
    distance = cKDTree(calibration.q).query(test.q, p=np.inf, distance_upper_bound=REVISIT_SPREAD)[0]
    repeated = _measured(test) & np.isfinite(distance)
    if not repeated.any():
        return []
    same = repeated & np.isin(_row_keys(test), _row_keys(calibration))
    word = MEASURED[test.kind]
    parts = [f"{n} {text}" for n, text in (
        (same.sum(), f"with identical {word}, the same measurements the fit was given (the test figures over them "
                     "are in-sample figures, not held-out ones)"),
        ((repeated & ~same).sum(), f"with new {word}, revisits (held out from the fit's measurements but not from "
                                   "its poses: a repeatability check, not the error at poses the fit never saw)")) if n]
    return [f"{where_test}: {repeated.sum()} of {len(test)} test poses repeat a calibration pose of "
            f"{where_calibration} (joint readings within {REVISIT_SPREAD:g} rad, m if prismatic): {'; '.join(parts)}"]
