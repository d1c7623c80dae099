"""The robust rule and the noise estimate on sets with few values to spare
(estimation/robust.py, estimation/estimate.py).

A tester's case: 6 poses of the 4-DOF arm (12 clean spots, 24 values, 19
parameters the spots determine numerically). The rule rejected 3 clean spots,
the 18 values left fitted 18 parameters exactly, and the command wrote that
exact fit as a calibration (exit 0) with standard deviations from a zero
residual (chi^2/dof 5e7, sigma 2.9e-5 mm).

Bounds: a clean set loses a unit with probability 1 % by construction of the
limit, so 30 clean sets lose a spot in at most one except with probability
< 4 % (the seeds are fixed: the count is one draw of it).
"""

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2, f

from cli_status import exit_status
from laser_calib.estimation import outliers
from laser_calib.estimation import robust
from laser_calib.estimation.estimate import NOISE_RATIO, EstimateOptions, estimate
from laser_calib.estimation.failures import NOT_A_CALIBRATION
from laser_calib.estimation.identifiability import TooFewValues
from laser_calib.estimation.redundancy import sigma_upper
from laser_calib.io.samples import load_samples, save_samples
from laser_calib.model.robot_file import load_robot, save_robot
from laser_calib.sim.simulation import paper_session
from test_robust import scattered


def _first(case: str, seed: int, poses: int):
    """The session and the first ``poses`` poses of its case-2 calibration set (the simulate command's
    case2_cal.csv, head -poses+1)."""
    session = paper_session(case, seed)
    return session, session.samples.subset(session.cases["case2"][0][:poses])


def test_the_limit_is_fishers_F_and_chi2_with_many_values():
    from laser_calib.estimation import redundancy
    for dims, dof, units in [(1, 3, 10), (2, 6, 12), (2, 77, 48), (3, 40, 100), (2, 10 ** 6, 20000)]:
        tail = redundancy.FAMILY_FALSE_REJECTION / units
        assert redundancy.outlier_limit(dims, dof, units) == pytest.approx(dims * f.isf(tail, dims, dof), rel=1e-9)
    # thousands of values: the chi^2 limit the rule used before; a handful: many times it
    assert redundancy.outlier_limit(2, 40000, 20000) == pytest.approx(chi2.isf(0.01 / 20000, 2), rel=1e-3)
    assert redundancy.outlier_limit(2, 6, 12) > 4 * chi2.isf(0.01 / 12, 2)


def test_the_testers_six_poses_lose_no_clean_spot_and_say_their_sigma_is_uncertain(tmp_path, capsys):
    """The tester's command lines: no spot rejected (without the ones farthest out the rest would be
    fitted exactly: nothing to judge them by), and no exact fit written as a calibration. The noise
    threshold keeps 16 of the 19 parameters the sigma trial fitted: 8 of the 24 values to spare, a
    calibration whose sigma, from the trial's 5, is said to be uncertain. (Its fit, started from the
    trial's minimum with the 3 reset to nominal, once lost all 12 spots: exit 3.)"""
    sim = tmp_path / "sim4"
    assert exit_status(["simulate", "--case", "paper-4dof", "--seed", "5", "--out", str(sim)]) == 0
    lines = (sim / "case2_cal.csv").read_text().splitlines(keepends=True)
    (tmp_path / "few6.csv").write_text("".join(lines[:7]))
    capsys.readouterr()
    code = exit_status(["estimate", "--robot", str(sim / "robot_nominal.yaml"), "--samples",
                        str(tmp_path / "few6.csv"), "--test", str(sim / "case2_test.csv"), "--out",
                        str(tmp_path / "out")])
    out = capsys.readouterr().err
    assert "rejected as outliers" not in out
    assert "warning: robust: too few values to tell an outlier: without the 3 of 12 measurements" in out
    assert "the data are fitted exactly" not in out and "chi^2/dof = 5" not in out
    assert code == 0, out
    assert "error:" not in out and "the spot sigma 1.29 mm is estimated from 5 residual degrees of freedom" in out
    # the same file on the estimator: nothing rejected
    robot = load_robot(sim / "robot_nominal.yaml")
    try:
        est = estimate(robot, load_samples(tmp_path / "few6.csv", robot), EstimateOptions())
    except TooFewValues:
        return
    assert est.rejected == () and est.robust["rejected"] == 0


@pytest.mark.parametrize("poses", [8, 10])
def test_clean_small_sets_lose_no_spot(poses):
    """8 or 10 clean poses (32, 40 values for 19 parameters): a spot the others predict loosely has a
    residual as large as the noise or larger without being wrong; before, 10 of 30 sets of 8 poses lost
    clean spots (28 in all), 8 of 30 sets of 10 poses (15)."""
    lost = 0
    for seed in range(30):
        session, samples = _first("paper-4dof", seed, poses)
        est = estimate(session.nominal, samples, EstimateOptions(joint_sigma=session.noise.joint_sigma))
        lost += bool(est.rejected)
    assert lost <= 1


def test_a_gross_error_in_a_small_set_is_still_rejected():
    """10 poses, one spot 20 cm off: enough values to spare to tell it, and it is the one listed."""
    found = 0
    for seed in range(10):
        session, samples = _first("paper-4dof", seed, 10)
        spots = samples.spots.copy()
        spots[3, 0] += [0.2, -0.2]
        est = estimate(session.nominal, replace(samples, spots=spots),
                       EstimateOptions(joint_sigma=session.noise.joint_sigma))
        assert set(est.rejected) <= {(3, 0)}
        found += est.rejected == ((3, 0),)
    assert found == 10


def _rejecting_all_but(keep: int):
    """A robust rule that rejects every measured spot but the first ``keep`` (in pose order), its final fit
    least squares on those: a rule that leaves too few values."""
    real = robust.robust_fit

    def rule(model, noise, free, prior_sigma, x0, solve, excluded=None, start=None, options=None):
        outcome = real(model, noise, free, prior_sigma, x0, solve, excluded, start)
        seen = model.samples.seen if excluded is None else model.samples.seen & ~excluded
        rejected = seen.copy()
        rejected.flat[np.flatnonzero(seen)[:keep]] = False
        problem = robust.Problem(model, noise, free, prior_sigma, rejected if excluded is None else excluded | rejected)
        return replace(outcome, fit=solve(problem, x0, None), rejected=rejected)
    return rule


def test_a_rejection_that_leaves_too_few_values_is_refused(monkeypatch, tmp_path, capsys):
    """Should the rule ever leave no more values than parameters, the exact fit of the rest is refused as
    before the fit: one line naming the samples file, exit 2, nothing written."""
    session, samples = _first("paper-4dof", 0, 12)
    save_samples(samples, tmp_path / "samples.csv")
    save_robot(session.nominal, tmp_path / "robot.yaml")
    monkeypatch.setattr(outliers, "robust_fit", _rejecting_all_but(9))   # 18 values for 19 parameters
    with pytest.raises(TooFewValues, match="18 measured values left after 15 rejected as outliers cannot "
                                           "determine and check 19 parameters"):
        estimate(session.nominal, samples, EstimateOptions())
    code = exit_status(["estimate", "--robot", str(tmp_path / "robot.yaml"), "--samples",
                        str(tmp_path / "samples.csv"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert err[-1].startswith("laser-calib") and f"{tmp_path / 'samples.csv'}: 18 measured values left" in err[-1]
    assert not (tmp_path / "out").exists()


def test_a_sigma_from_few_residual_values_is_said_to_be_uncertain():
    """The spot sigma estimated from the residual rests on the values less the parameters: 6 poses of
    the 4-DOF arm give 24 - 19 = 5, so the noise may be 2.5 times larger (95 %) and every standard
    deviation with it; 5 poses give 1, no basis for a standard deviation at all (Student's t with 1
    degree of freedom has no variance): no calibration. Given, the sigma needs no such warning."""
    session, six = _first("paper-4dof", 0, 6)
    options = EstimateOptions(joint_sigma=session.noise.joint_sigma)
    est = estimate(session.nominal, six, options)
    lines = [w for w in est.warnings if w.startswith("noise: the spot sigma")]
    assert len(lines) == 1, est.warnings
    assert "estimated from 5 residual degrees of freedom" in lines[0] and "2.5 times larger (95 %)" in lines[0]
    # the noise line is no failure; but 5 residual values leave room for alpha2 and theta3 at 12 degrees (the
    # truth is 1), errors no arm is built with: failures.implausible says no calibration
    failures = [w for w in est.warnings if w.startswith(NOT_A_CALIBRATION)]
    assert len(failures) == 1 and failures[0].startswith(f"{NOT_A_CALIBRATION}: alpha2 is fitted at 12 times"), failures
    given = estimate(session.nominal, six, replace(options, spot_sigma=session.noise.spot_sigma))
    assert not any("residual degrees of freedom" in w for w in given.warnings)
    _, five = _first("paper-4dof", 0, 5)
    est = estimate(session.nominal, five, options)
    assert any(w.startswith(f"{NOT_A_CALIBRATION}: the spot sigma") and "from only 1 residual degree of freedom"
               in w for w in est.warnings)
    assert sigma_upper(5) == pytest.approx(np.sqrt(5 / chi2.ppf(0.025, 5)))
    assert sigma_upper(7) > NOISE_RATIO > sigma_upper(8)   # the warning from 7 residual degrees of freedom down


def test_many_values_keep_their_rejections():
    """With hundreds of values the F limit is the chi^2 one within a few percent and the confirmation
    keeps every gross outlier: 5 % of the spots anywhere on the screen, all listed, nothing else."""
    session = paper_session("paper-7dof", 3)
    samples, picks = scattered(session, 3, 20)
    est = estimate(session.nominal, samples, EstimateOptions())
    assert set(est.rejected) == {(int(p), int(j)) for p, j in picks}
