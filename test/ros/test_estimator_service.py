"""The estimator's Estimate service: bad requests are refused in one line, and
several concurrent clients are all served; the node keeps serving."""

from __future__ import annotations

import json
import sys

from ros_harness import CLIENT, ROBOT


def test_bad_requests_and_concurrent_clients(ros):
    ros.start("estimator", "-p", f"robot:={ROBOT}")
    # 15 requests in flight at once, every one answered, none sent twice (the client fails when one
    # is not): the services profile's depth of 10 dropped the oldest waiting one
    out = ros.client("bad-and-concurrent", str(ROBOT))
    expected_refusals = {
        "empty": "no samples",
        "wrong_joint_count": "6 joint positions",
        "nan_joint": "joint_positions[2] is not finite",
        "nan_spot": "non-finite",
        "bad_method": "gauss",
        "bad_method_nothing_accumulated": "method: expected one of lm, ekf, got 'gauss'",  # the request's fault first
        # the request's samples were dropped without a word, the accumulated ones estimated
        "samples_and_accumulated": "use_accumulated is true and the request holds 30 samples and 0 test samples",
        "negative_sigma": "spot_sigma",
        "too_few": "",
        "nan_test_joint": "request: test sample 2 (pose 101): joint_positions[0] is not finite",
        "unseen_test": "request: test_samples: no spot is measured in the test set",
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
    # test_samples: held out, never fitted (the same estimate), the estimate's test figures
    assert out["tested"]["errors"] == goods[0]["errors"] and out["tested"]["sample_count"] == 30
    assert json.loads(out["tested"]["result_json"])["spot_error"]["test"]["after"]["all"]["n"] == 10
    assert "test" not in json.loads(goods[0]["result_json"])["spot_error"]
    assert out["good_ekf"]["success"], out["good_ekf"]["message"]
    assert ros.procs["estimator"].poll() is None  # still alive
    reset = ros.client("reset")
    assert reset["success"]
    assert ros.stop("estimator") == 0  # Ctrl-C: exit 0
    assert "Traceback" not in ros.log("estimator")


def test_the_estimate_applies_the_learned_compensator(ros, tmp_path):
    """The node's 'compensator' parameter (a diagnosis's compensator.json): every estimate request
    fits and predicts with its offsets, as `laser-calib estimate --compensator` does (one code path)."""
    import numpy as np
    from laser_calib.cli.main import main
    from laser_calib.diagnosis.compensator import Compensator, load_compensator
    from laser_calib.diagnosis.detector import Basis
    from laser_calib.estimation.estimate import EstimateOptions
    from laser_calib.io.samples import load_samples
    from laser_calib.model.robot_file import load_robot
    from laser_calib.report.calibration import calibrate

    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-7dof", "--seed", "0", "--out", str(sim)]) == 0
    robot, samples = load_robot(sim / "robot_nominal.yaml"), load_samples(sim / "case3_cal.csv")
    # A joint-2 offset following q1 (2 mrad peak): a regression of the detector's family.
    basis = Basis.of(samples.q[:, :1], 1)
    coef = 2e-3 * np.sin(np.arange(basis(samples.q[:1, :1]).shape[1]))[None, :]
    path = tmp_path / "compensator.json"
    Compensator(("q1",), ("theta2",), np.array([True]), basis, coef, 0.2, tuple(robot.param_names),
                np.zeros(robot.n_params)).save(path)
    ros.start("estimator", "-p", f"robot:={sim / 'robot_nominal.yaml'}", "-p", f"compensator:={path}")
    out = ros.client("estimate-csv", str(sim / "case3_cal.csv"))
    assert out["success"], out["message"]
    result = json.loads(out["result_json"])
    assert result["compensator"] == {"targets": ["theta2"], "heldout_gain": 0.2, "file": str(path)}
    used = result["options"]
    options = EstimateOptions(spot_sigma=used["spot_sigma"], joint_sigma=used["joint_sigma"], robust=used["robust"])
    core = calibrate(robot, samples, options, compensator=load_compensator(path)).to_json()
    without = calibrate(robot, samples, options).to_json()
    assert result["spot_error"] == core["spot_error"] != without["spot_error"]
    assert ros.stop("estimator") == 0


def test_the_joint_sigma_parameter_and_request_field_give_the_joint_reading_noise(ros, tmp_path):
    """The estimator had no joint_sigma: with spot_sigma given the joint-reading noise was 0, and an arm
    with noisy encoders got standard deviations too small. Its parameter joint_sigma (and an Estimate
    request's, 0 there being the node's) is the command line's --joint-sigma: a given sigma is used, not
    estimated; a value that is no joint noise is refused with the reason (`ros2 param set`, a request),
    the parameter then unchanged. (Its 0, none, and -1, not given: test/core/test_cli.py.)"""
    import pytest
    from laser_calib.cli.main import main
    from ros_harness import ros2_missing
    if ros2_missing():
        pytest.skip(ros2_missing())
    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-7dof", "--seed", "0", "--out", str(sim)]) == 0
    ros.start("estimator", "-p", f"robot:={sim / 'robot_nominal.yaml'}", "-p", "joint_sigma:=0.0005",
              "-p", "markers:=false")
    ros.wait_log("estimator", "input 'samples'", 60)
    # --no-daemon: one process discovers the node (--timeout: waits for it), without starting the daemon (2 s more)
    refused = ros.ros2("param", "set", "--no-daemon", "--timeout", "30", "/estimator", "joint_sigma", "-3")
    said = refused.stdout + refused.stderr
    assert "Setting parameter failed: joint_sigma: -3 rad is not a plausible joint-reading noise" in said, refused
    assert "or 0 for none, or -1 for not given" in said, refused
    node, own, bad = ros.client("estimate-joint-sigma", str(sim / "case3_cal.csv"), "0", "0.001", "-3")
    assert node["success"] and own["success"], (node["message"], own["message"])
    # the spot sigma (node and request 0) estimated, the joint sigma given: the parameter's, then the request's
    assert node["spot_sigma_estimated"] and own["spot_sigma_estimated"]
    assert node["joint_sigma_rad"] == 0.0005 and not node["joint_sigma_estimated"], node
    assert own["joint_sigma_rad"] == 0.001 and not own["joint_sigma_estimated"], own
    assert not bad["success"] and bad["message"].startswith("joint_sigma: -3 rad is not a plausible"), bad
    assert ros.stop("estimator") == 0
    assert "Traceback" not in ros.log("estimator")


def test_an_estimate_that_is_no_calibration_answers_success_false(ros, tmp_path):
    """What the command line refuses or exits 3 for, the service answers with success false:
    samples whose spot columns are swapped (nothing estimated), and a robot file that marks a
    revolute joint prismatic (the fit drops measurements: NOT A CALIBRATION, the fields filled)."""
    from dataclasses import replace

    from laser_calib.io.samples import load_samples, save_samples
    from wrong_robot import prismatic_mismatch

    sim, wrong = prismatic_mismatch(tmp_path)
    samples = load_samples(sim / "samples.csv")
    save_samples(replace(samples, spots=samples.spots[:, [1, 0]]), tmp_path / "swapped.csv")

    ros.start("estimator", "-p", f"robot:={sim / 'robot_nominal.yaml'}")
    swapped = ros.client("estimate-csv", str(tmp_path / "swapped.csv"))
    assert not swapped["success"] and "the spot columns look assigned wrongly" in swapped["message"]
    assert swapped["result_json"] == ""
    assert ros.stop("estimator") == 0

    ros.start("estimator", "-p", f"robot:={wrong}")
    lost = ros.client("estimate-csv", str(sim / "samples.csv"))
    assert not lost["success"] and "NOT A CALIBRATION: the fit lost" in lost["message"]
    assert json.loads(lost["result_json"])["robot"]  # the fields show where the fit went
    assert ros.stop("estimator") == 0


def finished_session(folder):
    """A session folder whose session.yaml says finished, with its (stand-in) result.json."""
    from laser_calib.session.folder import SessionDir
    folder.mkdir()
    SessionDir(folder).set_info(state="finished")
    (folder / "result.json").write_text("{}")
    return folder


def test_an_output_dir_that_cannot_be_written_is_refused_in_one_line(ros, tmp_path):
    """An Estimate request whose output_dir cannot be made (under /proc, or an existing file),
    holds a finished session (whose results it replaced, the folder then disagreeing with itself),
    or is relative (it was resolved in the estimator's working directory, not the caller's):
    success false, one line naming output_dir, no traceback, nothing in the session changed,
    nothing written; the node serves the next request."""
    from pathlib import Path

    from laser_calib.cli.main import main

    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-7dof", "--seed", "0", "--out", str(sim)]) == 0
    a_file = tmp_path / "a_file"
    a_file.write_text("not a folder\n")
    finished = finished_session(tmp_path / "finished")
    relative = f"relative-{tmp_path.name}"  # the estimator runs in this process's working directory
    ros.start("estimator", "-p", f"robot:={sim / 'robot_nominal.yaml'}")
    for name, out_dir in (("proc", "/proc/nope"), ("file", str(a_file)), ("under_file", str(a_file / "report")),
                          ("finished_session", str(finished)), ("relative", relative)):
        out = ros.client("estimate-csv", str(sim / "case3_cal.csv"), out_dir)
        message = out["message"]
        assert out["success"] is False, (name, message)
        assert message.startswith("output_dir: ") and out_dir in message and "\n" not in message, (name, message)
        assert "internal error" not in message, (name, message)
    assert sorted(p.name for p in finished.iterdir()) == ["result.json", "session.yaml"]
    assert (finished / "result.json").read_text() == "{}"
    assert not (Path.cwd() / relative).exists()
    good = ros.client("estimate-csv", str(sim / "case3_cal.csv"), str(tmp_path / "report"))
    assert good["success"], good["message"]
    assert (tmp_path / "report" / "report.md").exists()
    assert ros.stop("estimator") == 0
    assert "Traceback" not in ros.log("estimator"), ros.log("estimator")


def test_ctrl_c_during_an_estimate_answers_it_and_exits_0(ros, tmp_path):
    """Ctrl-C while an Estimate request with its diagnosis runs: the node was destroyed between
    the callback's return and rclpy's send of its response ('exception never retrieved: cannot use
    Destroyable' on stderr), and the client was never answered. Now the cleanup waits for it. The
    line the request logs after the stop reaches the console without rcl's complaint that /rosout,
    whose context the signal shut, could not take it."""
    from laser_calib.io.samples import save_samples
    from laser_calib.sim.simulation import paper_session
    save_samples(paper_session("paper-7dof", seed=1).samples, tmp_path / "samples.csv")
    ros.start("estimator", "-p", f"robot:={ROBOT}")
    ros.start_command("client", [sys.executable, str(CLIENT), "estimate-csv-diagnose", str(tmp_path / "samples.csv")])
    ros.wait_log("estimator", "then the diagnosis", 120, watch="client")
    assert ros.stop("estimator") == 0
    log = ros.log("estimator")
    assert "Traceback" not in log and "never retrieved" not in log, log[-3000:]
    assert "diagnosis: " in log.split("then the diagnosis")[-1], log[-3000:]
    assert "Failed to publish log message" not in log, log[-3000:]
    assert ros.wait_exit("client", 60) == 0, ros.log("client")
    answer = json.loads(ros.log("client").strip().splitlines()[-1])
    assert answer["success"] and json.loads(answer["diagnosis_json"])["verdict"], answer["message"]


def test_ctrl_c_during_a_calibrate_goal_exits_0_without_a_traceback(ros):
    """Ctrl-C while a Calibrate goal's diagnosis runs (a stage cannot be stopped): the node's
    cleanup destroyed it under the running stage, which then published its feedback on a
    destroyed node (RCLError traceback) and left the goal's state unset. Now the goal is
    aborted and the server destroyed first: exit 0, no traceback."""
    ros.start("estimator", "-p", f"robot:={ROBOT}")
    assert ros.client("calibrate-until-diagnosis", str(ROBOT))["stages"] == ["estimate", "diagnosis"]
    assert ros.stop("estimator") == 0
    log = ros.log("estimator")
    assert "Traceback" not in log and "RCLError" not in log and "Goal state not set" not in log, log[-3000:]



def test_request_samples_are_read_by_joint_name(ros):
    """A Sample's joint_positions follow its joint_names: a client filling it from joint_states
    keeps the driver's order (a UR driver lists shoulder_pan_joint last). Before, the positions
    were taken in the message's order whatever the names said: the reversed set was fitted as
    readings of other joints (mean spot error 870 mm, refused as not a calibration)."""
    ros.start("estimator", "-p", f"robot:={ROBOT}", "-p", "markers:=false")
    out = ros.client("samples-by-name", str(ROBOT))
    for name in ("unnamed", "named", "reversed"):
        assert out[name]["success"], (name, out[name]["message"])
    assert out["named"]["errors"] == out["unnamed"]["errors"]
    assert out["reversed"]["errors"] == out["unnamed"]["errors"]  # the same numbers, reordered exactly
    assert not out["one_unknown"]["success"]
    assert "sample 1 (pose 0)" in out["one_unknown"]["message"]
    assert "joint 'joint7' (parameter joint_names) is not in the sample's joint_names" in out["one_unknown"]["message"]
    assert not out["count_mismatch"]["success"]
    assert "6 joint_names but 7 joint_positions" in out["count_mismatch"]["message"]
    assert ros.stop("estimator") == 0


def test_a_sample_naming_a_joint_twice_is_refused(ros):
    """A Sample whose joint_names list joint1 twice holds two readings of it, and nothing says which
    is the joint's. The first was taken, silently: with the wrong one first (0.01 rad off), a
    calibration was answered, success true, theta1 fitted to the wrong reading."""
    ros.start("estimator", "-p", f"robot:={ROBOT}", "-p", "markers:=false")
    out = ros.client("samples-named-twice", str(ROBOT))
    for case in ("twice_last", "twice_first"):
        assert not out[case]["success"], (case, out[case]["message"])
        assert out[case]["message"].startswith("request: sample 1 (pose 0): joint 'joint1'"), out[case]["message"]
        assert "named twice in the sample's joint_names" in out[case]["message"], out[case]["message"]
        assert out[case]["errors"] == []  # no calibration
    assert out["once"]["success"], out["once"]["message"]  # the node still serves
    assert ros.stop("estimator") == 0
    assert "Traceback" not in ros.log("estimator")


def test_a_robot_file_without_lasers_is_refused_at_start(ros, tmp_path):
    """A robot file may leave out the lasers (an arm measured by another sensor, robot_file.py); the
    estimator fits laser spots, and with such a file it started and answered every request
    'internal error: ValueError: operands could not be broadcast ...' with a traceback in its log
    (the Calibrate action: an empty message). It now exits 2 at start, in one line, as the command
    line refuses spot samples for it."""
    text = ROBOT.read_text()
    robot = tmp_path / "no_lasers.yaml"
    robot.write_text(text[:text.index("\nslm:")] + "\n")
    ros.start("estimator", "-p", f"robot:={robot}")
    assert ros.wait_exit("estimator", 60) == 2
    log = ros.log("estimator")
    assert f"error: parameter robot: {robot}: spot samples need the robot's lasers" in log, log
    assert "Traceback" not in log, log


def _execute_calibrate_goal(cancel_requested: bool, request_sets: str) -> dict:
    """CalibrateServer.execute run on one goal in a child process, without rclpy.init or an
    ActionServer: stand-ins for the node and rclpy's goal handle (is_cancel_requested fixed to
    ``cancel_requested``) and request_sets replaced by ``request_sets``, Python source defining it.
    The result's success and message, what happened to the goal and the node's log."""
    import subprocess
    import textwrap

    from ros_harness import workspace_env
    program = textwrap.dedent(f"""
        import json, threading
        from laser_calib_interfaces.action import Calibrate
        from laser_calib_nodes import calibrate

        class Logger:
            lines = []
            def info(self, message): self.lines.append(("INFO", message))
            def warning(self, message): self.lines.append(("WARN", message))
            def error(self, message): self.lines.append(("ERROR", message))

        class Node:
            spot_sigma = 0.0
            logger = Logger()
            def get_logger(self): return self.logger

        class Goal:
            request, ended, is_cancel_requested = Calibrate.Goal(use_accumulated=True), None, {cancel_requested}
            def abort(self): self.ended = "aborted"
            def canceled(self): self.ended = "canceled"
            def publish_feedback(self, feedback): pass
    """) + textwrap.dedent(request_sets) + textwrap.dedent("""
        calibrate.request_sets = request_sets
        server = calibrate.CalibrateServer.__new__(calibrate.CalibrateServer)
        server.node, server.Calibrate, server.busy = Node(), Calibrate, threading.Lock()
        goal = Goal()
        result = server.execute(goal)
        print(json.dumps({"success": result.success, "message": result.message, "ended": goal.ended,
                          "log": Node.logger.lines}))
    """)
    run = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=60,
                         env=workspace_env())
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_the_calibrate_action_says_why_an_unexpected_error_aborted_it():
    """An error the estimate does not expect (a bug; seen with a robot file without lasers, refused at
    start since) escaped the action's execute callback: rclpy logged it and aborted the goal with an
    empty message, so the client was not told why. The action now answers as ~/estimate does:
    'internal error: TYPE: what', success false, the goal aborted, the traceback in the log."""
    out = _execute_calibrate_goal(False, """
        def request_sets(node, request):
            raise ValueError("operands could not be broadcast together")
    """)
    assert out["success"] is False and out["ended"] == "aborted", out
    assert out["message"] == "internal error: ValueError: operands could not be broadcast together", out
    assert out["log"][0][0] == "ERROR" and "Traceback" in out["log"][0][1], out


def test_a_calibrate_goal_canceled_while_it_waited_computes_nothing():
    """Goals are served one at a time: one canceled while another ran used to start its estimate
    once the server was free, and to be canceled, at best, before its diagnosis."""
    out = _execute_calibrate_goal(True, """
        def request_sets(node, request):
            raise AssertionError("the samples of a canceled goal were gathered")
    """)
    assert out["success"] is False and out["ended"] == "canceled", out
    assert out["message"] == "canceled before the estimate started; nothing was computed", out


def test_samples_of_a_longer_arm_are_refused_once_each_and_the_answer_says_so(ros):
    """A bag of another (longer) arm replayed into the estimator: each sample arrives on both of its
    subscriptions (transient local and volatile) and its refusal was logged twice; the request then
    said only that no samples had been accumulated, not that all had been refused."""
    four = ROBOT.parent / "manipulator_4dof.yaml"
    ros.start("estimator", "-p", f"robot:={four}")
    out = ros.client("longer-arm-samples", "3")
    assert out["success"] is False, out
    assert out["message"] == ("request: use_accumulated is true but no samples have been accumulated yet; the 3 "
                              "received were refused, the first: sample (pose 0): joint 'joint5' is beyond the 4 "
                              "joints of parameter joint_names (joint1 .. joint4): the readings of a longer arm?"), out
    refusals = [line for line in ros.log("estimator").splitlines() if "ignored: sample" in line]
    assert len(refusals) == 3, ros.log("estimator")
