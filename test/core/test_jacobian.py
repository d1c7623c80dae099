"""The analytic measurement Jacobian (eq. 5-12) against central finite differences."""

from dataclasses import replace

import numpy as np
import pytest

from laser_calib.model.kinematics import joint_columns, predict
from laser_calib.sim.simulation import bundled_robot, sample_poses

STEP = 1e-6  # truncation error ~ STEP^2 * third derivative: far below 1e-6 relative


@pytest.mark.parametrize("case", ["paper-7dof", "paper-4dof"])
@pytest.mark.parametrize("convention", ["paper", "standard"])
def test_jacobian_matches_central_differences(case, convention):
    robot = replace(bundled_robot(case), convention=convention)
    rng = np.random.default_rng(7)
    errors = rng.normal(0, 0.005, robot.n_params)
    if convention == "paper":
        q = sample_poses([robot.with_errors(errors)], 25, rng)  # both beams on the screen
    else:  # the paper's arms in another convention rarely aim at the screen: any valid joint values
        q = rng.uniform(robot.q_min, robot.q_max, (25, robot.n_joints))
    analytic = predict(robot, q, errors, jacobian=True)
    ok = np.isfinite(analytic.k).all(axis=1) & (np.abs(analytic.k) < 50).all(axis=1)
    numeric = np.zeros_like(analytic.jacobian)
    for k in range(robot.n_params):
        step = np.zeros(robot.n_params)
        step[k] = STEP
        numeric[..., k] = (predict(robot, q, errors + step).spots - predict(robot, q, errors - step).spots) / (2 * STEP)
    diff = np.abs(analytic.jacobian[ok] - numeric[ok]).max()
    assert ok.sum() >= 10
    assert diff / np.abs(numeric[ok]).max() < 1e-6


def test_joint_jacobian_is_the_theta_columns():
    robot = bundled_robot("paper-7dof")
    rng = np.random.default_rng(3)
    q = sample_poses([robot], 10, rng)
    jac = predict(robot, q, jacobian=True).jacobian[..., joint_columns(robot)]
    for i in range(robot.n_joints):
        dq = np.zeros_like(q)
        dq[:, i] = STEP
        numeric = (predict(robot, q + dq).spots - predict(robot, q - dq).spots) / (2 * STEP)
        assert np.allclose(jac[..., i], numeric, rtol=1e-6, atol=1e-9)


def test_link_block_has_the_papers_shape():
    """Jac_1 is 6 x (4N+5): a 6x4 block per link and a 6x5 SLM block; no error of
    a link moves the laser by more than its lever arm allows (a sanity bound)."""
    from laser_calib.model.kinematics import forward
    robot = bundled_robot("paper-7dof")
    state = forward(robot, np.zeros((1, robot.n_joints)), twists=True)
    assert state.twists.shape == (1, 6, 4 * 7 + 5)
    # translation errors (a_i, d_i, slm_x, slm_z) cause no rotation
    lengths = [4 * i for i in range(7)] + [4 * i + 1 for i in range(7)] + [28, 29]
    assert np.allclose(state.twists[0, 3:, lengths], 0)
    # rotation errors rotate about a unit axis
    angles = [4 * i + 2 for i in range(7)] + [4 * i + 3 for i in range(7)] + [30, 31, 32]
    assert np.allclose(np.linalg.norm(state.twists[0, 3:, angles], axis=1), 1)
