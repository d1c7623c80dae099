"""Error metrics: spot distances between measured (or true) and predicted spots."""

from __future__ import annotations

import numpy as np

from laser_calib.model.kinematics import predict
from laser_calib.model.robot import Robot
from laser_calib.io.samples import Samples


def spot_distances(robot: Robot, samples: Samples, errors: np.ndarray | None = None) -> np.ndarray:
    """(P,2) Euclidean distance in m between each seen spot and the model's
    prediction at the joint readings; NaN where the spot was not seen."""
    predicted = predict(robot, samples.q, errors).spots
    return np.linalg.norm(samples.spots - predicted, axis=2)


def laser_stats(distances: np.ndarray) -> dict:
    """Per laser and over all seen spots: count, mean, std, max, rms in mm."""
    out = {}
    columns = {f"laser{j + 1}": distances[:, j] for j in range(distances.shape[1])}
    columns["all"] = distances.ravel()
    for key, values in columns.items():
        seen = values[np.isfinite(values)] * 1e3
        if seen.size == 0:
            out[key] = {"n": 0, "mean_mm": None, "std_mm": None, "max_mm": None, "rms_mm": None}
            continue
        out[key] = {"n": int(seen.size), "mean_mm": float(seen.mean()),
                    "std_mm": float(seen.std(ddof=1)) if seen.size > 1 else 0.0,
                    "max_mm": float(seen.max()), "rms_mm": float(np.sqrt(np.mean(seen ** 2)))}
    return out
