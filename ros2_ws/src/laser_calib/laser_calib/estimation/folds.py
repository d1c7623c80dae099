"""How poses are split for held-out errors: seeded k-fold, or chronological
(calibrate on the first part of a session, test on the rest), how far the
test poses leave the joint range the calibration covered, and the joints it
never moved.

Samples are in measurement order (stamps increase, conventions.md), so row
order is time order.
"""

from __future__ import annotations

import numpy as np

# A reading this share of the covered span past its ends still counts as inside:
# the extreme poses of a random k-fold always lie just outside their training
# folds, a step past the data rather than a region of the workspace it never saw.
RANGE_SLACK = 0.05
STILL_SPREAD = 1e-6  # rad or m: readings within this of each other are one joint position (no calibration moves less)


def kfold_labels(n: int, k: int, seed: int) -> np.ndarray:
    """(n,) fold index 0..k-1 of each pose, a seeded random balanced split."""
    if not 2 <= k <= n:
        raise ValueError(f"k-fold needs 2 <= k <= {n} poses, got k = {k}")
    return np.random.default_rng(seed).permutation(np.arange(n) % k)


def chronological_labels(n: int, fraction: float) -> np.ndarray:
    """(n,) 0 for the first ``fraction`` of the poses in measurement order (the
    calibration), 1 for the rest (the test); both parts hold at least one pose."""
    if not 0 < fraction < 1:
        raise ValueError(f"the calibration fraction of a chronological split must be in (0, 1), got {fraction}")
    n_train = int(round(fraction * n))
    if not 1 <= n_train < n:
        raise ValueError(f"a chronological split of {n} poses at {fraction} leaves one part empty")
    return (np.arange(n) >= n_train).astype(int)


def outside_range(q: np.ndarray, labels: np.ndarray, tested, slack: float = RANGE_SLACK) -> np.ndarray:
    """(N,) fraction of the tested poses whose reading of joint i lies outside
    the [min, max] of joint i over the poses their prediction was fitted on
    (all poses of the other folds), widened by ``slack`` x its span on each
    side; q (P,N), labels (P,) fold of each pose, tested: the folds predicted
    (every fold for k-fold, the test part of a chronological split)."""
    outside = []
    for fold in tested:
        train, test = q[labels != fold], q[labels == fold]
        low, high = train.min(axis=0), train.max(axis=0)
        margin = slack * (high - low)
        outside.append((test < low - margin) | (test > high + margin))
    return np.concatenate(outside).mean(axis=0)


def range_warnings(fraction: np.ndarray, what: str, joints: tuple[str, ...]) -> list[str]:
    """One warning per joint (named by ``joints``, (N,)) with test poses outside the calibration's range."""
    return [f"{what}: {share:.0%} of the test poses have {joint} outside the range the calibration covered "
            "(held-out errors there are an extrapolation)"
            for joint, share in zip(joints, fraction) if share > 0]


def test_outside_range(q_calibration: np.ndarray, q_test: np.ndarray) -> np.ndarray:
    """outside_range (N,) of a test set (Q,N) against the calibration's readings (P,N)."""
    labels = np.r_[np.zeros(len(q_calibration), int), np.ones(len(q_test), int)]
    return outside_range(np.vstack([q_calibration, q_test]), labels, (1,))


def test_range_warnings(q_calibration: np.ndarray, q_test: np.ndarray, what: str, joints: tuple[str, ...]) -> list[str]:
    """range_warnings for a test set (Q,N) against the calibration's readings (P,N)."""
    return range_warnings(test_outside_range(q_calibration, q_test), what, joints)


def still_joint_warnings(q: np.ndarray, joints: tuple[str, ...]) -> list[str]:
    """One warning per joint whose readings q (P,N) do not change over the poses: what only its
    motion shows is held (identifiability), but the user should hear why, and a column of constant
    readings where the joint did move (a wrong export) leaves the rest of the fit to explain it."""
    if len(q) < 2:
        return []
    return [f"{name} reads {q[0, i]:.6g} in all {len(q)} poses: the joint never moved in these data (what only its "
            "motion shows is held); if it did move, its column holds something else"
            for i, name in enumerate(joints) if np.ptp(q[:, i]) <= STILL_SPREAD]
