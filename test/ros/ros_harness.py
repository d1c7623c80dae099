"""The ROS tests' harness: the workspace environment and node processes.

Every node runs as its own process from ros2_ws/install/laser_calib_nodes/lib/
laser_calib_nodes/ over real DDS, each test on its own ROS_DOMAIN_ID with
ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST. The pytest process stays ROS-free:
ROS clients run as subprocesses (ros_client.py). Skipped, with the reason,
only when the workspace is not built (scripts/setup).
"""

from __future__ import annotations

import itertools
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
INSTALL = ROOT / "ros2_ws" / "install"
BIN = INSTALL / "laser_calib_nodes" / "lib" / "laser_calib_nodes"
ROBOT = ROOT / "config" / "robots" / "humanoid_arm_7dof.yaml"
PARAMS = ROOT / "config" / "session.yaml"
EXAMPLE_ARM = ROOT / "config" / "dynamixel_arm.yaml"  # hardware.launch.py's arm_params, required
CLIENT = Path(__file__).resolve().parent / "ros_client.py"
NODES = ("arm_driver", "camera_sim", "spot_detector", "sequencer", "estimator", "replay")

# Ctrl-C to exit, s: generous for eight Python processes shutting down at once on two loaded
# cores; a node that hangs on Ctrl-C still fails
STOP_TIMEOUT = 30.0
# ros2param waits a fixed 5 s for a node's parameter services once `--timeout` has found the node
# (ros2param/api/__init__.py, Jazzy); a new process on a loaded machine can take longer to discover
# them (seen once in CI). A user would run the command again; so does Ros.ros2, PARAM_TRIES times.
PARAM_SERVICES_LATE = "Wait for service timed out waiting for parameter services"
PARAM_TRIES = 3

# each test its own domain of 10..209; a random start keeps clear of a killed earlier run's leftovers,
# and each pytest-xdist worker (PYTEST_XDIST_WORKER=gwN of PYTEST_XDIST_WORKER_COUNT) its own block
_WORKER = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
_BLOCK = 200 // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
_domains = itertools.count(random.Random(os.getpid()).randrange(0, _BLOCK))


def workspace_missing() -> str | None:
    missing = [name for name in NODES if not (BIN / name).exists()]
    if missing:
        return f"workspace not built ({BIN / missing[0]} missing): run scripts/setup"
    if not (INSTALL / "laser_calib_interfaces").is_dir():
        return "laser_calib_interfaces not built: run scripts/setup"
    return None


def children(pid: int) -> list[int]:
    """Every live descendant of pid (from /proc)."""
    parent_of = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            parent_of[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
    found, frontier = [], [pid]
    while frontier:
        kids = [p for p, parent in parent_of.items() if parent in frontier]
        found += kids
        frontier = kids
    return found


def ros2_missing() -> str | None:
    """Why tests of the real ros2 command line cannot run here, or None."""
    reason = workspace_missing()
    if reason is None and shutil.which("ros2", path=workspace_env()["PATH"]) is None:
        reason = ("the ros2 command line is not installed (../shared/tools/ros2cli/install.sh .venv; "
                  ".ci/run does it when ../shared is there)")
    return reason


_ENV: dict | None = None


def terminal_signals() -> None:
    """SIGINT and SIGQUIT at their defaults in a child, as a shell's foreground job has them. A
    suite started as a background job of a shell without job control (`(scripts/test &)`) ignores
    both, and its children inherit that: a node sent Ctrl-C before it set its own handler ran on
    to its end (test_exit_watchdog's Ctrl-C at every moment of a start: 'parameter robot is
    empty', exit 2, in a clean clone started so)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGQUIT, signal.SIG_DFL)


def workspace_env() -> dict:
    """os.environ plus what `source scripts/env.sh` sets."""
    global _ENV
    if _ENV is None:
        out = subprocess.run(["bash", "-c", f"source '{ROOT}/scripts/env.sh' >/dev/null && env -0"],
                             check=True, capture_output=True).stdout
        _ENV = dict(item.split("=", 1) for item in out.decode().split("\0") if "=" in item)
    return dict(_ENV)


class Ros:
    """Processes of one test on one DDS domain; all stopped (SIGINT, then SIGKILL) at the end."""

    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.domain = 10 + _BLOCK * _WORKER + next(_domains) % _BLOCK
        self.env = workspace_env()
        # PYTHONFAULTHANDLER: a node that does not exit on Ctrl-C is aborted (SIGABRT) before it is
        # killed, so its log shows where each of its threads was stuck
        self.env.update(ROS_DOMAIN_ID=str(self.domain), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                        PYTHONUNBUFFERED="1", PYTHONFAULTHANDLER="1")
        self.procs: dict[str, subprocess.Popen] = {}
        self.logs: dict[str, Path] = {}
        self.ros2_used = False  # the ros2 command line starts a daemon on this domain, stopped at the end

    def start(self, name: str, *ros_args: str, node: str | None = None, params: bool = True) -> subprocess.Popen:
        """Start an executable with --ros-args (the session parameter file first)."""
        node = node or name
        args = [str(BIN / node), "--ros-args"] + (["--params-file", str(PARAMS)] if params else []) + list(ros_args)
        return self.start_command(name, args)

    def start_command(self, name: str, args: list[str]) -> subprocess.Popen:
        """Start any command (`ros2 launch ...`) as a terminal starts a job: its own process
        group, which stop() signals as a whole, as Ctrl-C does, and Ctrl-C's signals at their
        defaults (terminal_signals)."""
        self.ros2_used |= args[0] == "ros2"
        log = self.tmp / f"{name}.log"
        handle = open(log, "ab")
        proc = subprocess.Popen(args, env=self.env, stdout=handle, stderr=subprocess.STDOUT, start_new_session=True,
                                preexec_fn=terminal_signals)
        handle.close()
        self.procs[name], self.logs[name] = proc, log
        return proc

    def interrupt(self, name: str) -> None:
        """Ctrl-C in the job's terminal: SIGINT to its whole process group."""
        try:
            os.killpg(self.procs[name].pid, signal.SIGINT)
        except ProcessLookupError:
            pass

    def run(self, args: list[str], timeout: float = 120) -> subprocess.CompletedProcess:
        self.ros2_used |= args[0] == "ros2"
        return subprocess.run(args, env=self.env, capture_output=True, text=True, timeout=timeout)

    def ros2(self, *args: str, timeout: float = 90) -> subprocess.CompletedProcess:
        """``ros2 *args``; a `ros2 param` verb is run again when its parameter services were late."""
        for _ in range(PARAM_TRIES if args[0] == "param" else 1):
            done = self.run(["ros2", *args], timeout=timeout)
            if PARAM_SERVICES_LATE not in done.stderr:
                break
        return done

    def client(self, *args: str, timeout: float = 150) -> dict:
        result = self.run([sys.executable, str(CLIENT), *args], timeout=timeout)
        assert result.returncode == 0, f"ros_client {args} failed:\n{result.stdout}\n{result.stderr}"
        return json.loads(result.stdout.strip().splitlines()[-1])

    def log(self, name: str) -> str:
        return self.logs[name].read_text(errors="replace")

    def wait_log(self, name: str, text: str, timeout: float, watch: str | None = None, count: int = 1) -> None:
        """Wait until ``text`` is ``count`` times in ``name``'s log; fail when ``timeout`` s pass or
        the process ``watch`` (``name`` unless given) has exited first."""
        watch = watch or name
        deadline = time.monotonic() + timeout
        while self.log(name).count(text) < count:
            if self.procs[watch].poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"not {count} x {text!r} in {name}'s log within {timeout} s, or {watch} exited; "
                            f"{watch}'s log:\n{self.log(watch)[-3000:]}")
            time.sleep(0.05)

    def wait_exit(self, name: str, timeout: float) -> int:
        try:
            return self.procs[name].wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            pytest.fail(f"{name} still running after {timeout} s; its log:\n{self.log(name)[-3000:]}")

    def stop(self, name: str, timeout: float = STOP_TIMEOUT) -> int:
        """SIGINT (Ctrl-C) and the exit code; aborted, then killed, if it does not exit."""
        proc = self.procs[name]
        if proc.poll() is None:
            self.interrupt(name)
            self._wait_or_abort(name, time.monotonic() + timeout)
        return proc.returncode

    def stop_all(self) -> dict[str, int]:
        """Ctrl-C to every job at once, as a terminal closing a session; the exit codes."""
        for name, proc in self.procs.items():
            if proc.poll() is None:
                self.interrupt(name)
        deadline = time.monotonic() + STOP_TIMEOUT
        codes = {name: self._wait_or_abort(name, deadline) for name in self.procs}
        if self.ros2_used:
            subprocess.run(["ros2", "daemon", "stop"], env=self.env, capture_output=True, timeout=60)
            self.ros2_used = False
        return codes

    def _wait_or_abort(self, name: str, deadline: float) -> int:
        """The exit code by the deadline; else SIGABRT to the job's group (the Python fault
        handler writes every thread's stack to the log), then SIGKILL."""
        proc = self.procs[name]
        try:
            return proc.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            for sig in (signal.SIGABRT, signal.SIGKILL):
                try:
                    os.killpg(proc.pid, sig)
                    return proc.wait(timeout=5)
                except ProcessLookupError:
                    break
                except subprocess.TimeoutExpired:
                    continue
            return proc.wait()


def start_sim(ros: Ros, out: Path, speed: float = 4.0) -> None:
    """The simulated arm, camera, detector and the estimator."""
    ros.start("estimator", "-p", f"robot:={ROBOT}", "--log-level", "estimator:=debug")  # a line per sample taken
    ros.start("arm_driver", "-p", f"robot:={ROBOT}", "-p", f"sim.joint_speed:={speed}",
              "-p", f"sim.true_robot_out:={out / 'robot_true.yaml'}")
    ros.start("camera_sim")
    ros.start("spot_detector")
