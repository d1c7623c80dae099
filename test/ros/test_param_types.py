"""A run-time parameter keeps its declared type: `ros2 param set /estimator spot_sigma 2` sends an
integer, which the node takes as 2.0 m. Before, the parameter was stored as the integer given
(`ros2 param get`: 'Integer value is: 2', `ros2 param dump`: 2) while `ros2 param describe` still
said double."""

from __future__ import annotations

from ros_harness import ROBOT


def test_an_integer_for_a_double_parameter_is_stored_as_a_double(ros):
    ros.start("estimator", "-p", f"robot:={ROBOT}")
    ros.start("spot_detector")
    ros.wait_log("estimator", "input 'samples'", 60)
    ros.wait_log("spot_detector", "calibration:", 60)
    for node, name, value in (("/estimator", "spot_sigma", 2), ("/estimator", "stream.max_joint_speed", 1),
                              ("/spot_detector", "min_peak_dn", 30)):
        got = ros.client("set-param", node, name, str(value))
        assert got == {"successful": True, "reason": "", "type": "DOUBLE", "value": float(value)}, (name, got)
    # the checks still apply, and a wrong type is still refused with the reason
    got = ros.client("set-param", "/estimator", "spot_sigma", "-1")
    assert not got["successful"] and got["reason"] == "spot_sigma: expected >= 0 m, got -1.0", got
    assert got["value"] == 2.0
    got = ros.client("set-param", "/estimator", "markers", "1")
    assert not got["successful"] and got["reason"] == "markers: expected bool, got int", got
    got = ros.client("set-param", "/estimator", "spot_sigma", '"abc"')
    assert not got["successful"] and got["reason"] == "spot_sigma: expected float, got str", got
    assert ros.stop("estimator") == 0 and ros.stop("spot_detector") == 0
