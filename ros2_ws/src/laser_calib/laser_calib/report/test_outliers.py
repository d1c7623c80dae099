"""The test measurements a calibration misses grossly: wrong detections, or structure the
calibration poses do not show. They are listed and reported apart from the test figures, as
the fit's own rejected measurements are from the in-sample ones; a test set mostly beyond the
limit is no set of wrong measurements but a model that misses it, and is counted whole."""

from __future__ import annotations

import numpy as np

from laser_calib.estimation.estimate import Estimate, spot_sigma_at_zero
from laser_calib.estimation.outliers import named
from laser_calib.estimation.problem import Problem
from laser_calib.estimation.redundancy import deletion_distances, outlier_limit
from laser_calib.io.samples import Samples
from laser_calib.measurement.base import MeasurementModel, NoiseModel
from laser_calib.measurement.noise_components import MIN_SIGMA

# More test units than this share beyond the outlier limit are no wrong measurements but a model that
# misses the test poses (a joint column negated in the calibration set: 56 of 60 spots): all are counted.
# The share is below the robust rule's third (estimation.robust.MAX_REJECTED): the test figures are what
# shows a wrong model, and leaving its misses out would hide it.
MAX_TEST_OUTLIERS = 0.1


def test_status(model: MeasurementModel, seen: np.ndarray, est: Estimate, dims: int) -> np.ndarray:
    """(P,C) per test unit seen (P,C) (a spot, a point, a pose: ``dims`` values) of ``model`` (the test
    poses): 'tested',
    'outlier', 'beyond' (beyond the limit, but more than MAX_TEST_OUTLIERS of them: counted) or empty
    (not seen). An outlier's residual under the calibrated model, against its noise plus the estimate's
    uncertainty carried to it, is beyond the robust rule's limit at the calibration residual's variance
    (redundancy.deletion_distances and outlier_limit, as for a unit the fit left out), or the model
    does not reach it. One wrong test spot made a sound calibration's test figure 18 times the honest
    one, unsaid (a new user's probe); without the carried uncertainty, half of the paper arms' clean
    test sets had a spot beyond the limit. An exact fit (no noise) tests nothing: every unit 'tested'."""
    status = np.where(seen, "tested", "").astype("U8")  # room for the longest word
    if spot_sigma_at_zero(est.sigma, est.sigma_estimated) or not seen.any():
        return status
    noise = NoiseModel(max(est.sigma, MIN_SIGMA), est.joint_sigma)
    t2, dof = deletion_distances(Problem(model, noise, est.fit.free), est.fit, seen)
    beyond = seen & (t2 > outlier_limit(dims, dof, int(seen.sum()))) if dof >= 1 else np.zeros_like(seen)
    status[beyond] = "outlier" if beyond.sum() <= MAX_TEST_OUTLIERS * seen.sum() else "beyond"
    return status


def test_outlier_warnings(status: np.ndarray, samples: Samples, columns: str) -> list[str]:
    """The warning naming the test units beyond the outlier limit (test_status (P,C) of ``samples``),
    none without; ``columns``: where the table says which (residuals.csv's)."""
    what = "spots" if samples.kind == "spot" else "poses"
    outlier, beyond, seen = (status == "outlier"), (status == "beyond"), int((status != "").sum())
    if beyond.any():
        return [f"test: {int(beyond.sum())} of {seen} held-out {what} lie beyond the outlier limit of the calibrated "
                f"model, more than {MAX_TEST_OUTLIERS:.0%}: the model misses the test poses (all counted)"]
    units = list(zip(*np.nonzero(outlier)))
    if not units:
        return []
    return [f"test: {len(units)} of {seen} held-out {what} lie beyond the outlier limit of the calibrated model and "
            f"are not counted in the test figures: {named(samples, units)} (their figures apart; {columns}): wrong "
            "measurements, or structure the calibration poses do not show (diagnose tests which)"]
