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
    # taken without a word (a new ROS user's probe): a 2 m spot, joints read 3 rad off, pairs of frame and
    # joint state 5 s apart, 100 rad/s commanded, a contrast no 8-bit image reaches, a mono8 mosaic of no
    # colours refused frame by frame, a capture folder that cannot be made named by errno alone, and a
    # truth file found missing after the whole session was measured
    "camera_sigma_m": ("camera_sim", ["spot_sigma:=2.0"], "error: parameter spot_sigma: expected > 0 and <= 0.05 m"),
    "arm_disturbance": ("arm_driver", [f"robot:={ROBOT}", "sim.joint_disturbance:=5.0"],
                        "error: parameter sim.joint_disturbance: expected >= 0 and <= 0.035"),
    "arm_read_noise": ("arm_driver", [f"robot:={ROBOT}", "sim.read_noise:=3.0"],
                       "error: parameter sim.read_noise: expected >= 0 and <= 0.035"),
    "sequencer_sync": ("sequencer", [f"robot:={ROBOT}", "sync_tolerance:=5.0"],
                       "error: parameter sync_tolerance: expected >= 0 and <= 0.5 s"),
    "estimator_sync": ("estimator", [f"robot:={ROBOT}", "sync_tolerance:=10.0"],
                       "error: parameter sync_tolerance: expected >= 0 and <= 0.5 s"),
    "sequencer_speed": ("sequencer", [f"robot:={ROBOT}", "move.joint_speed:=100.0"],
                        "error: parameter move.joint_speed: expected > 0 and <= 10 rad/s"),
    "detector_capture_count": ("spot_detector", ["capture_count:=-5"], "error: parameter capture_count: expected >= 0"),
    "detector_capture_period": ("spot_detector", ["capture_period:=-1.0"],
                                "error: parameter capture_period: expected >= 0"),
    "detector_min_peak": ("spot_detector", ["min_peak_dn:=5000.0"], "error: parameter min_peak_dn: expected 0..255"),
    "detector_mono": ("spot_detector", ["mono_pattern:=ZZZZ"], "error: parameter mono_pattern: bayer_pattern must be"),
    "detector_capture_dir": ("spot_detector", ["capture_dir:=/proc/x"],
                             "error: parameter capture_dir: cannot make /proc/x"),
    "sequencer_truth": ("sequencer", [f"robot:={ROBOT}", "truth:=/nonexistent/robot_true.yaml"],
                        "error: parameter truth: /nonexistent/robot_true.yaml: cannot read"),
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
