"""Prismatic joints (URDF and D-H): calibrated to their Cramer-Rao prediction.

A marker on the arm measured by a point sensor in known frames (sensor = base =
world, marker at the tip): the true errors lie in the parameters the data can
identify, the poses are fixed and each seed draws new noise. Pooled over the
seeds, the RMS distance of the calibrated model's marker to the true marker at
test poses is compared with the Cramer-Rao prediction

    RMS_CR = sqrt( mean_test tr(J_t Sigma J_t^T) ),  Sigma = sigma^2 (J_c^T J_c)^-1

(J_c, J_t the Jacobians of the identifiable parameters at the truth). The
pooled mean square is a mean of SEEDS x p chi-square terms (p ~ 16 identifiable
parameters here): its relative spread is sqrt(2 / (SEEDS p)) ~ 2.9 %, that of
the RMS half of it, ~1.4 %; 5 % is more than 3 of those.
"""

from pathlib import Path

import numpy as np
import pytest
import yaml

from laser_calib.estimation.estimate import EstimateOptions, estimate_model
from laser_calib.estimation.identifiability import analyse
from laser_calib.io.sensor_samples import SensorSamples
from laser_calib.measurement.base import NoiseModel, whiten
from laser_calib.measurement.frames import FRAMES, frame_names
from laser_calib.measurement.sensor import PointModel
from laser_calib.model.kinematics import forward, joint_columns, joint_jacobian
from laser_calib.model.robot_file import dump_robot, load_robot, robot_from_dict
from laser_calib.model.urdf import load_urdf_robot

DATA = Path(__file__).parent / "data"
SIGMA = 1e-4   # m per marker coordinate (a laser tracker)
SEEDS = 150
N_CAL, N_TEST = 40, 300


def _robot(kind):
    if kind == "urdf":
        return load_urdf_robot(DATA / "column_arm.urdf", "base_link", "marker")
    return load_robot(DATA / "dh_column.yaml")


def _samples(q, position):
    return SensorSamples(np.arange(len(q)), np.arange(len(q), dtype=float), q, position=position)


@pytest.mark.parametrize("kind", ["urdf", "dh"])
def test_prismatic_arm_is_calibrated_to_its_cramer_rao_prediction(kind):
    robot = _robot(kind)
    rng = np.random.default_rng(0)
    low, high = np.maximum(robot.q_min, -3.0), np.minimum(robot.q_max, 3.0)
    q_cal, q_test = rng.uniform(low, high, (N_CAL, robot.n_joints)), rng.uniform(low, high, (N_TEST, robot.n_joints))
    model = PointModel(robot, _samples(q_cal, np.zeros((N_CAL, 3))))
    frames = {n for frame in FRAMES for n in frame_names(frame)}
    held = np.array([name in frames for name in model.names])
    res = model.residuals(np.zeros(len(model.names)))
    _, jac = whiten(res, NoiseModel(SIGMA).whitener(res))
    free = analyse(jac, model.scales, model.names, held).free
    truth = np.where(free, rng.uniform(-1, 1, len(model.names)) * model.scales, 0.0)

    cal = model.residuals(truth, True)
    test_model = PointModel(robot, _samples(q_test, np.zeros((N_TEST, 3))))
    test = test_model.residuals(truth, True)
    j_cal = cal.jac[:, 0][..., free].reshape(-1, free.sum())
    covariance = SIGMA ** 2 * np.linalg.inv(j_cal.T @ j_cal)
    j_test = test.jac[:, 0][..., free]
    crb = np.sqrt(np.einsum("pin,nm,pim->p", j_test, covariance, j_test).mean())

    options = EstimateOptions(spot_sigma=SIGMA, fixed=tuple(n for n, h in zip(model.names, held) if h))
    true_test = PointModel(robot, _samples(q_test, test.predicted[:, 0]))
    squares = []
    for seed in range(SEEDS):
        noise = np.random.default_rng(100 + seed).normal(0, SIGMA, (N_CAL, 3))
        est = estimate_model(PointModel(robot, _samples(q_cal, cal.predicted[:, 0] + noise)), options)
        assert np.array_equal(est.identifiable, free)
        squares.append(np.mean(np.sum(true_test.residuals(est.values, False).r[:, 0] ** 2, axis=1)))
    ratio = np.sqrt(np.mean(squares)) / crb
    assert abs(ratio - 1) < 0.05, f"test RMS / Cramer-Rao = {ratio:.4f}"


def test_dh_prismatic_joint_moves_d_and_round_trips():
    robot = _robot("dh")
    assert list(joint_columns(robot)) == [3, 5, 11, 15]  # theta1, d2, theta3, theta4
    assert robot.n_params == 16 and robot.slm is None  # no lasers: no SLM parameters
    q = np.zeros((1, 4))
    lifted = q.copy()
    lifted[0, 1] = 0.25
    a, b = forward(robot, q), forward(robot, lifted)
    # lifting moves the marker by 0.25 m along joint 2's z, and turns nothing
    assert np.isclose(np.linalg.norm(b.origin - a.origin), 0.25)
    assert np.allclose(b.rotation, a.rotation)
    state = forward(robot, q, twists=True)
    assert np.allclose(joint_jacobian(robot, state.twists)[0, :3, 1], state.joint_axis[0, 1])
    again = robot_from_dict(yaml.safe_load(dump_robot(robot)))
    assert [j.prismatic for j in again.joints] == [False, True, False, False]


@pytest.mark.parametrize("kind", ["urdf", "dh"])
def test_a_prismatic_reading_in_millimetres_is_one_line_in_metres(kind):
    """The column's lift read in mm (a URDF's or a robot file's prismatic joint): the line gives
    the reading in m and says it looks like millimetres, not the degrees of a revolute joint."""
    from laser_calib.io.errors import InputError
    from laser_calib.io.samples import check_joint_range

    robot = _robot(kind)
    lift = {"urdf": 0, "dh": 1}[kind]   # the column: the URDF's first joint, the D-H file's second
    assert robot.prismatic.tolist() == [i == lift for i in range(4)]
    q = np.tile((robot.q_min + robot.q_max) / 2, (3, 1))
    q[2, lift] = 450.0   # 0.45 m
    with pytest.raises(InputError, match=rf"s\.csv: pose 2, field q{lift + 1}.*: 450 m outside the joint range "
                                         r"\[0, 0\.[68]\] .*\(a prismatic joint's readings are in metres; this looks "
                                         "like millimetres"):
        check_joint_range(q, robot, "s.csv", np.arange(3))
