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
    figures: dict[str, list] = {"AP": [], "RP": [], "AP_abc": [], "RP_abc": []}
    visits = 0
    for p in np.unique(pose[seen]):
        members = np.flatnonzero(seen & (pose == p))
        if len(members) < 2:
            continue
        barycentre = measured[members].mean(axis=0)
        figures["AP"].append(np.linalg.norm(barycentre - predicted[members].mean(axis=0)))
        spread = np.linalg.norm(measured[members] - barycentre, axis=1)
        figures["RP"].append(spread.mean() + 3 * spread.std(ddof=1))
        if rotation is not None:
            figures["AP_abc"].append(np.abs(rotation[members].mean(axis=0)))
            figures["RP_abc"].append(3 * rotation[members].std(axis=0, ddof=1))
        visits += len(members)
    if not figures["AP"]:
        return None
    out = {"poses": len(figures["AP"]), "visits": visits,
           "AP": summary(np.array(figures["AP"]), factor), "RP": summary(np.array(figures["RP"]), factor)}
    if rotation is not None:
        for name in ("AP", "RP"):
            angles = np.array(figures[f"{name}_abc"])             # (poses, 3)
            out |= {f"{name}_{axis}": summary(angles[:, i], angle_factor) for i, axis in enumerate("abc")}
    return out
