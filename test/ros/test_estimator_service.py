"""The estimator's Estimate service: bad requests are refused in one line, and
several concurrent clients are all served; the node keeps serving."""

from __future__ import annotations

import json

from ros_harness import ROBOT


def test_bad_requests_and_concurrent_clients(ros):
    ros.start("estimator", "-p", f"robot:={ROBOT}")
    out = ros.client("bad-and-concurrent", str(ROBOT))
    expected_refusals = {
        "empty": "no samples",
        "wrong_joint_count": "6 joint positions",
        "nan_joint": "joint_positions[2] is not finite",
        "nan_spot": "non-finite",
        "bad_method": "gauss",
        "negative_sigma": "spot_sigma",
        "too_few": "",
    }
    for name, text in expected_refusals.items():
        assert out[name]["success"] is False, (name, out[name]["message"])
        assert text in out[name]["message"], (name, out[name]["message"])
        assert "\n" not in out[name]["message"]
        assert "internal error" not in out[name]["message"]
    assert "pose 0" in out["wrong_joint_count"]["message"]  # names the sample
    goods = [out[name] for name in ("good_lm_1", "good_lm_2", "good_lm_3", "after_all")]
    for good in goods:
        assert good["success"], good["message"]
        assert good["errors"] == goods[0]["errors"]  # concurrent requests do not disturb each other
        assert good["sample_count"] == 30
        assert all(a < b for a, b in zip(good["after_mean"], good["before_mean"]))
        json.loads(good["result_json"])
    assert json.loads(out["good_lm_3"]["diagnosis_json"])["verdict"]  # laser_calib.diagnosis.engine ran
    assert out["good_lm_1"]["diagnosis_json"] == ""
    assert out["good_ekf"]["success"], out["good_ekf"]["message"]
    assert ros.procs["estimator"].poll() is None  # still alive
    reset = ros.client("reset")
    assert reset["success"]
    assert ros.stop("estimator") == 0  # Ctrl-C: exit 0
    assert "Traceback" not in ros.log("estimator")
