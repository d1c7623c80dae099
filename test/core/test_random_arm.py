"""Arms nobody here designed: random sensible D-H arms (a seeded generator of a random-arm
audit; each arm inlined below by its seed and number) in the paper's session with random
errors, estimated as `laser-calib estimate` does. Each determined error that carries no held
one is checked against the true error: 4 standard deviations, which ~26 normal errors all stay
within with probability 99.8 %.

Seed 0, arm 29 (a nearly still first joint, 0.6 deg of travel, then five revolute joints before
the screen): its weakest kept direction has a standard deviation of 5-6 tolerance scales
(alpha2, about 0.1 rad), inside the 10 the estimate keeps (identifiability.STD_FACTOR). The
noise then puts alpha2 at 17-18 scales in seeds 1 and 2, and the fit exited 3 (NOT A
CALIBRATION: "the nominal model is wrong"), though the values agree with the truth within their
standard deviations: a value beyond FAR_SCALES is a wrong model only when it lies beyond it by
more than its noise (failures.FAR_SIGMAS).
"""

import numpy as np
import pytest

from laser_calib.estimation.estimate import EstimateOptions, estimate
from laser_calib.estimation.failures import first_failure
from laser_calib.estimation.lm import levenberg_marquardt
from laser_calib.estimation.problem import Problem, residuals_at
from laser_calib.measurement.base import NoiseModel
from laser_calib.measurement.spot import SpotModel
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


def _calibrated(arm: dict, seed: int, options: EstimateOptions = EstimateOptions()):
    """The robot of ``arm``, its session (seed) with random errors, the case-2 calibration poses
    (30 + 30) and their estimate with ``options`` (default: those `laser-calib estimate` has)."""
    robot = robot_from_dict(arm, arm["name"])
    session = robot_session(robot, seed, 30, random_errors=True)
    cal = session.samples.subset(session.cases["case2"][0])
    return robot, session, cal, estimate(robot, cal, options)


def _assert_own_errors_agree(est, session) -> None:
    """Every determined error that carries no held one within Z_MAX of its std of the true error."""
    carriers = set(est.identifiability.carried)
    own = [i for i, name in enumerate(est.names) if np.isfinite(est.errors[i]) and name not in carriers]
    z = (est.errors[own] - session.errors[own]) / est.std[own]
    assert np.abs(z).max() < Z_MAX, dict(zip(np.array(est.names)[own], np.round(z, 2)))

# Seed 0, arms 9 and 23: spots of both lasers at every calibration pose.
# Arm 9 (revolute, nearly still, revolute; its wrist 160 deg of twist): the sigma trial, holding
# nothing, moved theta2 and theta3 by +-45 tolerance scales along a weak pair; the noise threshold
# then held theta3, the fit started with theta2 still there and lost all 60 spots. Arm 23 (two
# parallel axes, a still joint, two more parallel): theta3 -18 and theta4 +17 scales, theta4 held,
# 100 iterations wandering the laser module's angles to 150 scales (NOT CONVERGED).
START_ARMS = {
    "random_0_9": ({
        "name": "random_0_9",
        "joints": [
            {"a": -0.8837717603, "d": 0.0802119169, "alpha": -1.5707963268, "theta0": 3.1415926536,
             "min": -1.4527552496, "max": 0.0316023239},
            {"a": -0.4599468674, "d": 0.0, "alpha": 1.5707963268, "theta0": -2.5181682106,
             "min": 0.0005936859, "max": 0.0098462117},
            {"a": 0.0, "d": 0.0, "alpha": 2.7993598391, "theta0": 1.8423630796, "min": -3.1415926536,
             "max": 3.1415926536},
        ],
        "slm": {"a": -0.0172543374, "d": 0.0559918717, "alpha": 1.9819829024, "theta": 2.826035503, "beta": 0.0},
        "lasers": [{"gamma": -0.5235987756, "beta": 0.0}, {"gamma": 0.5235987756, "beta": 0.0}],
    }, 3),
    "random_0_23": ({
        "name": "random_0_23",
        "joints": [
            {"a": -0.6098022183, "d": 0.3415752506, "alpha": 0.0, "theta0": -1.5707963268,
             "min": -0.9555755707, "max": 3.3922492505},
            {"a": 0.0, "d": -0.1604225689, "alpha": 0.0, "theta0": -1.5707963268, "min": -4.06488556,
             "max": 0.0093749936},
            {"a": 0.0, "d": 0.0435929887, "alpha": 1.5707963268, "theta0": 3.1415926536, "min": -0.0076739032,
             "max": 0.0083466171},
            {"a": -0.194047783, "d": -0.1488073344, "alpha": 0.0, "theta0": 3.1415926536, "min": -0.6147867211,
             "max": 0.2256619231},
            {"a": 0.0968647348, "d": 0.0367444247, "alpha": 0.0, "theta0": 2.5320497533, "min": -0.9120369157,
             "max": 0.6330104734},
        ],
        "slm": {"a": -0.03, "d": 0.0218443453, "alpha": -1.1751098239, "theta": 2.845012032, "beta": 0.6361760873},
        "lasers": [{"gamma": -0.5235987756, "beta": 0.0}, {"gamma": 0.5235987756, "beta": 0.0}],
    }, 2),
}


@pytest.mark.parametrize("seed", [1, 2])
def test_weak_direction_beyond_far_scales_by_noise_is_a_calibration(seed):
    _, session, _, est = _calibrated(ARM, seed)
    assert first_failure(est.warnings) is None, est.warnings
    alpha2 = est.names.index("alpha2")
    assert abs(est.errors[alpha2]) / np.deg2rad(1.0) > 10.0, "the case this test is about: alpha2 beyond FAR_SCALES"
    _assert_own_errors_agree(est, session)


@pytest.mark.parametrize("arm", sorted(START_ARMS))
def test_fit_holding_more_than_the_sigma_trial_starts_from_nominal(arm):
    """The spot sigma is estimated by a trial fit that holds only what the data cannot see at all;
    the noise threshold then holds more. The trial's minimum is no start for the fit without those:
    its kept values carry what the trial moved the held ones by. Started from nominal, the fit
    reaches the minimum a start at the truth reaches (the held ones at nominal, same free set and
    sigma; the costs agree to LM's convergence: arm 23's old fit stopped at 67.2, not 51.3), fits
    every measured spot, and the errors that carry no held one agree with the truth (Z_MAX)."""
    robot, session, cal, est = _calibrated(*START_ARMS[arm])
    assert first_failure(est.warnings) is None, est.warnings
    measured = int(residuals_at(SpotModel(robot, cal), np.zeros(len(est.names))).valid.sum())
    assert est.fit.n_values == 2 * measured == 120
    free = est.identifiable
    problem = Problem(SpotModel(robot, cal), NoiseModel(est.sigma, 0.0), free)
    from_truth = levenberg_marquardt(problem, np.where(free, session.errors, 0.0))
    assert from_truth.converged and from_truth.n_values == 120
    assert est.fit.cost == pytest.approx(from_truth.cost, abs=1e-6)   # LM stops within 1e-4 std: 5e-9
    _assert_own_errors_agree(est, session)


# Seed 1, arm 0: a nearly still third joint (0.23 deg of travel)
ARM_STILL_THIRD_JOINT = {
    "name": "random_1_0",
    "joints": [
        {"a": -1.0949234862, "d": 0.0648419744, "alpha": -1.182297856, "theta0": 3.1415926536,
         "min": -0.3830511793, "max": 2.1061439702},
        {"a": -0.23340832, "d": -0.1891363403, "alpha": -1.5707963268, "theta0": 0.0,
         "min": 0.2272381595, "max": 3.1828110828},
        {"a": -0.1422988599, "d": 0.0, "alpha": 1.4123968531, "theta0": 0.1009619006,
         "min": -0.0014373576, "max": 0.0026482234},
        {"a": 0.2661526067, "d": 0.0, "alpha": -1.5707963268, "theta0": 3.1415926536,
         "min": -3.1415926536, "max": 3.1415926536},
    ],
    "slm": {"a": 0.05, "d": 0.0711529222, "alpha": -0.4441353317, "theta": -1.5073521915, "beta": 1.5066482894},
    "lasers": [{"gamma": -0.5235987756, "beta": 0.0}, {"gamma": 0.5235987756, "beta": 0.0}],
}


def test_the_largest_carrier_is_held_not_amplified():
    """The still third joint leaves five directions the data cannot see. Held in the robot's order
    (d4 among them), a3 and a4 carried their combinations with summed coefficients of 84: both came
    out at 33 tolerance scales, and the fit exited 3 (NOT A CALIBRATION) until their bound grew
    with that sum. The largest carrier is held instead (identifiability.AMPLIFY): a4, not d4, and no
    kept value carries more than about one held error per combination; the errors that carry no
    held one agree with the truth (Z_MAX)."""
    _, session, _, est = _calibrated(ARM_STILL_THIRD_JOINT, 1)
    assert first_failure(est.warnings) is None, est.warnings
    held = [name for name, kept in zip(est.names, est.identifiable) if not kept]
    assert held == ["a4", "alpha4", "theta4", "slm_z", "slm_rz"]
    assert est.identifiability.carry.max() < 1.5
    _assert_own_errors_agree(est, session)


def test_a_value_carrying_held_errors_is_judged_with_them():
    """Held in the robot's order (amplify None, as the sensor fit holds what its frames carry), the
    still third joint's a3 and a4 carry the five held errors' combinations with summed coefficients
    of 84 (Identifiability.carry), both at 33 tolerance scales, and the fit exited 3 (NOT A
    CALIBRATION) though a4's combination in the truth is at 37: a carried value's bound is
    FAR_SCALES (1 + carry). The errors that carry no held one agree with the truth (Z_MAX)."""
    _, session, _, est = _calibrated(ARM_STILL_THIRD_JOINT, 1, EstimateOptions(amplify=None))
    assert first_failure(est.warnings) is None, est.warnings
    a4 = est.names.index("a4")
    assert abs(est.errors[a4]) > 10 * 0.010 and est.identifiability.carry[a4] > 10, "the case this test is about"
    _assert_own_errors_agree(est, session)


# Seed 0, arm 7: the laser module's rz is a first-order combination of theta6 and slm_ry, each
# at about 5 times its weight (the module's alpha 79 deg, not 90).
ARM_AMPLIFIED_RZ = {
    "name": "random_0_7",
    "joints": [
        {"a": -0.3675336577, "d": 0.0304517448, "alpha": 0.0, "theta0": 1.5707963268,
         "min": -1.3038730802, "max": -0.0053460599},
        {"a": -0.0688322509, "d": -0.0559761335, "alpha": 1.5707963268, "theta0": 2.7501224356,
         "min": 0.0481333199, "max": 0.6526119258},
        {"a": -0.0428863657, "d": 0.0, "alpha": -1.5707963268, "theta0": 3.1415926536,
         "min": -1.2249934428, "max": 0.2181047152},
        {"a": 0.0849265103, "d": -0.0652435503, "alpha": 0.8716489352, "theta0": 1.5707963268,
         "min": -1.8163964379, "max": 1.7942972118},
        {"a": 0.0616467552, "d": -0.0104281413, "alpha": -1.5707963268, "theta0": 3.1415926536,
         "min": -0.0635962503, "max": 0.52202514},
        {"a": 0.0861922056, "d": 0.0, "alpha": 1.5707963268, "theta0": -1.3727379007,
         "min": -0.7982251983, "max": 0.6027616632},
    ],
    "slm": {"a": 0.0, "d": 0.0579106783, "alpha": 1.3828753987, "theta": 2.4419100331, "beta": 0.0},
    "lasers": [{"gamma": -0.5235987756, "beta": 0.0}, {"gamma": 0.5235987756, "beta": 0.0}],
}


def test_effect_free_data_is_explained_when_a_combination_would_amplify():
    """Effect-free data (geometric errors and noise only, both sigmas given). Held in the robot's
    order, slm_rz (true -0.68 deg) was carried by theta6 and slm_ry at 5.4 times its size: 3.7 deg
    each, where the kinematics is not linear, and the fit missed second-order structure a correct
    model does not leave: chi^2 fell only 4 below its value at the true errors, where fitting 27
    parameters takes about 27 off. The diagnosis said "structure remains" (d6 varies with q6,
    varying-coefficient p = 0.0015 after Bonferroni). Holding theta6 instead, the fit takes what a
    linear model takes (27 +- 2 sqrt(27)) and the verdict is "explained"."""
    from laser_calib.diagnosis.engine import diagnose
    from laser_calib.diagnosis.options import DiagnoseOptions
    from laser_calib.effects.effect_model import EffectModel
    from laser_calib.measurement.base import whiten
    from laser_calib.sim.effect_truth import effect_session
    from laser_calib.sim.simulation import NoiseSpec

    robot = robot_from_dict(ARM_AMPLIFIED_RZ, ARM_AMPLIFIED_RZ["name"])
    noise = NoiseSpec(spot=0.5e-3, joint=float(np.deg2rad(0.02)))   # the effects bench's
    session = effect_session(robot, 1, lambda *_: [], 80, 80, noise, 10.0)
    diagnosis = diagnose(session.nominal, session.cal, session.test, spot_sigma=noise.spot_sigma,
                         joint_sigma=noise.joint_sigma, options=DiagnoseOptions(nested=False))
    held = [name for name, kept in zip(diagnosis.final.model.names, diagnosis.final.estimate.identifiable) if not kept]
    assert "theta6" in held and "slm_rz" not in held, held
    model = EffectModel(SpotModel(robot, session.cal), [])
    chi2 = []
    for x in (session.errors, diagnosis.final.estimate.values):
        res = model.residuals(np.asarray(x, float), True)
        r, _ = whiten(res, NoiseModel(noise.spot_sigma, noise.joint_sigma).whitener(res))
        chi2.append(float(r @ r))
    n_free = int(np.sum(diagnosis.final.estimate.identifiable))
    assert abs(chi2[0] - chi2[1] - n_free) < 2 * np.sqrt(n_free), (chi2, n_free)
    assert diagnosis.verdict == "explained", diagnosis.evidence
