"""report/truth.py: the calibrated model against the true robot and on held-out poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from laser_calib.model.robot_file import load_robot
from laser_calib.report.truth import append_to_report, compare, truth_errors
from laser_calib.sim.simulation import true_errors
from laser_calib.io.samples import Samples
from laser_calib.model.kinematics import predict
from laser_calib.session.poses import generate_poses

ROBOT = Path(__file__).resolve().parents[2] / "config" / "robots" / "humanoid_arm_7dof.yaml"


def test_truth_errors_vanish_for_the_true_model_and_not_for_the_nominal():
    nominal = load_robot(ROBOT)
    true = nominal.with_errors(true_errors(nominal))          # the paper's +10 mm / +1 deg
    exact = truth_errors(nominal, true, true, n_poses=300)
    assert exact["end_effector"]["after"]["max_mm"] < 1e-9 and exact["spot"]["after"]["max_mm"] < 1e-9
    # +1 deg on 7 joints over a ~0.5 m arm moves the end effector by centimetres
    assert exact["end_effector"]["before"]["mean_mm"] > 10
    assert exact["spot_poses"] > 0 and exact["spot"]["before"]["n"] == 2 * exact["spot_poses"]


def test_held_out_poses_and_report_section(tmp_path):
    nominal = load_robot(ROBOT)
    true = nominal.with_errors(true_errors(nominal))
    q = generate_poses(true, 5, "whole", 2).q
    spots = predict(true, q).spots                              # exact measurements
    test = Samples(np.arange(5), np.arange(5.0), q, spots)
    result = compare(nominal, true, test, None)
    assert result["test"]["poses"] == 5 and result["test"]["after"]["max_mm"] < 1e-9
    assert result["test"]["before"]["mean_mm"] > 1 and "truth" not in result
    report = tmp_path / "report.md"
    report.write_text("# report\n")
    append_to_report(report, compare(nominal, true, test, true))
    text = report.read_text()
    assert "Test poses (measured, never fitted): 5 poses" in text
    assert "| end-effector position | calibrated | 0.000 |" in text
