"""The compensator's shape (diagnosis.compensation.refined): once the detector has found a
joint's error following the inputs, the compensator refits it on the basis the held-out
error chooses. Two cases of the effects bench (bench/effects_bench.py, paper-7dof, seed 8,
built here as the bench builds them) where the detector's basis, four knots per input and a
pair as the product of its readings, left the compensated test RMS 1.36 and 1.32 times the
true model's (now 1.08 and 1.13): a third harmonic of a joint's angle (three periods over
its range; both sigmas given) and an error following the sines of two joints (which neither
the product nor additive splines hold; the spot sigma given). Issue 13 asks for 25 %. In the bench's case of the second with both sigmas given the
richer basis predicted the held-out poses better, but not significantly (p = 0.11), and was
not taken."""

import numpy as np
import pytest

from laser_calib.diagnosis.compensation import refined
from laser_calib.diagnosis.detector import N_KNOTS, Basis, OffsetRegression, submodels
from laser_calib.diagnosis.engine import diagnose
from laser_calib.diagnosis.options import DiagnoseOptions
from laser_calib.estimation.estimate import EstimateOptions
from laser_calib.estimation.folds import kfold_labels
from laser_calib.sim.effect_truth import ForeignError, effect_session, sized, true_offsets_rms
from laser_calib.sim.simulation import NoiseSpec

NOISE = NoiseSpec(spot=0.5e-3, joint=float(np.deg2rad(0.02)))
VISIBLE = 150.0   # the bench's: the chi^2 excess the error leaves in the geometric fit
SEED = 8


def _joint_error(robot, joint: int, values: np.ndarray) -> np.ndarray:
    out = np.zeros((len(values), robot.n_params))
    out[:, robot.param_names.index(f"theta{joint + 1}")] = values
    return out


def harmonic(robot, rng) -> ForeignError:
    i, phase = int(rng.integers(robot.n_joints)), float(rng.uniform(0, 2 * np.pi))
    return ForeignError(f"error of joint {i + 1} ~ sin(3 q{i + 1} + {phase:.2f})",
                        lambda r, s: _joint_error(r, i, np.sin(3 * s.q[:, i] + phase)))


def two_joint(robot, rng) -> ForeignError:
    i, j = (int(k) for k in rng.choice(robot.n_joints, 2, replace=False))
    phase = float(rng.uniform(0, np.pi))
    return ForeignError(f"error of joint {i + 1} ~ sin q{j + 1} sin(q{i + 1} + {phase:.2f})",
                        lambda r, s: _joint_error(r, i, np.sin(s.q[:, j]) * np.sin(s.q[:, i] + phase)))


# the noise given as in the bench's case: both sigmas, or the spot sigma only (the joint's estimated)
@pytest.mark.parametrize("kind, joint_given", [(harmonic, True), (two_joint, False)],
                         ids=["harmonic, both sigmas given", "two joints, spot sigma given"])
def test_an_error_the_detector_basis_only_approximates_is_compensated_within_25_percent(kind, joint_given):
    def make(robot, errors, context, rng):
        return [sized(robot, errors, context, kind(robot, rng), NOISE, VISIBLE)]

    session = effect_session("paper-7dof", SEED, make, 80, 80, NOISE)
    diagnosis = diagnose(session.nominal, session.cal, session.test, spot_sigma=NOISE.spot_sigma,
                         joint_sigma=NOISE.joint_sigma if joint_given else None,
                         options=DiagnoseOptions(nested=False))
    assert session.truth[0].name.startswith("error of joint 1"), session.truth[0].name  # the bench's case
    compensator = diagnosis.compensator
    assert compensator is not None, diagnosis.evidence
    assert [t for t, u in zip(compensator.targets, compensator.used) if u] == ["theta1"]
    true_rms = true_offsets_rms(session, session.truth[0], EstimateOptions(spot_sigma=NOISE.spot_sigma,
                                                                           joint_sigma=NOISE.joint_sigma))
    compensated = diagnosis.compensated_test[session.test.seen]
    assert np.sqrt(np.mean(compensated ** 2)) * 1e3 <= 1.25 * true_rms


def test_on_a_noise_residual_the_detector_basis_is_mostly_kept():
    """A residual of pure noise and a sub-model the detector might have chosen (one direction
    with a pair of inputs): the best of the richer bases wins the folds by chance, and the
    paired test keeps the detector's basis unless it predicts better per pose. Without the
    test 1 of 40 seeds kept it; with it 30 (the test is not corrected for the choice among
    seven, refined's docstring). 25: binomial at 3/4, two standard deviations (2.7) below."""
    kept = 0
    for seed in range(40):
        rng = np.random.default_rng(seed)
        n_poses, n_values, n_inputs, n_directions = 80, 4, 3, 2
        z = rng.uniform(-1, 1, (n_poses, n_inputs))
        directions = rng.normal(size=(n_poses * n_values, n_directions))
        X = np.concatenate([np.repeat(z, n_values, axis=0), directions], axis=1)
        y = rng.normal(size=(n_poses, n_values))
        basis = Basis.of(z, n_inputs)
        pair_model = submodels(basis, n_inputs, n_directions)[len(basis.pairs) + n_inputs - 1]
        chosen = OffsetRegression(basis, n_inputs, 1.0, pair_model).fit(X, y.ravel())
        out = refined(chosen, X, y, kfold_labels(n_poses, 5, 0))
        kept += len(out.basis.knots) == N_KNOTS and not out.basis.tensor
    assert kept >= 25, kept
