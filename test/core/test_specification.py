"""The specification test (diagnosis.specification) on linear models whose truth is known:
its p-values are uniform when the form is right, it names the parameter and the
covariate when one varies, and it does not depend on the noise level."""

import numpy as np
from scipy import stats

from laser_calib.diagnosis.specification import (FREE, SMOOTH, covariate_table, legendre, load_table,
                                                   specification_tests)
from laser_calib.measurement.base import NoiseModel, Residuals

N_POSES, VALUES, N_PARAMS, N_JOINTS = 80, 4, 6, 3
SIGMA = 1e-3
NAMES = tuple(f"x{k + 1}" for k in range(N_PARAMS))


def linear_case(seed: int, varying: tuple[int, int, float] | None = None):
    """Residuals of a least-squares fit of a random linear model (P poses of 2x2
    values, n parameters) to noise of SIGMA, plus optionally parameter k varying
    as amplitude * u with covariate c (varying = (k, c, amplitude in SIGMA)); the
    covariates are the joint readings q (P,N) and the stamp."""
    rng = np.random.default_rng(seed)
    jac = rng.normal(size=(N_POSES, 2, 2, N_PARAMS))
    q = rng.uniform(-2, 2, size=(N_POSES, N_JOINTS))
    stamp = 10.0 * np.arange(N_POSES)
    r = SIGMA * rng.normal(size=(N_POSES, 2, 2))
    if varying is not None:
        k, c, amplitude = varying
        r += amplitude * SIGMA * jac[..., k] * legendre(q[:, c])[:, 0, None, None]
    flat_j, flat_r = jac.reshape(-1, N_PARAMS), r.ravel()
    r = (flat_r - flat_j @ np.linalg.lstsq(flat_j, flat_r, rcond=None)[0]).reshape(r.shape)
    res = Residuals(r, np.ones((N_POSES, 2), bool), jac, np.zeros((N_POSES, 2, 2, N_JOINTS)), np.zeros_like(r))
    return res, covariate_table(q, stamp, {})


def run(res, covariates, sigma=SIGMA):
    return specification_tests(NAMES, np.ones(N_PARAMS, bool), res, NoiseModel(sigma, 0.0), covariates)


def test_p_values_are_uniform_when_the_form_is_right():
    # One fixed pair over 200 independent data sets: its p-value is uniform under the null.
    p = [next(v.p for v in run(*linear_case(seed)) if (v.parameter, v.covariate) == ("x1", "q1"))
         for seed in range(200)]
    assert stats.kstest(p, "uniform").pvalue > 0.01


def test_family_rate_of_false_alarms_is_at_most_alpha():
    # Bonferroni bounds the family rate by 1 %: over 200 data sets, false alarms are at most
    # what a binomial(200, 0.01) exceeds with probability 0.001.
    alarms = sum(run(*linear_case(seed))[0].p_adjusted < 0.01 for seed in range(200))
    assert alarms <= stats.binom.ppf(0.999, 200, 0.01)


def test_a_varying_parameter_is_named_with_its_covariate():
    # x3 varying by +-1 sigma-per-unit-column with q2: a chi^2 excess of about P*4/3 = 107.
    found = run(*linear_case(5, (2, 1, 1.0)))
    assert found[0].p_adjusted < 0.01
    assert (found[0].parameter, found[0].covariate) == ("x3", "q2")
    assert "x3 varies with q2" in found[0].sentence()


def test_the_test_does_not_depend_on_the_noise_level():
    res, covariates = linear_case(3, (0, 2, 0.5))
    stated, misstated = run(res, covariates), run(res, covariates, sigma=4 * SIGMA)
    assert [(v.parameter, v.covariate) for v in stated] == [(v.parameter, v.covariate) for v in misstated]
    np.testing.assert_allclose([v.f for v in stated], [v.f for v in misstated], rtol=1e-9)


def test_constant_covariates_are_left_out():
    q = np.zeros((10, 2))
    q[:, 1] = np.linspace(0, 1, 10)
    assert [name for name, _ in covariate_table(q, np.zeros(10), {"temperature_c": np.full(10, 20.0)})] == ["q2"]


def test_the_added_effects_share_half_of_the_family_rate():
    # The last column as an added effect: its pairs share alpha/2, the geometric pairs the other half.
    res, covariates = linear_case(7, (N_PARAMS - 1, 0, 0.6))
    found = specification_tests(NAMES, np.ones(N_PARAMS, bool), res, NoiseModel(SIGMA, 0.0), covariates,
                                n_geometric=N_PARAMS - 1)
    n_effect = sum(v.parameter == NAMES[-1] for v in found)
    assert n_effect == len(covariates)
    for v in found:
        share = n_effect if v.parameter == NAMES[-1] else len(found) - n_effect
        assert v.p_adjusted == min(1.0, 2 * share * v.p)
    assert (found[0].parameter, found[0].covariate) == (NAMES[-1], "q1")


def test_a_parameter_following_a_gravity_torque_is_named():
    # x2 varying with the load of joint 3 (a link bending under it): the torques are covariates too.
    res, _ = linear_case(9)
    rng = np.random.default_rng(9)
    q = rng.uniform(-2, 2, size=(N_POSES, N_JOINTS))
    torques = np.cos(q) + rng.normal(scale=0.1, size=q.shape)
    res = Residuals(res.r + 1.0 * SIGMA * res.jac[..., 1] * legendre(torques[:, 2])[:, 0, None, None], res.valid,
                    res.jac, res.jac_q, res.r)
    loads = load_table(torques)
    assert [name for name, _ in loads] == ["torque1", "torque2", "torque3"]
    found = specification_tests(NAMES, np.ones(N_PARAMS, bool), res, NoiseModel(SIGMA, 0.0),
                                covariate_table(q, 10.0 * np.arange(N_POSES), {}), N_PARAMS - 1, loads)
    assert found[0].p_adjusted < 0.01
    assert (found[0].parameter, found[0].covariate) == ("x2", "torque3")
    # The added effect's column (the last) is not tested against the loads.
    assert not any(v.parameter == NAMES[-1] and v.covariate.startswith("torque") for v in found)
    assert any(v.parameter == NAMES[-1] and v.covariate == "q1" for v in found)


def test_every_column_is_tested_against_a_free_shape_of_a_drifts_covariate():
    # x2 steps by 1.5 sigma-per-unit-column three quarters through the session, while the model's
    # drift (the last column) follows the stamp: the step is found as x2 varying with the stamp in a
    # shape of its own, where the smooth (degree 1, 2) test of the same pair sees less of it.
    res, covariates = linear_case(11)
    stamp = dict(covariates)["stamp"]
    step = np.where(stamp > 0.75 * stamp.max(), 1.0, 0.0)
    res = Residuals(res.r + 1.5 * SIGMA * res.jac[..., 1] * (step - step.mean())[:, None, None], res.valid,
                    res.jac, res.jac_q, res.r)
    found = specification_tests(NAMES, np.ones(N_PARAMS, bool), res, NoiseModel(SIGMA, 0.0), covariates,
                                N_PARAMS - 1, drifts=("stamp",))
    assert (found[0].parameter, found[0].covariate, found[0].shape) == ("x2", "stamp", FREE)
    assert found[0].p_adjusted < 0.01 and "beyond a linear drift" in found[0].sentence()
    smooth = next(v for v in found if (v.parameter, v.covariate, v.shape) == ("x2", "stamp", SMOOTH))
    assert smooth.p > found[0].p
    # Three families, an equal share each: the free shapes (every column), the added effect's, the geometric.
    sizes = {"free": N_PARAMS, "effect": len(covariates), "geometric": len(found) - N_PARAMS - len(covariates)}
    for v in found:
        kind = "free" if v.shape == FREE else "effect" if v.parameter == NAMES[-1] else "geometric"
        assert v.p_adjusted == min(1.0, 3 * sizes[kind] * v.p)


def test_family_rate_with_a_drift_is_at_most_alpha():
    alarms = sum(specification_tests(NAMES, np.ones(N_PARAMS, bool), res, NoiseModel(SIGMA, 0.0), covariates,
                                     N_PARAMS - 1, drifts=("stamp",))[0].p_adjusted < 0.01
                 for res, covariates in (linear_case(seed) for seed in range(200)))
    assert alarms <= stats.binom.ppf(0.999, 200, 0.01)


def test_blocks_of_poses_give_the_test_on_all_of_them():
    # The test keeps only sums over the values: fed block by block of poses it finds the same F values.
    # (the smooth shapes, and the free shape of a drift's covariate)
    res, covariates = linear_case(4, (1, 0, 0.7))
    whole = specification_tests(NAMES, np.ones(N_PARAMS, bool), res, NoiseModel(SIGMA, 0.0), covariates,
                                N_PARAMS - 1, drifts=("stamp",))
    edges = [0, 7, 30, 31, N_POSES]
    blocks = [(slice(a, b), Residuals(res.r[a:b], res.valid[a:b], res.jac[a:b], res.jac_q[a:b], res.predicted[a:b]))
              for a, b in zip(edges[:-1], edges[1:])]
    parts = specification_tests(NAMES, np.ones(N_PARAMS, bool), iter(blocks), NoiseModel(SIGMA, 0.0), covariates,
                                N_PARAMS - 1, drifts=("stamp",))
    assert any(v.shape == FREE for v in parts)
    assert ([(v.parameter, v.covariate, v.shape, v.dof) for v in whole]
            == [(v.parameter, v.covariate, v.shape, v.dof) for v in parts])
    np.testing.assert_allclose([v.f for v in parts], [v.f for v in whole], rtol=1e-9)


def test_a_fit_without_a_measured_value_has_nothing_to_test():
    """A wrong robot file's final fit can lose every measured value (every beam off the screen):
    no column is then tested, and no test is reported (numpy's 'zero-size array to reduction
    operation maximum' was `diagnose`'s one line, exit 2, and its files unwritten)."""
    res, covariates = linear_case(3)
    lost = Residuals(np.zeros_like(res.r), np.zeros_like(res.valid), np.zeros_like(res.jac), res.jac_q, res.predicted)
    assert run(lost, covariates) == []
    assert run(res, covariates)  # the same poses measured are tested
