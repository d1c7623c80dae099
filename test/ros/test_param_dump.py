"""`ros2 param dump` of a node holds its parameters. The list parameters without a default
(arm_driver's joint_names and dynamixel.*, the sequencer's and the estimator's joint_names) were
declared typed but without a value, and rclpy's get_parameters service answers no value at
all when one asked for has none: the dump of such a node was `ros__parameters: {}`
(ros2/ros2cli#936). They are now declared with an empty list; a given list still works, and a
list of the wrong type is refused in one line."""

from __future__ import annotations

from ros_harness import ROBOT


def test_every_parameter_has_a_value(ros, tmp_path):
    ros.start("arm_driver", "-p", f"robot:={ROBOT}")
    ros.start("estimator", "-p", f"robot:={ROBOT}")
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={tmp_path / 'session'}",
              "-p", "wait_timeout:=600.0")
    ros.wait_log("arm_driver", "publishing at", 60)
    ros.wait_log("estimator", "input 'samples'", 60)
    for node, lists in (("/arm_driver", ("joint_names", "dynamixel.ids", "dynamixel.min")),
                        ("/estimator", ("joint_names",)), ("/sequencer", ("joint_names",))):
        got = ros.client("parameters-of", node)
        assert len(got["values"]) == len(got["names"]) > 5, (node, got)  # was: no value at all
        assert got["values"]["robot"] == str(ROBOT), (node, got)
        for name in lists:
            assert got["values"][name] == [], (node, name, got["values"][name])
        if node == "/sequencer":  # the launch files refuse these as their arguments (arguments.py): all of them
            from laser_calib.session.folder import PLAN_DEFAULTS
            from laser_calib_nodes.arguments import SEQUENCER_PARAMETERS
            ours = {name for name in got["names"] if name not in ("use_sim_time", "start_type_description_service")
                    and not name.startswith(("robot", "qos_overrides"))}
            assert ours == set(SEQUENCER_PARAMETERS) | set(PLAN_DEFAULTS), ours ^ (set(SEQUENCER_PARAMETERS) |
                                                                                 set(PLAN_DEFAULTS))
    assert ros.stop("sequencer") == 0 and ros.stop("arm_driver") == 0 and ros.stop("estimator") == 0
    # the dump loads back: the empty lists arrive unset and are taken as empty
    dump = tmp_path / "dump.yaml"
    dump.write_text("/arm_driver:\n  ros__parameters:\n    robot: " + str(ROBOT) + "\n    joint_names: []\n"
                    "    dynamixel:\n      ids: []\n      min: []\n")
    ros.start("arm_again", "--params-file", str(dump), node="arm_driver", params=False)
    ros.wait_log("arm_again", "publishing at", 60)
    assert ros.stop("arm_again") == 0


def test_a_list_parameter_given_or_refused(ros):
    names = [f"j{i}" for i in range(1, 8)]
    ros.start("arm_names", "-p", f"robot:={ROBOT}", "-p", f"joint_names:=[{', '.join(names)}]", node="arm_driver")
    ros.start("arm_numbers", "-p", f"robot:={ROBOT}", "-p", "joint_names:=[1, 2, 3, 4, 5, 6, 7]", node="arm_driver")
    assert ros.wait_exit("arm_numbers", 60) == 2
    last = [line for line in ros.log("arm_numbers").splitlines() if line.strip()][-1]
    assert last == "error: parameter joint_names: expected a list of str, got [1, 2, 3, 4, 5, 6, 7]", last
    ros.wait_log("arm_names", "publishing at", 60)
    assert ros.client("parameters-of", "/arm_driver")["values"]["joint_names"] == names
    assert ros.client("move", *["0.0"] * 7)["names"] == names
    assert ros.stop("arm_names") == 0
