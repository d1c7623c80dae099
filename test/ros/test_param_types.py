"""A run-time parameter keeps its declared type: `ros2 param set /estimator stream.max_joint_speed 1`
sends an integer, which the node takes as 1.0 rad/s. Before, the parameter was stored as the integer
given (`ros2 param get`: 'Integer value is: 1', `ros2 param dump`: 1) while `ros2 param describe`
still said double. A spot sigma beyond what a camera can have (0.5: millimetres typed as metres) is
refused like the command line's --spot-sigma."""

from __future__ import annotations

from ros_harness import ROBOT


def test_an_integer_for_a_double_parameter_is_stored_as_a_double(ros):
    ros.start("estimator", "-p", f"robot:={ROBOT}")
    ros.start("spot_detector")
    ros.wait_log("estimator", "input 'samples'", 60)
    ros.wait_log("spot_detector", "calibration:", 60)
    for node, name, value in (("/estimator", "spot_sigma", 0), ("/estimator", "stream.max_joint_speed", 1),
                              ("/spot_detector", "min_peak_dn", 30)):
        got = ros.client("set-param", node, name, str(value))
        assert got == {"successful": True, "reason": "", "type": "DOUBLE", "value": float(value)}, (name, got)
    # the checks still apply, and a wrong type is still refused with the reason
    for value in ("-1", "0.5"):
        got = ros.client("set-param", "/estimator", "spot_sigma", value)
        assert not got["successful"] and got["reason"].startswith(
            f"spot_sigma: {float(value):g} m is not a plausible spot noise for a camera on a screen"), got
        assert got["value"] == 0.0
    got = ros.client("set-param", "/estimator", "spot_sigma", "0.002")
    assert got["successful"] and got["value"] == 0.002, got
    got = ros.client("set-param", "/estimator", "markers", "1")
    assert not got["successful"] and got["reason"] == "markers: expected bool, got int", got
    got = ros.client("set-param", "/estimator", "spot_sigma", '"abc"')
    assert not got["successful"] and got["reason"] == "spot_sigma: expected float, got str", got
    assert ros.stop("estimator") == 0 and ros.stop("spot_detector") == 0
