"""Too few poses for the diagnosis is a data limit with one rule
(diagnosis.engine.minimum_poses): the command line refuses in one line, the
nodes' estimate (session.estimate) succeeds and says the diagnosis was skipped."""

import numpy as np
import pytest

from laser_calib.cli.main import main as cli_main
from laser_calib.diagnosis.engine import DiagnoseOptions, TooFewPoses, diagnose, minimum_poses
from laser_calib.io.samples import save_samples
from laser_calib.model.robot_file import save_robot
from laser_calib.session.estimate import estimate_options, run_calibration
from laser_calib.sim.simulation import paper_session


def session(poses_per_span: int):
    s = paper_session("paper-7dof", seed=4, n_per_span=poses_per_span)
    assert s.samples.seen.all()  # 4 measured values a pose, so the numbers below hold
    return s


def test_minimum_poses_follows_the_folds_and_the_estimate_rule():
    # 5 folds of 12 poses: 3, 3, 2, 2, 2; the smallest training fold holds 9 poses, 36 values >= 33
    assert minimum_poses(33, 4.0, 5) == 12
    assert minimum_poses(1, 4.0, 5) == 5      # at least a pose a fold
    assert minimum_poses(33, 0.0, 5) == 5     # no measured value: the estimate says so itself


def test_the_minimum_is_enough():
    s = session(6)
    assert len(s.samples) == 12
    diagnose(s.nominal, s.samples, options=DiagnoseOptions(method="lm"))  # no fold left without enough values


def test_diagnose_refuses_too_few_poses_in_one_line(tmp_path, capsys):
    s = session(5)
    with pytest.raises(TooFewPoses, match="10 poses, at least 12 needed"):
        diagnose(s.nominal, s.samples, options=DiagnoseOptions(method="lm"))
    save_robot(s.nominal, tmp_path / "robot.yaml")
    save_samples(s.samples, tmp_path / "samples.csv")
    code = cli_main(["diagnose", "--robot", str(tmp_path / "robot.yaml"), "--samples",
                     str(tmp_path / "samples.csv"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and "10 poses, at least 12 needed" in err[-1] and "Traceback" not in "\n".join(err)


def test_the_nodes_estimate_succeeds_with_the_diagnosis_skipped():
    s = session(5)
    outcome = run_calibration(s.nominal, s.samples, estimate_options("lm", 0.0, False, False), None, diagnose=True)
    assert outcome.message.endswith("diagnosis skipped: 10 poses, at least 12 needed")
    assert '"skipped"' in outcome.diagnosis_json
    assert np.isfinite(outcome.calibration.calibrated.vector()).all()
