"""The final estimate's noise as launch arguments: spot_sigma (m) and joint_sigma (rad) of
session.launch.py, hardware.launch.py and run-session reach the sequencer (estimate.spot_sigma,
estimate.joint_sigma) and the estimator (spot_sigma, joint_sigma: an Estimate request's 0 is its
parameter, and its online EKF's noise); empty, the default, leaves the parameter file's. Before
they were arguments, only a parameter file of one's own set them. A value a node would refuse is
refused before any node starts, in one line naming the argument."""

from __future__ import annotations

import json
import sys
import time

import pytest
import yaml

from ros_harness import EXAMPLE_ARM, ROBOT, ROOT, ros2_missing

NOISE = ("spot_sigma:=0.0005", "joint_sigma:=0.001")
SPOT_REFUSED = ("0.5 m is not a plausible spot noise for a camera on a screen (expected 1e-09 .. 0.05 m; lengths "
                "are in metres), or 0 to estimate it")
JOINT_REFUSED = ("5 rad is not a plausible joint-reading noise (expected more than 0, at most 0.035 rad; angles are "
                 "in radians), or 0 for none, or -1 for not given (estimated with the spot sigma when that is "
                 "estimated, else 0)")
REFUSALS = {("spot_sigma", "0.5"): f"spot_sigma: {SPOT_REFUSED}",     # millimetres typed as metres
            ("joint_sigma", "5"): f"joint_sigma: {JOINT_REFUSED}",    # degrees typed as radians
            ("spot_sigma", "1mm"): "spot_sigma: expected a number, got '1mm'"}

GRAPH = """import json, sys
from laser_calib_nodes import graph
spec, make = (graph.SESSION_ARGS, graph.session_nodes) if sys.argv[1] == "session" else \\
    (graph.HARDWARE_ARGS, graph.hardware_nodes)
values = {name: default for name, (default, _) in spec.items()}
values.update(dict(item.split(":=", 1) for item in sys.argv[2:]))
print(json.dumps({node.executable: node.params for node in make(values)}))"""


def screen_calibration(folder) -> str:
    """A valid screen calibration file, which hardware.launch.py reads before the noise arguments."""
    from laser_calib.vision.camera import default_camera, save_calibration
    save_calibration(default_camera().ideal_calibration(), folder / "screen.yaml")
    return str(folder / "screen.yaml")


def node_params(ros, tmp_path, launch: str, *args: str) -> dict:
    """The parameters each node of the launch file's graph is given with these arguments (no node started)."""
    given = [f"output_dir:={tmp_path / 'out'}", f"robot:={ROBOT}"]
    if launch == "hardware":
        given += [f"calibration:={screen_calibration(tmp_path)}", f"arm_params:={EXAMPLE_ARM}"]
    done = ros.run([sys.executable, "-c", GRAPH, launch, *given, *args])
    assert done.returncode == 0, done
    return json.loads(done.stdout)


@pytest.mark.parametrize("launch", ["session", "hardware"])
def test_both_graphs_give_the_noise_to_the_sequencer_and_the_estimator(ros, tmp_path, launch):
    params = node_params(ros, tmp_path, launch, *NOISE)
    assert (params["sequencer"]["estimate.spot_sigma"], params["sequencer"]["estimate.joint_sigma"]) == (0.0005, 0.001)
    assert (params["estimator"]["spot_sigma"], params["estimator"]["joint_sigma"]) == (0.0005, 0.001)
    # not given: neither node is given one, the parameter file's values stand
    params = node_params(ros, tmp_path, launch)
    assert not {"estimate.spot_sigma", "estimate.joint_sigma"} & set(params["sequencer"]), params
    assert not {"spot_sigma", "joint_sigma"} & set(params["estimator"]), params


def test_launch_gives_the_noise_to_the_sequencer_and_the_estimator(ros, tmp_path):
    if ros2_missing():
        pytest.skip(ros2_missing())
    out = tmp_path / "session"
    ros.start_command("launch", ["ros2", "launch", "laser_calib_nodes", "session.launch.py", f"output_dir:={out}",
                                 "poses:=12", "speed:=4.0", *NOISE])
    deadline = time.monotonic() + 120
    while not (out / "session.yaml").exists():  # the sequencer has declared its parameters and started the session
        assert ros.procs["launch"].poll() is None and time.monotonic() < deadline, ros.log("launch")[-3000:]
        time.sleep(0.2)
    sequencer = ros.client("parameters-of", "/sequencer")["values"]
    estimator = ros.client("parameters-of", "/estimator")["values"]
    assert (sequencer["estimate.spot_sigma"], sequencer["estimate.joint_sigma"]) == (0.0005, 0.001), sequencer
    assert (estimator["spot_sigma"], estimator["joint_sigma"]) == (0.0005, 0.001), estimator
    settings = yaml.safe_load((out / "session.yaml").read_text())["settings"]
    assert (settings["estimate.spot_sigma"], settings["estimate.joint_sigma"]) == (0.0005, 0.001), settings


def test_bad_noise_arguments_are_refused_before_any_node_starts(ros, tmp_path):
    """scripts/run-session's options, then `ros2 launch` of both launch files."""
    for (name, value), line in REFUSALS.items():
        out = tmp_path / f"{name}_{value}"
        result = ros.run([str(ROOT / "scripts" / "run-session"), "--no-setup", "--out", str(out),
                          f"--{name.replace('_', '-')}", value], timeout=120)
        assert result.returncode == 2 and result.stderr == f"run-session: {line}\n", result
        assert not out.exists()
    if ros2_missing():
        pytest.skip(ros2_missing())
    calibration = screen_calibration(tmp_path)
    launches = {"session_spot": ("session.launch.py", ("spot_sigma", "0.5"), []),
                "hardware_joint": ("hardware.launch.py", ("joint_sigma", "5"), [f"arm_params:={EXAMPLE_ARM}"])}
    for name, (launch, (arg, value), more) in launches.items():
        ros.start_command(name, ["ros2", "launch", "laser_calib_nodes", launch, f"output_dir:={tmp_path / name}",
                                 f"robot:={ROBOT}", f"calibration:={calibration}", f"{arg}:={value}", *more])
    for name, (_, given, _) in launches.items():
        assert ros.wait_exit(name, 60) != 0, ros.log(name)
        log = ros.log(name)
        errors = [line for line in log.splitlines() if "ERROR" in line]
        assert "process started" not in log and "Traceback" not in log, log
        assert len(errors) == 1 and REFUSALS[given] in errors[0], log
        assert not (tmp_path / name).exists()
