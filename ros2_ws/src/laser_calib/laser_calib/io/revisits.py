"""Repeated visits of a pose (rows sharing a pose id, conventions.md) checked for
agreement: their joint readings must name one pose, else a warning.

The sequencer records a visit once every reading is within its settle tolerance
(0.003 rad, session/settle.py) of the pose's goal, so two visits of one goal read
at most 0.006 rad apart; encoder noise is smaller still (a count of a 4096-count
encoder is 0.0015 rad; the simulator's default joint disturbance +-0.0017 rad).
Readings of one id over REVISIT_SPREAD apart are two poses under one id (an
export that reused ids, a typo): the fit takes each row at its own readings, but
ISO 9283 accuracy and repeatability group the rows by id as one pose.
"""

from __future__ import annotations

import numpy as np

REVISIT_SPREAD = 0.02  # rad (m for a prismatic joint): over 3x the widest spread of honest visits
LISTED = 5             # poses named in the warning line


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
