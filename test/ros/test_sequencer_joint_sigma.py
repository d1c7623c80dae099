"""The sequencer's estimate.joint_sigma, beside its estimate.spot_sigma, is the final estimate's
joint-reading sigma (the command line's --joint-sigma; -1: not given, 0: none): a user with a
known encoder noise can give it. Before, the sequencer had none: its Estimate request left
joint_sigma 0 (the estimator's parameter) and its own estimate ('local') always estimated it with
the spot sigma. (Its refusals at the start: test_param_ranges.py.)"""

from __future__ import annotations

import json

import pytest

from ros_harness import ROOT

ROBOT = ROOT / "config" / "robots" / "manipulator_4dof.yaml"


@pytest.mark.parametrize("mode", ["local", "service"])
def test_a_given_joint_sigma_is_the_final_estimates(ros, tmp_path, mode):
    out = tmp_path / "out"
    if mode == "service":  # the estimator's own joint_sigma is another: the request's is the sequencer's
        ros.start("estimator", "-p", f"robot:={ROBOT}", "-p", "joint_sigma:=0.001", "-p", "markers:=false")
    ros.start("arm_driver", "-p", f"robot:={ROBOT}", "-p", "sim.joint_speed:=4.0")
    ros.start("camera_sim")
    ros.start("spot_detector")
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "poses:=12",
              "-p", "test_poses:=0", "-p", "span:=whole", "-p", "seed:=5", "-p", f"estimate.mode:={mode}",
              "-p", "estimate.diagnose:=false", "-p", "estimate.joint_sigma:=0.0005")
    code = ros.wait_exit("sequencer", 240)
    log = ros.log("sequencer")
    assert code == 0 and "Traceback" not in log, log[-3000:]
    result = json.loads((out / "result.json").read_text())
    # the spot sigma (estimate.spot_sigma 0) estimated, the joint sigma given
    assert result["spot_sigma_estimated"], result
    assert result["joint_sigma_rad"] == 0.0005 and not result["joint_sigma_estimated"], result
