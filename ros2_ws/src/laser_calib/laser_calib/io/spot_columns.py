"""The spot columns' assignment checked against the nominal model: a samples file
whose l1 and l2 columns (or y and z) are swapped is refused, not fitted; a negated
y or z that matches as well is named beside the swap (MIRRORS).

Such a file fits to a wrong minimum with an exit status 0 (the fit drops the
spots it cannot reach, or fits errors of metres), so it is caught before the fit,
where the file's name is known. Each pose's spots are compared with the nominal
model's prediction as given and under each swap; a pose votes for a swap when
its spots lie more than SWAP_MARGIN closer to the swapped prediction, and at
most half as far (SWAP_RATIO) from it.

Why it does not fire on honest data: a measured spot m lies at the nominal
model's error e from its predicted spot p, and a swap predicts p' instead, so
|m - p'| >= |p - p'| - e and the swap gains at most 2e - |p - p'|. A pose votes
only where its nominal error exceeds half of (|p - p'| + SWAP_MARGIN): the two
spots of a pose lie 0.17 m to 1 m apart (lasers at +-30 deg), y and z differ
alike away from the screen's diagonal, and manufacturing errors (10 mm / 1 deg)
move a spot by tens of mm (the paper's 7-DOF arm: median 90 mm, the worst spot
of a session 0.3 m to 0.8 m). A swap shows the other way round, at every pose
whose spots lie more than SWAP_MARGIN plus twice the error apart, so the file is
refused when most poses vote; a minority (gross outliers) never refuses it.
In simulated sessions of both paper arms (seeds 0-5, spot noise 2 mm to 50 mm,
paper's or random errors; the 7-DOF arm from its URDF too) no honest pose
voted, and every swapped file was refused with 77 % of its poses voting or more.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.model.kinematics import predict
from laser_calib.model.robot import Robot

SWAP_MARGIN = 0.1  # m: a pose votes for a swap that brings its spots closer by more (module docstring)
# and that at least halves their distance: spots that match no assignment (made up, or
# another robot's) are far from both predictions, and that is no swap
SWAP_RATIO = 2.0
MIN_VOTES = 3      # a pose or two can be outliers; a swap of the columns shows at every pose

# (what the columns hold if the swap is true, the laser order, the coordinate order)
SWAPS = (("l1_* and l2_* swapped (laser 1's spot is in l2_y,l2_z)", [1, 0], [0, 1]),
         ("y and z swapped (l1_y holds laser 1's z)", [0, 1], [1, 0]),
         ("l1_* and l2_* swapped, and y and z swapped", [1, 0], [1, 0]))
# A coordinate negated (a screen frame's axis, or an image's rows, the other way round) is
# never refused on its own: for spots on one side of an axis it looks like a nominal model
# off along it, as a screen frame placed wrongly is. It is named beside a refused swap
# that it predicts alike (ALIKE), as y negated and l1 <-> l2 do for lasers that are
# mirror images about y, so the message does not name one cause where there are two.
MIRRORS = (("y negated (the screen frame's y axis, or the image's, reversed)", [-1, 1]),
           ("z negated (the screen frame's z axis, or the image's, reversed)", [1, -1]))
MIRROR_LABELS = {label for label, _ in MIRRORS}
ALIKE = 2.0
# (label, laser order, coordinate order, coordinate signs) of every assignment compared
ASSIGNMENTS = ([(label, lasers, coords, [1, 1]) for label, lasers, coords in SWAPS]
               + [(label, [0, 1], [0, 1], signs) for label, signs in MIRRORS])


@dataclass(frozen=True)
class SwapVotes:
    """How one swap of the columns compares with the columns as given: votes of the
    judged poses (a spot measured and predicted on the screen plane both ways); the
    median over those poses of their spots' mean distance to the prediction, m."""

    label: str
    votes: int
    judged: int
    median_given: float
    median_swapped: float


def swap_votes(robot: Robot, q: np.ndarray, spots: np.ndarray) -> list[SwapVotes]:
    """Each swap's votes (module docstring) from the spots (P,2,2) [pose, laser, (y,z)]
    at the joint readings q (P,N), and the nominal model's prediction there: SWAPS,
    then MIRRORS."""
    predicted = predict(robot, q)
    ahead = np.isfinite(predicted.spots).all(axis=2) & (predicted.k > 0)  # (P,2) beam meets the screen plane
    seen = ~np.isnan(spots).any(axis=2)
    given = np.linalg.norm(spots - predicted.spots, axis=2)               # (P,2) m
    out = []
    for label, lasers, coords, signs in ASSIGNMENTS:
        swapped = np.linalg.norm(spots - predicted.spots[:, lasers][:, :, coords] * signs, axis=2)
        usable = seen & ahead & ahead[:, lasers]                          # (P,2) judged both ways
        judged = usable.any(axis=1)
        if not judged.any():
            continue
        count = usable[judged].sum(axis=1)
        mean_given = np.where(usable, given, 0.0)[judged].sum(axis=1) / count
        mean_swapped = np.where(usable, swapped, 0.0)[judged].sum(axis=1) / count
        closer = (mean_given - mean_swapped > SWAP_MARGIN) & (SWAP_RATIO * mean_swapped < mean_given)
        out.append(SwapVotes(label, int(closer.sum()), int(judged.sum()),
                             float(np.median(mean_given)), float(np.median(mean_swapped))))
    return out


def check_spot_columns(robot: Robot, q: np.ndarray, spots: np.ndarray, source: str) -> None:
    """One line naming ``source`` when most poses' spots (P,2,2) at the joint readings
    q (P,N) match the nominal model far better with swapped columns (swap_votes)."""
    votes = [v for v in swap_votes(robot, q, spots) if v.votes >= MIN_VOTES and 2 * v.votes > v.judged]
    mirrors = [v for v in votes if v.label in MIRROR_LABELS]
    found = [v for v in votes if v.label not in MIRROR_LABELS]
    if found:
        worst = max(found, key=lambda v: (v.votes, -v.median_swapped))
        named = sorted([worst] + [v for v in mirrors if v.median_swapped <= ALIKE * worst.median_swapped],
                       key=lambda v: v.median_swapped)
        best = named[0]
        raise InputError(source, f"the spot columns look assigned wrongly: {', or '.join(v.label for v in named)}. "
                                 f"At {best.votes} of {best.judged} poses the spots lie over {SWAP_MARGIN * 1e3:.0f} mm "
                                 f"closer to the nominal model's spots so changed (median {best.median_swapped * 1e3:.0f} "
                                 f"mm so, {best.median_given * 1e3:.0f} mm as given); the columns are "
                                 "l1_y,l1_z,l2_y,l2_z, laser 1 the first of the robot file's lasers, y and z along the "
                                 "screen frame's axes")
