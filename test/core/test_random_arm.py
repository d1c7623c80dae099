"""An arm nobody here designed: a random sensible 6-joint D-H arm (audit_random_arms/arms.py,
seed 0, arm 29: a nearly still first joint, 0.6 deg of travel, then five revolute joints
before the screen) in the paper's session with random errors.

Its weakest kept direction has a standard deviation of 5-6 tolerance scales (alpha2, about
0.1 rad), inside the 10 the estimate keeps (identifiability.STD_FACTOR). The noise then puts
alpha2 at 17-18 scales in seeds 1 and 2, and the fit exited 3 (NOT A CALIBRATION: "the nominal
model is wrong"), though the values agree with the truth within their standard deviations:
a value beyond FAR_SCALES is a wrong model only when it lies beyond it by more than its
noise (failures.FAR_SIGMAS). Each determined error that carries no held one is checked
against the true error: 4 standard deviations, which ~26 normal errors all stay within with
probability 99.8 %.
"""

import numpy as np
import pytest

from laser_calib.estimation.estimate import EstimateOptions, estimate
from laser_calib.estimation.failures import first_failure
from laser_calib.model.robot_file import robot_from_dict
from laser_calib.sim.simulation import robot_session

ARM = {
    "name": "random_0_29",
    "joints": [
        {"a": -0.7804142763, "d": -0.0384729592, "alpha": 0.0, "theta0": 2.8603709071,
         "min": -0.0085191845, "max": 0.002308898},
        {"a": 0.0, "d": 0.0, "alpha": 1.5707963268, "theta0": 3.1415926536, "min": -3.8099766969, "max": 0.4974394068},
        {"a": 0.0, "d": 0.2874705777, "alpha": 1.5707963268, "theta0": -1.5707963268,
         "min": -3.1415926536, "max": 3.1415926536},
        {"a": 0.0, "d": -0.1435739608, "alpha": -1.5707963268, "theta0": 1.5707963268,
         "min": -3.1415926536, "max": 3.1415926536},
        {"a": -0.0542935165, "d": -0.2755875748, "alpha": -1.5707963268, "theta0": 3.1415926536,
         "min": -0.4956377673, "max": 0.540626792},
        {"a": 0.2348318552, "d": -0.0594756247, "alpha": 0.0, "theta0": -3.0658563396,
         "min": -0.8653485504, "max": 0.1409059748},
    ],
    "slm": {"a": 0.05, "d": 0.061070073, "alpha": 1.5583965624, "theta": -0.3521419059, "beta": 0.0},
    "lasers": [{"gamma": -0.5235987756, "beta": 0.0}, {"gamma": 0.5235987756, "beta": 0.0}],
}
Z_MAX = 4.0


@pytest.mark.parametrize("seed", [1, 2])
def test_weak_direction_beyond_far_scales_by_noise_is_a_calibration(seed):
    robot = robot_from_dict(ARM, "random_0_29")
    session = robot_session(robot, seed, 30, random_errors=True)
    cal = session.samples.subset(session.cases["case2"][0])
    est = estimate(robot, cal, EstimateOptions())
    assert first_failure(est.warnings) is None, est.warnings
    alpha2 = est.names.index("alpha2")
    assert est.errors[alpha2] / np.deg2rad(1.0) > 10.0 or est.errors[alpha2] / np.deg2rad(1.0) < -10.0, \
        "the case this test is about: alpha2 fitted beyond FAR_SCALES"
    carriers = set(est.identifiability.carried)
    own = [i for i, name in enumerate(est.names) if np.isfinite(est.errors[i]) and name not in carriers]
    z = (est.errors[own] - session.errors[own]) / est.std[own]
    assert np.abs(z).max() < Z_MAX, dict(zip(np.array(est.names)[own], np.round(z, 2)))
