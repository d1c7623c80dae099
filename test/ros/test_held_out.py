"""A simulated session with held-out test poses: measured, never fitted (not even by the
online estimator), given to the estimate as its test set (the Estimate request's test_samples,
the estimator's accumulated test_samples), and the report's figures against the simulator's
true robot."""

from __future__ import annotations

import json

import numpy as np

from ros_harness import ROBOT, start_sim

FIT, TEST = 10, 4


def test_test_poses_are_measured_and_held_out(ros, tmp_path):
    from laser_calib.io.samples import load_samples
    from laser_calib.io import bag
    out = tmp_path / "out"
    out.mkdir()
    start_sim(ros, out)
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", f"poses:={FIT}",
              "-p", f"test_poses:={TEST}", "-p", "span:=whole", "-p", "seed:=4", "-p", "estimate.diagnose:=false")
    assert ros.wait_exit("sequencer", 240) == 0, ros.log("sequencer")[-3000:]
    assert len(load_samples(out / "samples.csv")) == FIT
    test = load_samples(out / "test_samples.csv")
    assert len(test) == TEST and min(test.pose) == FIT
    assert len(bag.read_samples(out / "bag", "/test_samples")) == TEST
    online = ros.client("params", str(FIT))
    assert online["sample_count"] == FIT                        # the estimator never saw a test pose
    # ... but the estimate tested on them: the sequencer's request carried them, the estimator kept them apart
    assert f"with {FIT} samples and {TEST} test samples" in ros.log("sequencer")
    tested = json.loads((out / "result.json").read_text())["spot_error"]["test"]["after"]
    assert tested["all"]["n"] == int(np.isfinite(test.spots).all(axis=2).sum()) > 0, tested
    accumulated = ros.client("estimate-accumulated")
    assert accumulated["success"] and accumulated["sample_count"] == FIT, accumulated["message"]
    assert json.loads(accumulated["result_json"])["spot_error"]["test"] == \
        json.loads((out / "result.json").read_text())["spot_error"]["test"]
    result = json.loads((out / "truth.json").read_text())
    assert result["test"]["poses"] == TEST
    truth = result["truth"]
    # the paper's errors (+10 mm / +1 deg) against a calibration from 10 poses: better everywhere on average
    for what in ("end_effector", "spot"):
        assert truth[what]["after"]["mean_mm"] < truth[what]["before"]["mean_mm"], truth
    assert result["test"]["after"]["mean_mm"] < result["test"]["before"]["mean_mm"]
    report = (out / "report.md").read_text()
    assert "## Held-out poses and the truth" in report and "end-effector position" in report
    log = ros.log("sequencer")
    assert "Test poses (measured, never fitted)" in log and "Traceback" not in log
    # the truth table's rows in the log come with its header (what each number is, and its unit)
    table = [line.split("]: ", 1)[1] for line in log.splitlines() if "[sequencer]: |" in line]
    assert table[0] == "| error | model | mean mm | rms mm | max mm |", table
    assert any(line.startswith("| end-effector position | calibrated |") for line in table), table
    assert any("Against the true robot over the whole workspace" in line for line in log.splitlines())
    # the summary holds the estimate's warnings, and is logged at WARN when there are any
    summary = next(line for line in log.splitlines() if f"lm on {FIT} poses: mean spot error" in line)
    assert summary.startswith("[WARN]" if json.loads((out / "result.json").read_text())["warnings"] else "[INFO]")
