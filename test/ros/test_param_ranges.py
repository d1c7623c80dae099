"""Out-of-range parameter values are refused at the start, in one line naming the parameter,
exit 2, as the nodes' other parameters are. Before: a negative seed of the simulation ended
arm_driver and camera_sim with numpy's traceback (exit 1); rate:=.inf started a timer of
period 0 (a busy loop 'publishing at inf Hz'), and rate:=1e9 one of 1 ns (a busy loop too); camera_sim's spot_sigma:=0.0 rendered no spot
(a divide-by-zero warning, every spot unseen) and spot_detector's screen.half_y:=-1.0 saw no
spot in any frame, both without a word. The estimator's spot_sigma:=0.5 (0.5 mm meant) was taken as a
camera's noise of half a metre; its joint_sigma:=3.0 (degrees meant) is refused the same way, and so is
the sequencer's estimate.joint_sigma:=-3 (no joint noise; its -1 is not given), and its 0 (none) when it
would ask the estimator, whose request cannot say none (its 0 is the estimator's joint_sigma)."""

from __future__ import annotations

from ros_harness import ROBOT

CASES = {  # name: (node, parameters, the reason's start)
    "arm_seed": ("arm_driver", [f"robot:={ROBOT}", "sim.seed:=-1"], "error: parameter sim.seed: expected >= 0"),
    "arm_rate": ("arm_driver", [f"robot:={ROBOT}", "rate:=.inf"], "error: parameter rate: expected > 0"),
    "arm_rate_busy": ("arm_driver", [f"robot:={ROBOT}", "rate:=1e9"],
                      "error: parameter rate: expected > 0 and <= 1000 Hz, got 1000000000.0"),
    "camera_seed": ("camera_sim", ["seed:=-1"], "error: parameter seed: expected >= 0"),
    "camera_rate": ("camera_sim", ["rate:=.inf"], "error: parameter rate: expected > 0"),
    "camera_rate_busy": ("camera_sim", ["rate:=5000.0"], "error: parameter rate: expected > 0 and <= 1000 Hz"),
    "camera_sigma": ("camera_sim", ["spot_sigma:=0.0"], "error: parameter spot_sigma: expected > 0"),
    "detector_half": ("spot_detector", ["screen.half_y:=-1.0"], "error: parameter screen.half_y: expected > 0"),
    "detector_rate": ("spot_detector", ["false_refusal_rate:=1.5"],
                      "error: parameter false_refusal_rate: expected 0..1, got 1.5"),
    # millimetres typed as metres: a camera's noise of half a metre, every spot weighted as noise
    "estimator_sigma": ("estimator", [f"robot:={ROBOT}", "spot_sigma:=0.5"],
                        "error: parameter spot_sigma: 0.5 m is not a plausible spot noise"),
    # degrees typed as radians
    "estimator_joint_sigma": ("estimator", [f"robot:={ROBOT}", "joint_sigma:=3.0"],
                              "error: parameter joint_sigma: 3 rad is not a plausible joint-reading noise"),
    "sequencer_joint_sigma": ("sequencer", [f"robot:={ROBOT}", "estimate.joint_sigma:=-3"],
                              "error: parameter estimate.joint_sigma: -3 rad is not a plausible joint-reading noise"),
    "sequencer_no_joint_noise": ("sequencer", [f"robot:={ROBOT}", "estimate.joint_sigma:=0.0"],
                                 "error: parameter estimate.joint_sigma: 0 (no joint-reading noise) cannot be asked "
                                 "of the estimator"),
}


def test_out_of_range_parameters_give_one_line(ros):
    for name, (node, params, _) in CASES.items():
        ros.start(name, *[arg for p in params for arg in ("-p", p)], node=node, params=False)
    for name, (node, _, reason) in CASES.items():
        code = ros.wait_exit(name, 60)
        log = ros.log(name)
        lines = [line for line in log.splitlines() if line.strip()]
        assert code == 2 and "Traceback" not in log, (name, code, log[-2000:])
        assert lines[-1].startswith(reason), (name, lines[-1])
