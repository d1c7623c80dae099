"""arm_driver over the Dynamixel backend, against the Protocol 2.0 servo
emulator on a pseudo-terminal (test/dynamixel_emulator.py): joint states,
a goal reached, and a servo fault giving one log line, torque off, exit 1 (so does a servo whose
torque was switched off from outside, at the next goal), and ending a session's pose at once, named;
a servo that never confirms torque off on shutdown: one ERROR line, exit 5; a Ctrl-C
while the driver starts, after the servos' torque is on: torque off; a port or baud rate that
cannot be used: one line, exit 2."""

from __future__ import annotations

import math
import signal
import sys
import time
from pathlib import Path

from ros_harness import ROOT

ROBOT_4DOF = ROOT / "config" / "robots" / "manipulator_4dof.yaml"


def start_driver(ros, emulator):
    return ros.start("arm_driver", "-p", f"robot:={ROBOT_4DOF}", "-p", "backend:=dynamixel",
                     "-p", f"dynamixel.port:={emulator.port}", "-p", "dynamixel.baudrate:=57600",
                     "-p", "dynamixel.ids:=[1, 2, 3, 4]", "-p", "dynamixel.profile_velocity:=0",
                     "-p", "rate:=20.0", params=False)


def test_dynamixel_arm_driver(ros):
    from dynamixel_emulator import DynamixelEmulator
    tpr = 4096 / (2 * math.pi)
    with DynamixelEmulator(ids=(1, 2, 3, 4)) as emulator:
        proc = start_driver(ros, emulator)
        moved = ros.client("move", "0.2", "-0.1", "0.3", "0.0")
        assert all(abs(v) < 1e-3 for v in moved["first"])          # 2048 ticks = q 0
        assert abs(moved["reached"][0] - 0.2) < 0.01
        assert abs(emulator.present_position(1) - (2048 + round(0.2 * tpr))) <= 2
        assert emulator.torque_enabled(1)

        emulator.servos[3].silent = True                             # servo 3 stops answering
        deadline = time.monotonic() + 30
        while proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert proc.returncode == 1, ros.log("arm_driver")
        log = ros.log("arm_driver")
        assert "Traceback" not in log
        errors = [line for line in log.splitlines() if "Dynamixel servo 3" in line]
        assert errors and "arm stopped" in errors[0], log
        assert not emulator.torque_enabled(1) and not emulator.torque_enabled(2)  # safe stop


def test_a_servo_whose_torque_was_switched_off_is_named_at_the_next_goal(ros):
    """Torque switched off from outside the driver mid-session (Dynamixel Wizard, a brown-out
    reboot): the goals were taken silently, the arm never arrived and the session said 'arm not
    settled', blaming the arm. The driver now finds it at the next goal: one line naming the
    servo, the arm stopped, exit 1."""
    from dynamixel_emulator import DynamixelEmulator
    from ros_harness import CLIENT
    with DynamixelEmulator(ids=(1, 2, 3, 4)) as emulator:
        start_driver(ros, emulator)
        ros.client("move", "0.2", "-0.1", "0.3", "0.0")
        emulator.switch_torque_off(2)
        held = emulator.present_position(2)
        ros.start_command("move", [sys.executable, str(CLIENT), "move", "0.0", "0.0", "0.0", "0.0"])
        assert ros.wait_exit("arm_driver", 60) == 1, ros.log("arm_driver")
        log = ros.log("arm_driver")
        errors = [line for line in log.splitlines() if "Dynamixel servo 2" in line]
        assert len(errors) == 1 and "torque is off (switched off from outside this driver" in errors[0], log
        assert "arm stopped" in errors[0] and "Traceback" not in log, log
        assert emulator.present_position(2) == held and not any(emulator.torque_enabled(i) for i in (1, 3, 4))


def test_torque_off_not_confirmed_on_shutdown_is_an_error(ros):
    """Ctrl-C with servo 1 losing every torque-off write: the node retries, then logs one ERROR
    line through the ROS logger naming servo 1 and exits 5 (it exited 0 with a plain stderr line)."""
    from dynamixel_emulator import DynamixelEmulator
    with DynamixelEmulator(ids=(1, 2, 3, 4)) as emulator:
        start_driver(ros, emulator)
        ros.wait_log("arm_driver", "publishing at", 60)           # opened: torque on, publishing
        emulator.servos[1].lost_torque_offs = 100
        assert ros.stop("arm_driver") == 5, ros.log("arm_driver")
        log = ros.log("arm_driver")
        errors = [line for line in log.splitlines() if "torque off" in line]
        assert len(errors) == 1 and "[ERROR]" in errors[0] and "[arm_driver]" in errors[0], log
        assert "servo 1 did not confirm torque off" in errors[0] and "Traceback" not in log, log
        assert "Failed to publish log message" not in log, log   # to /rosout, whose context the signal shut
        assert emulator.torque_enabled(1) and not any(emulator.torque_enabled(i) for i in (2, 3, 4))


def start_glitching_session(ros, ticks: int, out, poses: int, *sequencer_args: str, overload: str = "") -> None:
    """glitching_arm.py (servos whose last one's reading glitches by ``ticks`` as each pose is
    measured, the second overloading on the way to step ``overload`` if given, and a camera of the
    true arm), arm_driver on its servos, and a sequencer."""
    ros.start_command("glitching_arm", [sys.executable, str(Path(__file__).with_name("glitching_arm.py")),
                                        str(ROBOT_4DOF), "1,2,3,4", str(ticks), *([overload] if overload else [])])
    ros.wait_log("glitching_arm", "\n", 60)
    port = ros.log("glitching_arm").splitlines()[0]
    ros.start("arm_driver", "-p", f"robot:={ROBOT_4DOF}", "-p", "backend:=dynamixel", "-p", f"dynamixel.port:={port}",
              "-p", "dynamixel.ids:=[1, 2, 3, 4]", "-p", "dynamixel.profile_velocity:=0", "-p", "rate:=50.0",
              # the emulator answers from a Python thread beside a ROS node: on a loaded machine later than
              # a USB adapter's 2 x 16 ms (the driver stopped the arm, 'no answer'), as test/hardware allows
              "-p", "dynamixel.latency_timer_ms:=250.0", params=False)
    ros.start("sequencer", "-p", f"robot:={ROBOT_4DOF}", "-p", f"output_dir:={out}", "-p", f"poses:={poses}",
              "-p", "estimate.mode:=none", "-p", "move.joint_speed:=2.0", *sequencer_args)


def test_a_reading_glitch_while_a_pose_is_measured_is_not_averaged_in(ros, tmp_path):
    """A session of arm_driver on servos whose last one's reading glitches by 300 ticks (0.46 rad)
    for two reads each time a pose has settled, while its frames are taken (glitching_arm.py;
    the servo stays put and the camera sees the true arm). The glitch was averaged into the
    sample: poses recorded up to 0.15 rad off, their spots the true arm's, exit 0 and not a word.
    Now the sequencer warns and takes the frames again once the arm has settled anew: every
    sample is at its pose."""
    import numpy as np
    from laser_calib.io.samples import load_samples
    from laser_calib.model.robot_file import load_robot
    from laser_calib.session.poses import load_poses
    poses = 4
    out = tmp_path / "out"
    start_glitching_session(ros, 300, out, poses)
    assert ros.wait_exit("sequencer", 180) == 0, ros.log("sequencer")[-3000:]
    log = ros.log("sequencer")
    # each pose's glitch lands among its frames unless the driver's DDS lagged the camera's 0.2 s of them
    assert 1 <= log.count("a joint reading left the goal while its frames were taken") <= poses, log
    assert "glitched pose" in ros.log("glitching_arm")
    robot = load_robot(ROBOT_4DOF)
    measured, planned = load_samples(out / "samples.csv", robot), load_poses(out / "poses.csv", robot)
    assert len(measured.q) == poses
    assert np.abs(measured.q - planned.q[:poses]).max() < 0.003, measured.q - planned.q[:poses]  # settle tolerance


def test_an_arm_driver_that_died_is_named_when_the_pose_times_out(ros, tmp_path):
    """arm_driver killed after the first pose: the sequencer waited out settle.timeout and said
    "arm not settled (... joint states since the command, every one stamped before it ... a
    driver stamping 0, or on another clock?)", blaming clocks. The line now says the joint
    states stopped."""
    start_glitching_session(ros, 0, tmp_path / "out", 4, "-p", "settle.timeout:=3.0")
    ros.wait_log("sequencer", "1/4 poses done", 120)
    ros.procs["arm_driver"].send_signal(signal.SIGKILL)
    assert ros.wait_exit("sequencer", 60) == 3, ros.log("sequencer")[-3000:]
    last = [line for line in ros.log("sequencer").splitlines() if line.strip()][-1]
    assert "arm not settled after 3 s" in last and "no joint state for" in last, last
    assert last.endswith("s: has the arm driver stopped?"), last


def test_a_fault_that_stops_the_arm_ends_the_pose_at_once_naming_it(ros, tmp_path):
    """A servo overloads on the way to the second pose: arm_driver stops the arm, names the fault
    in its own log and exits 1. The sequencer waited out settle.timeout (60 s here) and said 'arm
    not settled ... has the arm driver stopped?', the cause in another log. The driver's ERROR on
    /diagnostics now ends the wait at once, and the sequencer's last line names the fault."""
    start_glitching_session(ros, 0, tmp_path / "out", 4, "-p", "settle.timeout:=60.0", overload="1")
    ros.wait_log("sequencer", "1/4 poses done", 120)
    assert ros.wait_exit("arm_driver", 60) == 1, ros.log("arm_driver")[-3000:]
    assert ros.wait_exit("sequencer", 20) == 3, ros.log("sequencer")[-3000:]   # well within settle.timeout
    last = [line for line in ros.log("sequencer").splitlines() if line.strip()][-1]
    assert "pose 2/4 (id 1): the arm stopped on a fault, /arm_driver: arm: Dynamixel servo 2" in last, last
    assert "overload" in last and "arm stopped (no joint state for" in last, last


STARTS_INTERRUPTED = """import sys, rclpy
from laser_calib_nodes.arm_driver import ArmDriver
def interrupted(*_args, **_kwargs):
    raise KeyboardInterrupt
ArmDriver.create_timer = interrupted  # the signal at that instant
rclpy.init(args=sys.argv[1:])
try:
    ArmDriver()
except KeyboardInterrupt:
    print("interrupted")
finally:
    rclpy.shutdown()"""


def test_a_ctrl_c_while_the_driver_starts_leaves_no_servo_on(ros):
    """A stop signal between the backend's open (torque on) and the end of ArmDriver's constructor
    (its publishers, subscription and timer): common.run never gets the node to close it, so the
    constructor does. The signal is stood in for by the timer's creation raising KeyboardInterrupt."""
    import sys

    from dynamixel_emulator import DynamixelEmulator
    with DynamixelEmulator(ids=(1, 2, 3, 4)) as emulator:
        out = ros.run([sys.executable, "-c", STARTS_INTERRUPTED, "--ros-args", "-p", f"robot:={ROBOT_4DOF}",
                       "-p", "backend:=dynamixel", "-p", f"dynamixel.port:={emulator.port}",
                       "-p", "dynamixel.ids:=[1, 2, 3, 4]"], timeout=60)
        assert out.stdout.strip() == "interrupted", out
        assert [emulator.torque_enabled(i) for i in (1, 2, 3, 4)] == [False] * 4


def test_a_port_or_baud_rate_that_cannot_be_used_is_a_setting_exit_2(ros, tmp_path):
    """A port that names no device, or a baud rate the adapter cannot take, is a setting to
    correct: one line and exit 2, as the other bad parameters (it was exit 1, a bus fault's); so is
    a servo whose Max Position Limit is inside its joint's range (it was "arm not settled" later)."""
    from dynamixel_emulator import DynamixelEmulator
    with DynamixelEmulator(ids=(1, 2, 3, 4)) as emulator:
        for name, port, baud, said in (("no_port", tmp_path / "ttyUSB9", 57600, "cannot open"),
                                       ("bad_baud", emulator.port, 12345, "unsupported baud rate 12345")):
            ros.start(name, "-p", f"robot:={ROBOT_4DOF}", "-p", "backend:=dynamixel", "-p", f"dynamixel.port:={port}",
                      "-p", f"dynamixel.baudrate:={baud}", "-p", "dynamixel.ids:=[1, 2, 3, 4]", node="arm_driver",
                      params=False)
            assert ros.wait_exit(name, 60) == 2, ros.log(name)
            lines = ros.log(name).strip().splitlines()
            assert len(lines) == 1 and said in lines[0] and str(port) in lines[0], lines
        assert not any(emulator.torque_enabled(i) for i in (1, 2, 3, 4))
        # a servo whose own limits would ignore the joint's goals: a setting too, said before any torque is on
        from dynamixel_emulator import ADDR_MAX_POSITION_LIMIT
        emulator.servos[3].put(ADDR_MAX_POSITION_LIMIT, 4, 2100)
        ros.start("servo_limits", "-p", f"robot:={ROBOT_4DOF}", "-p", "backend:=dynamixel",
                  "-p", f"dynamixel.port:={emulator.port}", "-p", "dynamixel.ids:=[1, 2, 3, 4]", node="arm_driver",
                  params=False)
        assert ros.wait_exit("servo_limits", 60) == 2, ros.log("servo_limits")
        lines = ros.log("servo_limits").strip().splitlines()
        assert len(lines) == 1 and "Dynamixel servo 3: joint3's range is ticks" in lines[0], lines
        assert "beyond the servo's Min/Max Position Limit 0 .. 2100" in lines[0], lines
        assert not any(emulator.torque_enabled(i) for i in (1, 2, 3, 4))
