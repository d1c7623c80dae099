"""A tree (two arms on one torso, each with a marker) and a coupled (mimic)
torso joint, calibrated from a point sensor with one unknown sensor frame.

The bound: a least-squares fit of p identifiable parameters from M values of
noise sigma predicts new poses drawn like the calibration poses with a mean
square error of sigma^2 p / M per value, so the RMS marker distance (3 values)
is about sigma sqrt(3 p / M). One draw of it spreads by ~sqrt(2 / p) / 2 (~10 %
for p ~ 45): 1.5 times the bound is far outside the spread, and a model that
misses a shared or coupled joint is off by millimetres. The true errors (1 mm,
0.1 deg) keep second-order terms (~2e-6 m) far below sigma.
"""

from pathlib import Path

import numpy as np
import pytest

from laser_calib.estimation.estimate import EstimateOptions
from laser_calib.estimation.sensor_fit import SensorFitOptions, calibrate, make_model
from laser_calib.io.sensor_samples import SensorSamples
from laser_calib.measurement.sensor import PointModel
from laser_calib.model.kinematics import forward
from laser_calib.model.urdf import load_urdf_robot, robot_from_urdf

DATA = Path(__file__).parent / "data"
SIGMA = 1e-4
TORSO = DATA / "torso_two_arms.urdf"


def _samples(robot, q, tips, position=None):
    n = len(q)
    extra = {} if tips is None else {"tip": tips.astype(float)}
    return SensorSamples(np.arange(n), np.arange(n, dtype=float), q, extra=extra,
                         position=np.zeros((n, 3)) if position is None else position)


def _calibrate_and_test(robot, tips_cal, tips_test, seed=0):
    """Test RMS marker distance to the truth, and the bound sigma sqrt(3 p / M)."""
    rng = np.random.default_rng(seed)
    low, high = robot.q_min, robot.q_max
    q_cal = rng.uniform(low, high, (len(tips_cal), robot.n_joints))
    q_test = rng.uniform(low, high, (len(tips_test), robot.n_joints))
    model = PointModel(robot, _samples(robot, q_cal, tips_cal))
    truth = rng.normal(0, 0.1, len(model.names)) * model.scales
    held = tuple(n for n in model.names if n.startswith(("base_", "target")))
    truth[[model.names.index(n) for n in held]] = 0.0
    measured = model.residuals(truth, False).predicted[:, 0] + rng.normal(0, SIGMA, (len(q_cal), 3))
    options = SensorFitOptions(estimate=EstimateOptions(spot_sigma=SIGMA, fixed=held))
    fit = calibrate(robot, _samples(robot, q_cal, tips_cal, measured), options)
    true_test = make_model(robot, _samples(robot, q_test, tips_test)).residuals(truth, False).predicted[:, 0]
    test = make_model(robot, _samples(robot, q_test, tips_test, true_test))
    error = np.sqrt(np.mean(np.sum(test.residuals(fit.estimate.values, False).r[:, 0] ** 2, axis=1)))
    p = int(fit.estimate.identifiable.sum())
    return error, SIGMA * np.sqrt(3 * p / (3 * len(q_cal))), fit


def test_two_arms_on_one_torso_are_calibrated_jointly():
    robot = load_urdf_robot(TORSO, "base_link", ["left_tool", "right_tool"])
    assert robot.n_joints == 8 and robot.n_params == 9 * 7  # the torso's joints counted once
    tips = np.arange(160) % 2
    error, bound, fit = _calibrate_and_test(robot, tips, np.arange(200) % 2)
    assert error < 1.5 * bound
    names = fit.model.names
    assert "target2_x" in names and names.count("torso_yaw.offset") == 1
    # a left-arm pose moves no right-arm parameter, both move the torso's
    res = fit.model.residuals(fit.estimate.values, True)
    left, right = tips == 0, tips == 1
    right_arm = [i for i, n in enumerate(names) if n.startswith("right_")]
    torso = names.index("torso_pitch_1.x")
    assert np.all(res.jac[left][..., right_arm] == 0)
    assert np.abs(res.jac[left][..., torso]).max() > 0 and np.abs(res.jac[right][..., torso]).max() > 0


def test_a_coupled_torso_joint_is_calibrated_through_its_source():
    robot = load_urdf_robot(TORSO, "base_link", "left_tool")
    assert robot.chain.readings == ("torso_yaw", "torso_pitch_1", "left_shoulder", "left_elbow", "left_wrist")
    mimic = robot.chain.joints[2]
    assert (mimic.name, mimic.coupled, mimic.multiplier, mimic.mimic_offset) == ("torso_pitch_2", True, -0.8, 0.1)
    error, bound, _ = _calibrate_and_test(robot, np.zeros(80), np.zeros(200))  # tip column of one tip: all 0
    assert error < 1.5 * bound


def test_a_tree_needs_the_tip_column():
    robot = load_urdf_robot(TORSO, "base_link", ["left_tool", "right_tool"])
    q = np.zeros((3, robot.n_joints))
    with pytest.raises(ValueError, match="need a 'tip' column"):
        PointModel(robot, _samples(robot, q, None))
    with pytest.raises(ValueError, match="tip 2 is not one of 0..1"):
        PointModel(robot, _samples(robot, q, np.array([0, 1, 2])))


def test_a_mimic_source_off_the_way_is_read_for_its_mimic_joint():
    """From torso_2 down, torso_pitch_2 is on the way but its source torso_pitch_1
    is above the base: its reading is the last column of q, with no parameters."""
    robot = robot_from_urdf(TORSO.read_text(), "torso_2", "left_tool")
    assert robot.joint_names[-1] == "torso_pitch_1"
    assert not any(name.startswith("torso_pitch_1.") for name in robot.param_names)
    q = np.zeros((2, robot.n_joints))
    q[1, -1] = 0.2
    rotation = forward(robot, q).rotation
    angle = np.degrees(np.arccos((np.trace(rotation[1] @ rotation[0].T) - 1) / 2))
    assert angle == pytest.approx(np.degrees(0.8 * 0.2))  # torso_pitch_2 = -0.8 q_torso_pitch_1 + 0.1
