"""scripts/run-session owns its session: a second session on the live folder is
refused in one line naming the owner's PID, and SIGKILL of run-session leaves no
node running (they die with their launcher) and no stale lock. Runs without
ros2cli (run-session starts laser_calib_nodes.graph, not `ros2 launch`)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from ros_harness import ROOT, Ros, children
from test_crash_resume import csv_rows

RUN_SESSION = str(ROOT / "scripts" / "run-session")


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_second_session_refused_and_sigkill_leaves_no_node(ros: Ros, tmp_path):
    from laser_calib.session.lock import LOCK_FILE, SessionLock
    out = tmp_path / "session"
    args = [RUN_SESSION, "--no-setup", "--out", str(out), "--poses", "10", "--speed", "4.0"]
    proc = ros.start_command("run-session", args)
    deadline = time.monotonic() + 300
    while not (out / "samples.csv").exists():
        assert proc.poll() is None, ros.log("run-session")
        assert time.monotonic() < deadline, ros.log("run-session")
        time.sleep(0.1)
    owner = int((out / LOCK_FILE).read_text())
    nodes = [pid for pid in children(proc.pid) if b"lib/laser_calib_nodes/" in Path(f"/proc/{pid}/cmdline").read_bytes()]
    assert len(nodes) == 5, nodes

    second = ros.run(args, timeout=120)
    lines = second.stderr.strip().splitlines()
    assert second.returncode == 2 and len(lines) == 1 and f"PID {owner}" in lines[0], second

    os.kill(proc.pid, signal.SIGKILL)
    deadline = time.monotonic() + 30
    while any(alive(pid) for pid in nodes + [owner]) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert not [pid for pid in nodes + [owner] if alive(pid)], ros.log("run-session")
    SessionLock(out).acquire()  # no stale lock: the folder can be resumed


def test_lock_held_by_the_parent_is_the_sessions_own(tmp_path):
    """A sequencer started by the session's launcher finds the lock held by its parent and
    goes on; any other process is refused, naming the owner."""
    import subprocess
    import sys
    import pytest
    from laser_calib.session.lock import SessionBusy, SessionLock
    folder = tmp_path / "new" / "session"
    held = SessionLock(folder)
    held.acquire()                                  # creates the folder
    with pytest.raises(SessionBusy, match=f"in use by the session of PID {os.getpid()} ") as busy:
        SessionLock(folder).acquire()               # this very process is not its own parent
    assert busy.value.owner == os.getpid()
    child = subprocess.run([sys.executable, "-c", "import sys; from laser_calib.session.lock import SessionLock; "
                            "SessionLock(sys.argv[1]).acquire(); print('through')", str(folder)],
                           capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT / "ros2_ws" / "src"
                                                                                             / "laser_calib")})
    assert child.returncode == 0 and child.stdout.strip() == "through", child.stderr
    held.release()


@pytest.mark.parametrize("stop", ["ctrl-c", "kill"])
def test_ctrl_c_stops_every_node_cleanly(ros: Ros, tmp_path, stop):
    """ctrl-c: the terminal's, SIGINT to the whole process group: the runner forwards it, the nodes
    get it twice. kill: a supervisor's or `kill PID`'s SIGTERM to run-session alone, which bash held
    until its foreground child ended: the session went on to its end."""
    out = tmp_path / "session"
    proc = ros.start_command("run-session", [RUN_SESSION, "--no-setup", "--out", str(out), "--poses", "10",
                                             "--speed", "4.0"])
    deadline = time.monotonic() + 300
    # Measuring: the first pose's line in the sequencer's log. A line logged in the very instant of the stop
    # goes to /rosout after rclpy's signal thread has shut the context ('Failed to publish log message to
    # rosout'): rclpy shuts it from its own thread, and no node can order its lines around that. So the stop
    # comes between two lines: not as samples.csv opens (the other nodes still logged their first lines: 4 of
    # 18 runs), nor as its first row is written (the sequencer's 'measured' line follows it at once: CI, once).
    log = out / "logs" / "sequencer.log"
    while not (log.exists() and "1/10 poses done" in log.read_text()):
        assert proc.poll() is None and time.monotonic() < deadline, ros.log("run-session")
        time.sleep(0.1)
    nodes = [pid for pid in children(proc.pid) if b"lib/laser_calib_nodes/" in Path(f"/proc/{pid}/cmdline").read_bytes()]
    if stop == "ctrl-c":
        ros.interrupt("run-session")
    else:
        os.kill(proc.pid, signal.SIGTERM)
    assert ros.wait_exit("run-session", 30) == 130, ros.log("run-session")
    assert not [pid for pid in nodes if alive(pid)]
    logs = {path.name: path.read_text() for path in (out / "logs").glob("*.log")}
    assert len(logs) == 5 and not [name for name, text in logs.items() if "Traceback" in text], logs
    assert not [name for name, text in logs.items() if "Failed to publish log message" in text], logs
    assert "run again with the same --out to resume" in ros.log("run-session")


def test_a_refused_plan_is_one_line_on_stderr_and_leaves_no_folder(ros: Ros, tmp_path):
    """--poses 0 or --span medium: the sequencer's error line came on stdout (stderr empty) after
    every node had started, and the folder was left holding .lock, logs/ and robot_true.yaml. Now
    the graph refuses the plan before it takes the folder."""
    for option, value, said in (("--poses", "0", "poses: need at least one pose, got 0"),
                                ("--span", "medium", "span: expected 'small' or 'whole', got 'medium'")):
        out = tmp_path / option.strip("-")
        result = ros.run([RUN_SESSION, "--no-setup", "--out", str(out), option, value], timeout=120)
        assert result.returncode == 2 and result.stderr == f"run-session: {said}\n", result
        assert "error" not in result.stdout and not out.exists(), result


def test_a_start_the_sequencer_refuses_is_said_on_stderr_and_leaves_no_folder(ros: Ros, tmp_path):
    """A refusal only the sequencer makes (resume:=yes with no session to resume): its error line
    on stderr, not among the results, and no folder of this run's left (nothing was measured)."""
    out = tmp_path / "new" / "session"
    result = ros.run([RUN_SESSION, "--no-setup", "--out", str(out), "--", "-p", "resume:='yes'"], timeout=120)
    assert result.returncode == 2, result
    assert result.stderr.strip().splitlines()[-1] == f"error: {out}: no session to resume", result
    assert "error" not in result.stdout and not (tmp_path / "new").exists(), result


def test_env_sh_puts_the_wheels_packages_on_the_ament_path(ros: Ros):
    """ament_index (ros2 interface, launch) finds the wheels' packages after `source scripts/env.sh`."""
    found = ros.run([str(ROOT / ".venv" / "bin" / "python"), "-c",
                     "from ament_index_python.packages import get_package_share_directory as share; "
                     "print(share('std_msgs')); print(share('laser_calib_interfaces'))"])
    assert found.returncode == 0, found.stderr


def test_env_sh_puts_the_command_line_on_the_path(ros: Ros):
    """`laser-calib`, as the README and docs/ write it, works after `source scripts/env.sh`."""
    found = ros.run(["laser-calib", "--help"])
    assert found.returncode == 0 and found.stdout.startswith("usage: laser-calib"), found


def test_an_output_folder_that_cannot_be_made_is_one_line(ros: Ros, tmp_path):
    """--out under a regular file (or on a read-only disk): run-session ended in a NotADirectoryError
    traceback, exit 1, then 'run again with the same --out to resume', where nothing could ever be
    written. Now one line naming the folder, exit 2; the sequencer started alone says the same."""
    (tmp_path / "file").write_text("")
    out = tmp_path / "file" / "session"
    result = ros.run([RUN_SESSION, "--no-setup", "--out", str(out)], timeout=120)
    assert result.returncode == 2, result
    assert result.stderr == (f"run-session: {out}: cannot create the session folder or its .lock: "
                             f"Not a directory ({out})\n"), result
    ros.start("sequencer", "-p", f"robot:={ROOT / 'config' / 'robots' / 'humanoid_arm_7dof.yaml'}",
              "-p", f"output_dir:={out}")
    assert ros.wait_exit("sequencer", 60) == 2
    assert ros.log("sequencer").strip().splitlines()[-1].startswith(f"error: {out}: cannot create"), \
        ros.log("sequencer")
    assert "Traceback" not in ros.log("sequencer")


def test_a_session_in_a_namespace_is_resumed_only_there_and_its_bag_is_read(ros: Ros, tmp_path, capsys):
    """Two sessions on one ROS domain are refused, and the refusal says to give each its own
    namespace; a session in one (namespace:=rig2) records /rig2/samples. Its bag read as no session
    ('no topic /samples') to `estimate --bag` and to its own resume, which lost sight of the poses
    only the bag held. A resume in another namespace is refused: its poses would go to other topics."""
    from laser_calib.cli.main import main
    from laser_calib.io import bag
    out = tmp_path / "session"
    # the 4-DOF arm: 12 poses, 48 values for its 21 errors (the 7-DOF's 33 left the robust rule too few)
    plan = [RUN_SESSION, "--no-setup", "--out", str(out), "--robot", str(ROOT / "config" / "robots" /
            "manipulator_4dof.yaml"), "--poses", "12", "--test-poses", "2", "--span", "small", "--speed", "4.0"]
    proc = ros.start_command("run-session", plan + ["--namespace", "rig2"])
    deadline = time.monotonic() + 300
    while not csv_rows(out / "samples.csv"):   # measuring (test_ctrl_c_stops_every_node_cleanly)
        assert proc.poll() is None and time.monotonic() < deadline, ros.log("run-session")
        time.sleep(0.1)
    ros.interrupt("run-session")
    assert ros.wait_exit("run-session", 30) == 130, ros.log("run-session")
    refused = ros.run(plan, timeout=120)
    assert refused.returncode == 2, refused
    assert refused.stderr.strip().splitlines()[-1] == (
        f"error: {out}: holds a partial session recorded in ROS namespace /rig2, resumed in /; resume it in /rig2 "
        "(the launch's namespace:=rig2) or choose another output_dir"), refused
    resumed = ros.run(plan + ["--namespace", "rig2"], timeout=300)
    assert resumed.returncode == 0 and "resuming" in resumed.stdout + resumed.stderr, resumed
    assert {"/rig2/samples", "/rig2/test_samples"} <= set(bag.bag_topics(out / "bag"))
    assert len(bag.read_samples(out / "bag")) == 12 and csv_rows(out / "samples.csv") == 12
    capsys.readouterr()
    assert main(["estimate", "--bag", str(out / "bag"), "--robot", str(out / "robot.yaml"),
                 "--out", str(tmp_path / "estimate")]) == 0
    assert f"tested on 2 poses of {out / 'bag'} /rig2/test_samples" in capsys.readouterr().err
