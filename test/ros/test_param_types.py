"""A run-time parameter keeps its declared type: `ros2 param set /estimator stream.max_joint_speed 1`
sends an integer, which the node takes as 1.0 rad/s. Before, the parameter was stored as the integer
given (`ros2 param get`: 'Integer value is: 1', `ros2 param dump`: 1) while `ros2 param describe`
still said double. A spot sigma beyond what a camera can have (0.5: millimetres typed as metres) is
refused like the command line's --spot-sigma, and a joint sigma that is no joint noise (-3) like
--joint-sigma (its 0, none, and -1, not given, are taken)."""

from __future__ import annotations

import os

import pytest

from ros_harness import ROBOT, workspace_env


def test_an_integer_for_a_double_parameter_is_stored_as_a_double(ros):
    ros.start("estimator", "-p", f"robot:={ROBOT}")
    ros.start("spot_detector")
    ros.wait_log("estimator", "input 'samples'", 60)
    ros.wait_log("spot_detector", "calibration:", 60)
    settings = [("/estimator", "spot_sigma", "0"), ("/estimator", "stream.max_joint_speed", "1"),
                ("/spot_detector", "min_peak_dn", "30"),
                # the checks still apply, and a wrong type is still refused with the reason
                ("/estimator", "spot_sigma", "-1"), ("/estimator", "spot_sigma", "0.5"),
                ("/estimator", "spot_sigma", "0.002"), ("/estimator", "markers", "1"),
                ("/estimator", "spot_sigma", '"abc"'),
                # joint_sigma: 0 (none) and -1 (not given) are its values, other negatives are not
                ("/estimator", "joint_sigma", "0"), ("/estimator", "joint_sigma", "-3"),
                ("/estimator", "joint_sigma", "-1"),
                # rclpy lets any node switch to simulated time while it runs: without /clock the timers of
                # arm_driver and camera_sim stopped, and the session ended blaming the arm driver
                ("/spot_detector", "use_sim_time", "true"), ("/estimator", "use_sim_time", "true")]
    got = ros.client("set-param", *[part for setting in settings for part in setting])
    for (_, name, value), result in zip(settings[:3], got):
        assert result == {"successful": True, "reason": "", "type": "DOUBLE", "value": float(value)}, (name, result)
    for value, result in zip(("-1", "0.5"), got[3:5]):
        assert not result["successful"] and result["reason"].startswith(
            f"spot_sigma: {float(value):g} m is not a plausible spot noise for a camera on a screen"), result
        assert result["value"] == 0.0
    assert got[5]["successful"] and got[5]["value"] == 0.002, got[5]
    assert not got[6]["successful"] and got[6]["reason"] == "markers: expected bool, got int", got[6]
    assert not got[7]["successful"] and got[7]["reason"] == "spot_sigma: expected float, got str", got[7]
    assert got[8] == {"successful": True, "reason": "", "type": "DOUBLE", "value": 0.0}, got[8]
    assert not got[9]["successful"] and got[9]["reason"].startswith(
        "joint_sigma: -3 rad is not a plausible joint-reading noise"), got[9]
    assert got[9]["value"] == 0.0
    assert got[10] == {"successful": True, "reason": "", "type": "DOUBLE", "value": -1.0}, got[10]
    for result in got[11:]:
        assert not result["successful"] and result["reason"].startswith("use_sim_time: set it when the node starts")
        assert result["value"] is False, result
    assert ros.stop("estimator") == 0 and ros.stop("spot_detector") == 0


def test_a_run_time_parameter_is_checked_by_its_declared_rule_and_none_is_left_without_an_attribute(monkeypatch):
    """A run-time parameter's rule is given once, to its declaration: the set check is that rule. A
    run-time parameter that dynamic() would not store anywhere (a `param set` answered 'successful'
    and changing nothing) is refused when the node is made."""
    monkeypatch.setenv("AMENT_PREFIX_PATH", workspace_env()["AMENT_PREFIX_PATH"])   # the package's files
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import rclpy
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from laser_calib_nodes import parameters
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=ros_domain())
    try:
        node = Node("rules", context=context)
        node.gain = parameters.declare(node, "gain", 1.0, "a gain", read_only=False, rule=parameters.positive)
        node.label = parameters.declare(node, "label", "a", "a label", read_only=False)
        with pytest.raises(ValueError, match=r"run-time parameters \['gain', 'label'\]"):
            parameters.dynamic(node, {"gain": "gain"})
        parameters.dynamic(node, {"gain": "gain", "label": "label"})
        refused = node.set_parameters([Parameter("gain", value=-2.0)])[0]
        assert not refused.successful and refused.reason == "gain: expected > 0, got -2.0" and node.gain == 1.0
        assert node.set_parameters([Parameter("gain", value=3)])[0].successful and node.gain == 3.0
        assert node.set_parameters([Parameter("label", value="b")])[0].successful and node.label == "b"
        node.destroy_node()
    finally:
        rclpy.shutdown(context=context)


def ros_domain() -> int:
    """A DDS domain of this worker no node of the other tests uses (ros_harness's blocks start at 10)."""
    return 2 + int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)


@pytest.mark.parametrize("node", ["sequencer", "estimator", "arm_driver", "spot_detector", "camera_sim"])
def test_help_prints_what_the_node_does_and_exits_0(ros, node):
    """`ros2 run laser_calib_nodes sequencer --help` started the node, which stopped on its first
    missing parameter ('error: parameter output_dir is empty', exit 2) with no usage at all."""
    from ros_harness import INSTALL
    result = ros.run([str(INSTALL / "laser_calib_nodes" / "lib" / "laser_calib_nodes" / node), "--help"], timeout=60)
    assert result.returncode == 0 and result.stderr == "", result
    assert result.stdout.startswith(f"{node}: ") and "--ros-args" in result.stdout, result.stdout
