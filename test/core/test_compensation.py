"""The compensator's shape (diagnosis.compensation.refined): once the detector has found a
joint's error following the inputs, the compensator refits it on the basis the held-out
error chooses. Two cases of the effects bench (bench/effects_bench.py, paper-7dof, seed 8,
built here as the bench builds them) where the detector's basis, four knots per input and a
pair as the product of its readings, left the compensated test RMS 1.36 and 1.35 times the
true model's: a third harmonic of a joint's angle (three periods over its range) and an
error following the sines of two joints (which neither the product nor additive splines
hold). Issue 13 asks for 25 %."""

import numpy as np
import pytest

from laser_calib.diagnosis.engine import diagnose
from laser_calib.diagnosis.options import DiagnoseOptions
from laser_calib.estimation.estimate import EstimateOptions
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


@pytest.mark.parametrize("kind", [harmonic, two_joint], ids=["harmonic", "two joints"])
def test_an_error_the_detector_basis_only_approximates_is_compensated_within_25_percent(kind):
    def make(robot, errors, context, rng):
        return [sized(robot, errors, context, kind(robot, rng), NOISE, VISIBLE)]

    session = effect_session("paper-7dof", SEED, make, 80, 80, NOISE)
    diagnosis = diagnose(session.nominal, session.cal, session.test, spot_sigma=NOISE.spot_sigma,
                         joint_sigma=NOISE.joint_sigma, options=DiagnoseOptions(nested=False))
    assert session.truth[0].name.startswith("error of joint 1"), session.truth[0].name  # the bench's case
    compensator = diagnosis.compensator
    assert compensator is not None, diagnosis.evidence
    assert [t for t, u in zip(compensator.targets, compensator.used) if u] == ["theta1"]
    true_rms = true_offsets_rms(session, session.truth[0], EstimateOptions(spot_sigma=NOISE.spot_sigma,
                                                                           joint_sigma=NOISE.joint_sigma))
    compensated = diagnosis.compensated_test[session.test.seen]
    assert np.sqrt(np.mean(compensated ** 2)) * 1e3 <= 1.25 * true_rms
