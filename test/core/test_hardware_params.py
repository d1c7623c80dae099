"""The parameter files hardware.launch.py starts a real arm and camera with (its default params
config/session.yaml, and the example arm_params config/dynamixel_arm.yaml) pair every camera frame with a
joint state, whatever the camera's rate and phase. session.yaml gave the sequencer the simulated
camera's sync_tolerance, 0.005 s (that camera stamps each frame with a joint state's stamp): a
camera of its own clock, at 3 Hz beside the Dynamixel arm's 30 Hz joint states, had no frame
within 5 ms of one, and the session ended at its first pose (exit 3: fewer than 3 spot frames
paired), while the sequencer's own rule (its parameter's description) is at least half the
joint_states period."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from laser_calib.session.average import FrameCollector
from laser_calib.session.settle import SettleDetector, SettleRule

CONFIG = Path(__file__).resolve().parents[2] / "config"


def test_the_hardware_launchs_defaults_pair_a_camera_at_any_phase():
    session = yaml.safe_load((CONFIG / "session.yaml").read_text())
    tolerance = session["sequencer"]["ros__parameters"].get("sync_tolerance", 0.02)   # the node's default
    for arm_file in ("dynamixel_arm.yaml", "session.yaml"):   # the real arm's rate, the simulated one's
        rate = yaml.safe_load((CONFIG / arm_file).read_text())["arm_driver"]["ros__parameters"]["rate"]
        period = 1.0 / rate
        state = (np.zeros(4), None)
        for phase in np.linspace(0.0, period, 7, endpoint=False):   # a frame's offset from the joint states
            collector = FrameCollector(3, tolerance, SettleDetector(np.zeros(4), SettleRule(), 0.0), 100.0,
                                       state)                         # settled at 100 s
            for stamp in 100.0 + period * np.arange(1, 2 * rate):      # two seconds of joint states
                collector.add_state(stamp, state)
            for stamp in 100.0 + phase + np.arange(1, 4) / 3.0:       # a 3 Hz camera's three frames
                collector.add_frame(stamp, np.zeros((2, 2)))
            assert collector.complete, (arm_file, rate, phase, tolerance)
