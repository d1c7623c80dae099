"""LM and the paper's EKF: same minimum, estimates consistent with their covariance.

Tolerances come from the reported covariance: for an efficient, unbiased
estimator (x_hat - x)^T Sigma^-1 (x_hat - x) follows chi^2 with as many degrees
of freedom as free parameters; the bounds are its 99.9 % quantiles.
"""

import re
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import chi2

from laser_calib.estimation.estimate import EstimateOptions, estimate, prior_sigmas
from laser_calib.estimation.ekf import EkfOptions, information_update
from laser_calib.estimation.lm import LmOptions, levenberg_marquardt
from laser_calib.estimation.problem import Problem, whitened_factor
from laser_calib.measurement.base import NoiseModel, Residuals, whiten
from laser_calib.measurement.spot import SpotModel
from laser_calib.sim.simulation import NoiseSpec, measure, paper_session


def _options(session, **kw):
    return EstimateOptions(spot_sigma=session.noise.spot_sigma, joint_sigma=session.noise.joint_sigma, **kw)


def _mahalanobis(est, truth):
    free = est.identifiable
    delta = (est.errors - truth)[free]
    cov = est.fit.covariance[np.ix_(free, free)]
    return float(delta @ np.linalg.solve(cov, delta))


def _gauge_truth(session, est):
    """True errors in the estimate's gauge: a parameter held at nominal hands its
    value to the partner that carries the sum (the 4-DOF pairs d1+d2, d4+slm_z)."""
    truth = session.errors.copy()
    names = list(est.names)
    for fixed, text in est.identifiability.merged.items():
        partner = text.split("from ")[1].split(";")[0].split(", ")[0]
        truth[names.index(partner)] += truth[names.index(fixed)]
        truth[names.index(fixed)] = 0.0
    return truth


@pytest.mark.parametrize("case", ["paper-7dof", "paper-4dof"])
def test_lm_estimates_are_consistent_with_their_covariance(case):
    d2 = []
    for seed in range(8):
        session = paper_session(case, seed)
        est = estimate(session.nominal, session.samples, _options(session))
        # the 4-DOF arm's two sum-only pairs are one rank-deficiency line; nothing else
        assert est.fit.converged and all(w.startswith("rank deficient") for w in est.warnings)
        d2.append(_mahalanobis(est, _gauge_truth(session, est)))
        dof = int(est.identifiable.sum())
        assert d2[-1] < chi2.ppf(0.999, dof), (seed, d2[-1])
    # the mean of 8 chi^2_dof / dof has std sqrt(2 / dof / 8); allow 4 of them
    assert abs(np.mean(d2) / dof - 1) < 4 * np.sqrt(2 / dof / 8)


def test_ekf_reaches_the_lm_minimum():
    session = paper_session("paper-7dof", 11)
    cal = session.samples.subset(session.cases["case2"][0])
    lm = estimate(session.nominal, cal, _options(session))
    ekf = estimate(session.nominal, cal, _options(session, method="ekf", ekf=EkfOptions(r=None)))
    assert ekf.fit.converged
    # The EKF stops when its state changes by < 1e-7: far inside a tenth of a standard deviation.
    assert np.all(np.abs(ekf.errors - lm.errors) < 0.1 * lm.std)
    assert ekf.fit.cost == pytest.approx(lm.fit.cost, rel=1e-6)


@pytest.mark.parametrize("given", [{}, {"prior": True}, {"spot_sigma": None}, {"spot_sigma": None, "prior": True}])
def test_paper_ekf_settings_reach_the_lm_minimum(given):
    """Q = R = 1e-4 I, stop below 1e-7: the fixed point is LM's, with joint noise, with the prior
    and with the spot sigma estimated. R scales the whole noise model (ekf.filter_noise): R as
    the spot sigma alone (10 mm, the joint noise kept) was another weighting of the spots, and,
    with a prior, of the data against it; its point was LM's at a spot sigma of 10 mm."""
    session = paper_session("paper-4dof", 2)
    options = replace(_options(session), **given)
    est = estimate(session.nominal, session.samples, replace(options, method="ekf"))
    lm = estimate(session.nominal, session.samples, options)
    assert est.fit.converged and est.fit.iterations < 5000
    # Converging linearly, the last 1e-7 step leaves more than 1e-7 to go: compare in std units.
    assert np.all(np.abs(est.errors - lm.errors)[lm.identifiable] < 0.05 * lm.std[lm.identifiable])
    assert est.fit.chi2 == pytest.approx(lm.fit.chi2, rel=1e-3)


def test_prior_adds_its_information():
    """With the prior, the normal matrix at the same x gains diag(1 / tolerance^2)
    exactly, and no standard deviation grows."""
    session = paper_session("paper-7dof", 4)
    cal = session.samples.subset(session.cases["case1"][0])
    model = SpotModel(session.nominal, cal)
    options = _options(session, prior=True)
    sigma = prior_sigmas(model, 33, options)
    noise = NoiseModel(options.spot_sigma, options.joint_sigma)
    x = session.errors
    plain_normal = Problem(model, noise, np.ones(33, bool)).normal_equations(x)
    prior_normal = Problem(model, noise, np.ones(33, bool), sigma).normal_equations(x)
    gained = (prior_normal.information - plain_normal.information) / np.outer(model.scales, model.scales)
    tol = np.where(np.array(model.scales) == 0.010, 0.010, np.deg2rad(1.0))
    assert np.allclose(gained, np.diag(1 / tol ** 2), rtol=1e-9, atol=1e-6 / tol.min() ** 2)
    # the same free set in both (case 1 has a direction beyond the noise threshold)
    plain = estimate(session.nominal, cal, _options(session, std_factor=None))
    with_prior = estimate(session.nominal, cal, options)
    assert np.all(with_prior.std <= plain.std * 1.001)


def test_sigma_is_estimated_from_the_residual():
    noise = NoiseSpec(spot=0.002, joint=0.0)
    session = paper_session("paper-7dof", 5, noise=noise)
    est = estimate(session.nominal, session.samples, EstimateOptions())
    assert est.sigma_estimated
    # relative std of a sigma estimate with ~200 dof is ~1/sqrt(2*200) = 5 %: allow 3 of them
    assert est.sigma == pytest.approx(noise.spot_sigma, rel=0.15)



@pytest.mark.parametrize("spot_given", [False, True], ids=["neither given", "spot sigma given"])
@pytest.mark.parametrize("case", ["paper-7dof", "paper-4dof"])
def test_joint_noise_is_estimated_with_the_spot_sigma(case, spot_given):
    """Neither sigma given (the command line's and the nodes' default), or the spot sigma alone
    (its rated value; the joint one was then taken as 0, and a probe found 80 % of the 7-DOF errors
    within two of their stds, mean d^2 / dof 2.6): joint-reading noise moves
    a pose's spots by the length of its levers, and one spot sigma spread evenly over them made
    the standard deviations too small (0.5 mm spots, +-0.1 deg joints: mean d^2 / dof 4.0 on the
    7-DOF arm, 5.4 on the 4-DOF). Both components are estimated, and the errors are consistent
    with their covariance. The reference is the fit of the noise-free spots with the same
    parameters held: the 4-DOF arm's held d2 and slm_z are merged exactly only at its nominal
    angles, so against its true errors (_gauge_truth) a fit is off by a bias of its own (d^2 / dof
    4.4 with the sigmas given and no joint noise; 1.04 against this reference)."""
    noise = NoiseSpec(spot=0.0005, joint=np.deg2rad(0.1))
    d2 = []
    for seed in range(8):
        session = paper_session(case, seed, noise=noise)
        est = estimate(session.nominal, session.samples, EstimateOptions(
            spot_sigma=noise.spot_sigma if spot_given else None, joint_sigma=None))
        assert est.sigma_estimated != spot_given and est.joint_sigma_estimated, seed
        # ~100 to 120 values, about half of them carrying mostly joint noise: its sigma's relative
        # std is about 1 / sqrt(2 * 50) = 10 %; allow 3 of them
        assert est.joint_sigma == pytest.approx(noise.joint_sigma, rel=0.3), seed
        held = tuple(name for name, kept in zip(est.names, est.identifiable) if not kept)
        reference = estimate(session.nominal, session.truth, EstimateOptions(spot_sigma=1e-6, fixed=held,
                                                                             robust=False))
        d2.append(_mahalanobis(est, reference.fit.x))
    dof = int(est.identifiable.sum())
    # the mean of 8 chi^2_dof / dof has std sqrt(2 / dof / 8); allow 4 of them
    assert abs(np.mean(d2) / dof - 1) < 4 * np.sqrt(2 / dof / 8), np.mean(d2) / dof

def test_no_joint_noise_is_found_where_there_is_none():
    """The joint-reading noise is used only where the residual shows it (one-sided likelihood
    ratio, p < 0.05): of 16 sets without it, more than 3 would happen with probability 0.007."""
    noise = NoiseSpec(spot=0.0005, joint=0.0)
    found = 0
    for case in ("paper-7dof", "paper-4dof"):
        for seed in range(8):
            session = paper_session(case, seed, noise=noise)
            est = estimate(session.nominal, session.samples, EstimateOptions(joint_sigma=None))
            found += est.joint_sigma_estimated
            assert est.joint_sigma == 0.0 or est.joint_sigma_estimated
    assert found <= 3

def test_joint_noise_the_fit_takes_up_is_still_found():
    """A joint read wrong at one pose moves its spots as that joint's own errors do, so the fit
    takes up part of that noise and its residual shows less. The plain likelihood of the residual
    (scaled evenly for the values the fit took) missed 0.05 deg beside 1 mm spots in 8 of 16
    sessions (the UR10e's 0.058 deg in 6 of 7), and the standard deviations were too small; the
    restricted likelihood allows for what the fit took up (noise_components)."""
    noise = NoiseSpec(spot=0.001, joint=np.deg2rad(0.05))
    ratios = []
    for case in ("paper-7dof", "paper-4dof"):
        for seed in range(8):
            session = paper_session(case, seed, noise=noise)
            est = estimate(session.nominal, session.samples, EstimateOptions(joint_sigma=None))
            if est.joint_sigma_estimated:
                ratios.append(est.joint_sigma / noise.joint_sigma)
    # at p < 0.05 a set is missed by chance too; more than 2 of 16 is the test's weakness
    assert len(ratios) >= 14, ratios
    # each ratio's relative std is about 13 % (~50 values carrying the joint noise): 3 stds of the mean
    assert abs(np.mean(ratios) - 1) < 3 * 0.13 / np.sqrt(len(ratios)), ratios


def test_joint_noise_the_residual_cannot_rule_out_is_said():
    """Where the residual shows no joint-reading noise, the standard deviations assume none; the
    largest joint sigma it allows (95 %) is said, with how much larger the stds would be under it
    (joint_noise_bound.hidden). On this 4-DOF session with the paper's 0.058 deg the test found none,
    and the stds with the true sigmas given are 1.4 times the reported ones: the bound holds the
    truth and the factor said covers it."""
    session = paper_session("paper-4dof", 3)
    est = estimate(session.nominal, session.samples, EstimateOptions(joint_sigma=None))
    assert not est.joint_sigma_estimated
    [line] = [w for w in est.warnings if "no joint-reading noise shows in the residual" in w]
    bound, factor = (float(v) for v in re.search(r"up to (\S+) deg .* up to (\S+) times larger", line).groups())
    assert np.deg2rad(bound) >= session.noise.joint_sigma
    given = estimate(session.nominal, session.samples, EstimateOptions(spot_sigma=session.noise.spot_sigma,
                                                                      joint_sigma=session.noise.joint_sigma))
    kept = est.identifiable
    assert factor >= np.max(given.fit.std[kept] / est.fit.std[kept]) > 1.2


def test_a_joint_sigma_far_above_what_the_residual_allows_is_said():
    """0.02 typed for 0.02 deg is 1.1 deg of joint-reading noise: the fit weighs each pose by a noise
    its spots do not show (a probe's 0.5 rad left the calibration 53 mm off, exit 0). Said when
    over twice the largest the residual allows (95 %); the true sigma given is not."""
    session = paper_session("paper-7dof", 0)
    said = [w for w in estimate(session.nominal, session.samples, EstimateOptions(joint_sigma=0.02)).warnings
            if "the residual allows at most" in w]
    assert len(said) == 1 and "far below the joint sigma given, 0.02 rad (1.15 deg" in said[0], said
    true = estimate(session.nominal, session.samples, EstimateOptions(joint_sigma=session.noise.joint_sigma))
    assert not [w for w in true.warnings if "the residual allows at most" in w], true.warnings


def test_values_that_are_mostly_noise_are_said():
    """Kept by the identifiability rule (std under STD_FACTOR tolerance scales) but beyond WEAK_FACTOR:
    a joint moving +-0.01 rad wrote its neighbours' lengths with stds of 33-66 mm and no word (a new
    user's probe). The paper's arm at its noise has none."""
    session = paper_session("paper-7dof", 0)
    given = EstimateOptions(spot_sigma=session.noise.spot_sigma, joint_sigma=session.noise.joint_sigma)
    assert not [w for w in estimate(session.nominal, session.samples, given).warnings if "weakly" in w]
    narrow = session.samples.q.copy()
    narrow[:, 3] = -1.0 + 0.01 * np.sin(np.arange(len(narrow)))     # joint 4 barely moves
    samples, _ = measure(session.true, narrow, np.random.default_rng(1),
                         NoiseSpec(spot=session.noise.spot_sigma, joint=session.noise.joint_sigma))
    est = estimate(session.nominal, samples, given)
    [line] = [w for w in est.warnings if w.startswith("weakly determined: ")]
    named = re.findall(r"(\w+) \(std (\S+) tolerance scales\)", line)
    scales = dict(zip(est.names, est.fit.std / SpotModel(session.nominal, samples).scales))
    assert named and all(3 < float(ratio) <= 10 and abs(scales[name] - float(ratio)) < 0.05 * float(ratio)
                         for name, ratio in named), line


def test_large_corrections_the_data_barely_determine_are_a_caution_in_the_calibrated_files(tmp_path):
    """Poses within half a degree of one pose (a new user's probe): theta2 written +27 deg with a std
    of 11 deg, exit 0, the calibrated model 733 mm RMS off over the workspace where the nominal was
    142, and nothing in the files but the values. The warning names them, and the robot file's
    header says CAUTION, as for a calibration worse than nominal on its test poses; the paper's
    sessions at their noise get neither."""
    from laser_calib.cli.main import main
    from laser_calib.io.samples import save_samples
    from laser_calib.model.robot_file import dump_robot

    session = paper_session("paper-7dof", 0)
    given = EstimateOptions(spot_sigma=session.noise.spot_sigma, joint_sigma=session.noise.joint_sigma)
    assert not [w for w in estimate(session.nominal, session.samples, given).warnings if "barely" in w]
    rng = np.random.default_rng(21)
    centre = session.samples.q[7]
    q = centre + rng.uniform(-1, 1, (30, len(centre))) * np.deg2rad(0.5)
    samples, _ = measure(session.true, q, rng, NoiseSpec(spot=session.noise.spot_sigma,
                                                          joint=session.noise.joint_sigma))
    est = estimate(session.nominal, samples, given)
    [line] = [w for w in est.warnings if w.startswith("large corrections the data barely determine:")]
    named = re.findall(r"(\w+) at ([\d.]+) tolerance scales from nominal, std ([\d.]+)", line)
    assert named and all(float(size) > 3 and float(std) > 3 for _, size, std in named), line
    (tmp_path / "robot.yaml").write_text(dump_robot(session.nominal))
    save_samples(samples, tmp_path / "samples.csv")
    assert main(["estimate", "--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "samples.csv"),
                 "--spot-sigma", str(session.noise.spot_sigma), "--joint-sigma", str(session.noise.joint_sigma),
                 "--out", str(tmp_path / "out")]) == 0
    header = (tmp_path / "out" / "robot_calibrated.yaml").read_text().split("\n\n")[0]
    assert "# CAUTION: large corrections the data barely determine:" in header, header


def test_robust_rejects_a_wrong_detection():
    session = paper_session("paper-7dof", 6)
    spots = session.samples.spots.copy()
    spots[17, 1] += [0.03, -0.02]  # one spot 36 mm off: a reflection taken for the laser
    samples = replace(session.samples, spots=spots)
    plain = estimate(session.nominal, samples, _options(session, robust=False))
    robust = estimate(session.nominal, samples, _options(session, robust=True))
    assert robust.rejected == ((17, 1),)
    assert any("exceeds the noise model" in w for w in plain.warnings)
    assert _mahalanobis(robust, session.errors) < chi2.ppf(0.999, 33)
    assert _mahalanobis(plain, session.errors) > _mahalanobis(robust, session.errors)


def test_the_robust_rule_judges_again_with_the_joint_noise_it_did_not_know():
    """The robust rule runs before the noise is estimated, so without joint noise, and rejected clean
    spots on long levers for the scatter it gives them (0.5 mm spots, +-0.1 deg joints, 20 sessions of
    120 poses: 39 of 4800 spots on the 7-DOF arm, 54 on the 4-DOF; none with both sigmas given). With
    the joint noise the residual shows, it runs again: none here, and a wrong spot is still rejected."""
    noise = NoiseSpec(spot=0.0005, joint=np.deg2rad(0.1))
    for case in ("paper-7dof", "paper-4dof"):
        for seed in range(5):
            session = paper_session(case, seed, 60, noise=noise)
            est = estimate(session.nominal, session.samples, EstimateOptions(joint_sigma=None))
            assert est.joint_sigma_estimated and est.rejected == (), (case, seed, est.warnings)
    session = paper_session("paper-7dof", 6, noise=noise)
    spots = session.samples.spots.copy()
    spots[17, 1] += [0.03, -0.02]  # one spot 36 mm off: a reflection taken for the laser
    est = estimate(session.nominal, replace(session.samples, spots=spots), EstimateOptions(joint_sigma=None))
    assert est.rejected == ((17, 1),) and est.joint_sigma_estimated
    said = [w for w in est.warnings if w.startswith("robust:")]
    assert len(said) == 1 and "no joint-reading noise" not in said[0], est.warnings

def test_fixed_parameters_stay_nominal_and_are_reported_without_value():
    session = paper_session("paper-7dof", 8)
    est = estimate(session.nominal, session.samples, _options(session, fixed=("a1", "theta7")))
    names = list(est.names)
    for name in ("a1", "theta7"):
        assert np.isnan(est.errors[names.index(name)]) and not est.identifiable[names.index(name)]
        assert est.values[names.index(name)] == 0.0


def test_a_parameter_held_by_fix_is_carried_by_those_it_cannot_be_told_from():
    """The 4-DOF arm sees only d1 + d2: with d1 held by --fix, d2 is kept and its value is the sum.
    It was written with no note (a UR10e's wrist_3_joint.rz after --fix wrist_3_joint.offset, a new
    user's probe); it now carries d1's combination, as a kept value carries a merged one's."""
    session = paper_session("paper-4dof", 0)
    est = estimate(session.nominal, session.samples, _options(session, fixed=("d1",)))
    assert est.identifiable[list(est.names).index("d2")]
    assert est.identifiability.carried["d2"] == ("d1",)
    assert est.identifiability.carry[list(est.names).index("d2")] > 0


def test_normal_equations_by_blocks_equal_the_stacked_jacobian():
    """Blocks of 7 poses sum to the normal equations of the whole stack, and the
    QR factor has the stacked Jacobian's singular values."""
    session = paper_session("paper-7dof", 3)
    model = SpotModel(session.nominal, session.samples)
    noise = NoiseModel(session.noise.spot_sigma, session.noise.joint_sigma)
    free = np.ones(33, bool)
    free[5] = False
    x = session.errors * 0.5
    res = model.residuals(x, True)
    r, jac = whiten(res, noise.whitener(res))
    jac = jac[:, free] * model.scales[free]
    blocks = Problem(model, noise, free, chunk=7).normal_equations(x)
    scale = np.abs(jac.T @ jac).max()
    assert np.allclose(blocks.information, jac.T @ jac, rtol=1e-12, atol=1e-12 * scale)
    assert np.allclose(blocks.gradient, jac.T @ r, rtol=1e-12, atol=1e-12 * np.abs(jac.T @ r).max())
    assert blocks.cost == pytest.approx(0.5 * r @ r, rel=1e-12)
    assert blocks.n_values == 2 * int(res.valid.sum())
    factor, n_values = whitened_factor(model, noise, x, chunk=7)
    full = whiten(res, noise.whitener(res))[1]
    assert n_values == blocks.n_values
    assert np.allclose(np.linalg.svd(factor, compute_uv=False), np.linalg.svd(full, compute_uv=False),
                       rtol=1e-10)


class _Exponential:
    """One parameter, predicted = exp(x) at every pose: a Gauss-Newton step from
    x = 0 towards measured 1e10 overflows exp."""

    names = ("x",)
    scales = np.ones(1)

    def residuals(self, x, jacobian=True):
        predicted = np.full((4, 1, 1), np.exp(x[0]))
        jac = predicted[..., None] if jacobian else None
        return Residuals(1e10 - predicted, np.ones((4, 1), bool), jac, None, predicted)


def test_an_overflowing_trial_is_a_rejected_step_without_warning():
    problem = Problem(_Exponential(), NoiseModel(1.0), np.ones(1, bool))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = levenberg_marquardt(problem, np.zeros(1), LmOptions(max_iter=200))
    assert fit.converged and fit.x[0] == pytest.approx(np.log(1e10), rel=1e-9)


class _Undefined:
    """One parameter, predicted ``value`` (NaN, inf) at every x: a model evaluated where it is not
    defined, or overflowing."""

    names = ("x",)
    scales = np.ones(1)

    def __init__(self, value):
        self.value = value

    def residuals(self, x, jacobian=True):
        predicted = np.full((4, 1, 1), self.value)
        return Residuals(1.0 - predicted, np.ones((4, 1), bool), predicted[..., None] if jacobian else None,
                         None, predicted)


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_normal_equations_without_a_finite_step_are_a_breakdown_not_a_loop(value):
    problem = Problem(_Undefined(value), NoiseModel(1.0), np.ones(1, bool))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # inf - inf on the way: the breakdown is the test
        with pytest.raises(np.linalg.LinAlgError, match="no finite damped step"):
            levenberg_marquardt(problem, np.zeros(1))


def test_information_update_is_the_kalman_update():
    """The shared EKF update against filterpy's Kalman-gain form, R = I."""
    rng = np.random.default_rng(4)
    k, m = 6, 4
    a = rng.normal(size=(k, k))
    covariance = a @ a.T + np.eye(k)
    h, residual, x = rng.normal(size=(m, k)), rng.normal(size=m), rng.normal(size=k)
    reference = ExtendedKalmanFilter(dim_x=k, dim_z=m)
    reference.x, reference.P = x.copy(), covariance.copy()
    reference.update(residual + h @ x, lambda s: h, lambda s: h @ s, R=np.eye(m))
    updated, posterior = information_update(x, covariance, h.T @ h, h.T @ residual)
    assert np.allclose(updated, reference.x, rtol=1e-10, atol=1e-12)
    assert np.allclose(posterior, reference.P, rtol=1e-10, atol=1e-12)


def test_the_report_takes_the_estimates_own_predictions():
    """What the model predicts at the start and at the result comes from the passes
    the estimate made (computed once): the same numbers as predicting anew, and the
    start pass's residuals are residuals_at's."""
    from laser_calib.estimation.problem import factor_and_residuals, residuals_at
    session = paper_session("paper-7dof", 4)
    model = SpotModel(session.nominal, session.samples)
    for method in ("lm", "ekf"):
        est = estimate(session.nominal, session.samples, EstimateOptions(method=method))
        assert np.array_equal(est.fit.predicted, residuals_at(model, est.values).predicted, equal_nan=True)
        assert np.array_equal(est.predicted_at_start, residuals_at(model, np.zeros(33)).predicted, equal_nan=True)
    _, _, start = factor_and_residuals(model, NoiseModel(0.001), np.zeros(33), chunk=7)
    nominal = residuals_at(model, np.zeros(33))
    assert np.array_equal(start.r, nominal.r) and np.array_equal(start.valid, nominal.valid)


def test_a_parameter_held_for_the_given_sigma_says_so():
    """A spot sigma given 10x too large holds slm_rz (its std would exceed 10 tolerances): the rank
    line said 'the data determine 32 of 33' as if the data lacked it (helper probe); it now names the
    sigma given. The true sigma holds nothing."""
    session = paper_session("paper-7dof", 4)
    cal = session.samples.subset(session.cases["case3"][0])
    over = estimate(session.nominal, cal, EstimateOptions(spot_sigma=0.0115))
    ranks = [w for w in over.warnings if w.startswith("rank deficient")]
    assert len(ranks) == 1 and "33 parameters at the spot sigma given (11.5 mm; 1 held for it)" in ranks[0], ranks
    right = estimate(session.nominal, cal, _options(session))
    assert not any(w.startswith("rank deficient") for w in right.warnings), right.warnings


def test_a_spot_sigma_at_zero_beside_joint_noise_is_not_an_exact_fit():
    """A simulated session (scripts/main's, recorded: 60 poses of the 7-DOF arm, detection noise
    about 0.09 mm, joint readings about 0.06 deg) where the likelihood puts the spot component at
    its boundary, 0: the joint noise carries the residual (1.7 mm mean spot error). It was
    reported as "the data are fitted exactly (repeated poses?) ... the standard deviations mean
    nothing", and the spot sigma as 5.63e-08 mm "estimated from the residual"."""
    from laser_calib.io.samples import load_samples
    from laser_calib.model.robot_file import load_robot
    from laser_calib.report.files import spot_sigma_phrase

    folder = Path(__file__).parent / "data" / "joint_noise_session"
    robot = load_robot(folder / "robot.yaml")
    est = estimate(robot, load_samples(folder / "samples.csv", robot), EstimateOptions(joint_sigma=None))
    assert est.sigma_estimated and est.joint_sigma_estimated and est.sigma < 1e-7
    assert est.joint_sigma == pytest.approx(np.deg2rad(0.06), rel=0.3)
    assert not [w for w in est.warnings if "fitted exactly" in w], est.warnings
    assert np.isfinite(est.std[est.identifiable]).all() and (est.std[est.identifiable] > 0).all()
    assert spot_sigma_phrase(est).startswith("Spot sigma below what the data resolve")


def test_the_restricted_likelihood_of_dependent_columns_is_that_of_their_span():
    """A fit gone wrong can leave fewer measured values than determined parameters: X^T C^-1 X is
    singular, and the likelihood raised 'Singular matrix' from the middle of an estimate. Over the
    directions X spans (pseudo-determinant, pseudo-inverse) it is the likelihood of a basis of
    them up to a constant: det(A^T M A) over its range is det(M) det(A A^T) for X = B A."""
    from laser_calib.measurement.noise_components import deviance
    rng = np.random.default_rng(4)
    n_poses, basis_columns = 12, 3
    res = Residuals(r=rng.normal(0, 1e-3, (n_poses, 2, 2)), valid=np.ones((n_poses, 2), bool), jac=None,
                    jac_q=rng.normal(0, 0.5, (n_poses, 2, 2, 4)), predicted=np.zeros((n_poses, 2, 2)))
    basis = rng.normal(0, 1, (n_poses, 2, 2, basis_columns))
    mixed = basis @ rng.normal(0, 1, (basis_columns, 2))     # two columns in the span of the three
    dependent = np.concatenate([basis, mixed, np.zeros((n_poses, 2, 2, 1))], axis=-1)   # and one never seen
    of_basis, of_dependent = deviance(res, 1.0, basis), deviance(res, 1.0, dependent)
    sigmas = [(1e-3, 1e-4), (3e-4, 2e-3), (2e-3, 1e-6), (47.0, 1e-4)]
    offsets = [of_dependent(s, j) - of_basis(s, j) for s, j in sigmas]
    assert np.allclose(offsets, offsets[0], rtol=0, atol=1e-6), offsets
