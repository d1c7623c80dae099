"""Error statistics, the one helper every table uses: count, mean, std, RMS, P95
and max of a set of errors, ISO 9283 pose accuracy and repeatability where the
data has repeated poses, and the spot distances of a laser calibration."""

from __future__ import annotations

import numpy as np

from laser_calib.io.samples import Samples
from laser_calib.model.kinematics import predict
from laser_calib.model.robot import Robot

STATISTICS = ("mean", "std", "rms", "p95", "max")


def summary(values: np.ndarray, factor: float = 1.0, suffix: str = "") -> dict:
    """n and mean, std (ddof 1; 0 for one value), RMS, 95th percentile (linear
    interpolation) and max of the finite entries of ``values`` (any shape) times
    ``factor``, keyed '<statistic><suffix>'; None for each when nothing is finite."""
    seen = np.asarray(values, float)
    seen = seen[np.isfinite(seen)] * factor
    if seen.size == 0:
        return {"n": 0} | {name + suffix: None for name in STATISTICS}
    figures = {"mean": seen.mean(), "std": seen.std(ddof=1) if seen.size > 1 else 0.0,
               "rms": np.sqrt(np.mean(seen ** 2)), "p95": np.percentile(seen, 95), "max": seen.max()}
    return {"n": int(seen.size)} | {name + suffix: float(value) for name, value in figures.items()}


def rms_where_both(before: np.ndarray, after: np.ndarray) -> tuple[float, float, int] | None:
    """RMS (m) of two models' distances (same shape, NaN where a model predicts nothing) over the
    measurements both predict, and how many those are; None when there are none. A comparison of
    two models on a test set counts only what both predict."""
    both = np.isfinite(before) & np.isfinite(after)
    if not both.any():
        return None
    return float(np.sqrt(np.mean(before[both] ** 2))), float(np.sqrt(np.mean(after[both] ** 2))), int(both.sum())


def one_pose_decides(before: np.ndarray, after: np.ndarray, poses: np.ndarray) -> str | None:
    """The clause naming the pose that carries over half of the increase of the sum of squares
    from ``before`` to ``after`` (two models' distances (P,...) in m, NaN where a model predicts
    nothing, over the measurements both predict; ``poses`` (P,) the pose ids), saying whether
    the rest is worse without it; None when no pose does. A test figure one pose decides says
    more about that pose (a grazing beam, a configuration the calibration poses pin down poorly:
    the true model itself missed one such spot by 16 mm) than about the model."""
    both = np.isfinite(before) & np.isfinite(after)
    squares = (np.where(both, after, 0.0) ** 2 - np.where(both, before, 0.0) ** 2).reshape(len(before), -1)
    increase = squares.sum(axis=1)                                    # (P,) m^2
    worst = int(np.argmax(increase)) if len(increase) else 0
    if not len(increase) or increase.sum() <= 0 or increase[worst] <= 0.5 * increase.sum():
        return None
    others = np.arange(len(before)) != worst
    rest = rms_where_both(before[others], after[others])
    if rest is not None and rest[1] <= rest[0]:
        return (f"without test pose {int(poses[worst])} it is not worse (RMS {rest[0] * 1e3:.3g} mm -> "
                f"{rest[1] * 1e3:.3g} mm): look at that pose first")
    return f"test pose {int(poses[worst])} alone carries {increase[worst] / increase.sum():.0%} of the increase"


def worse_on_test_warning(before: np.ndarray, after: np.ndarray, poses: np.ndarray, figures: str,
                          causes: str) -> list[str]:
    """The warning when the model of ``after`` misses a test set by more than that of ``before``
    (one_pose_decides' distances and pose ids; RMS over what both predict), [] otherwise:
    ``figures`` (a template of the RMS {before} and {after} in mm and the {count}), then
    ``causes`` (what makes a model worse on poses it never saw) and the pose that carries most
    of the increase; when the figure is not worse without that pose, the pose instead of the causes."""
    compared = rms_where_both(before, after)
    if compared is None or compared[1] <= compared[0]:
        return []
    said = figures.format(before=compared[0] * 1e3, after=compared[1] * 1e3, count=compared[2])
    decided = one_pose_decides(before, after, poses)
    if decided is not None and decided.startswith("without"):  # one pose, not the model
        return [f"{said}; {decided}"]
    return [f"{said}: {causes}" + (f"; {decided}" if decided else "")]


def spot_distances(robot: Robot, samples: Samples, errors: np.ndarray | None = None) -> np.ndarray:
    """(P,2) Euclidean distance in m between each seen spot and the model's
    prediction at the joint readings; NaN where the spot was not seen."""
    predicted = predict(robot, samples.q, errors).spots
    return np.linalg.norm(samples.spots - predicted, axis=2)


def laser_stats(distances: np.ndarray) -> dict:
    """summary() in mm of the spot distances (P,2) per laser and over all seen spots."""
    columns = {f"laser{j + 1}": distances[:, j] for j in range(distances.shape[1])}
    columns["all"] = distances
    return {key: summary(values, 1e3, "_mm") for key, values in columns.items()}


def iso9283(pose: np.ndarray, measured: np.ndarray, predicted: np.ndarray, factor: float = 1.0,
            rotation: np.ndarray | None = None, angle_factor: float = 1.0) -> dict | None:
    """ISO 9283 (7.2.1, 7.2.2) pose accuracy AP and repeatability RP of each pose
    visited at least twice, the predicted pose standing for the command.

    Position: AP = |mean measured - mean predicted| (the distance of the
    barycentre of the attained positions from the commanded one) and
    RP = mean(l) + 3 S_l, l_i = |measured_i - barycentre|, S_l its standard
    deviation (ddof 1). Orientation, when ``rotation`` (P,3) gives each visit's
    rotation vector of inv(predicted) · measured in rad (small angles: the
    standard's a, b, c deviations about the three axes): AP_a = |mean a_i| and
    RP_a = 3 S_a per axis.

    pose (P,) ids, equal for repeated visits; measured, predicted (P,D) in m,
    NaN rows where not seen. None when no pose has two seen visits, else
    {"poses", "visits", "AP", "RP"[, "AP_a".."RP_c"]}: summaries over the
    repeated poses, lengths times ``factor``, angles times ``angle_factor``."""
    seen = np.isfinite(measured).all(axis=1) & np.isfinite(predicted).all(axis=1)
    if rotation is not None:
        seen &= np.isfinite(rotation).all(axis=1)
    # The visits grouped by pose id (sorted, as np.unique orders the poses), each
    # group's sums by one reduceat: a Python loop per pose costs minutes at 10^5 poses.
    rows = np.flatnonzero(seen)
    _, group, counts = np.unique(pose[rows], return_inverse=True, return_counts=True)
    repeated = counts[group] >= 2
    if not repeated.any():
        return None
    rows, group = rows[repeated], group[repeated]
    order = np.argsort(group, kind="stable")
    rows = rows[order]
    # relabelled 0..G-1 over the sorted visits: (G,) first visit and visits per repeated pose
    _, starts, group, counts = np.unique(group[order], return_index=True, return_inverse=True, return_counts=True)

    def group_mean(values: np.ndarray) -> np.ndarray:               # (V,K) -> (G,K)
        return np.add.reduceat(values, starts, axis=0) / counts[:, None]

    def group_std(values: np.ndarray, mean: np.ndarray) -> np.ndarray:   # ddof 1, (G,K)
        return np.sqrt(np.add.reduceat((values - mean[group]) ** 2, starts, axis=0) / (counts - 1)[:, None])

    barycentre = group_mean(measured[rows])
    spread = np.linalg.norm(measured[rows] - barycentre[group], axis=1)[:, None]   # (V,1)
    mean_spread = group_mean(spread)
    out = {"poses": len(counts), "visits": int(counts.sum()),
           "AP": summary(np.linalg.norm(barycentre - group_mean(predicted[rows]), axis=1), factor),
           "RP": summary((mean_spread + 3 * group_std(spread, mean_spread))[:, 0], factor)}
    if rotation is not None:
        mean_rotation = group_mean(rotation[rows])
        figures = {"AP": np.abs(mean_rotation), "RP": 3 * group_std(rotation[rows], mean_rotation)}   # (G,3)
        for name, angles in figures.items():
            out |= {f"{name}_{axis}": summary(angles[:, i], angle_factor) for i, axis in enumerate("abc")}
    return out
