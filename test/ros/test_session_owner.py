"""One owner per session folder, across processes: a second sequencer on a live folder is
refused with one line naming the owner's PID; a SIGKILLed owner leaves no stale lock."""

from __future__ import annotations

import signal
import time

from ros_harness import ROBOT, start_sim
from test_crash_resume import csv_rows as rows


def test_second_session_refused_then_resumed_after_a_kill(ros, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    start_sim(ros, out)
    args = ("-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "poses:=3", "-p", "span:=small",
            "-p", "estimate.mode:=none")
    owner = ros.start("sequencer", *args)
    deadline = time.monotonic() + 120
    while not rows(out / "samples.csv"):   # one pose measured: the session is live
        assert owner.poll() is None and time.monotonic() < deadline, ros.log("sequencer")
        time.sleep(0.05)
    owner.send_signal(signal.SIGSTOP)      # the owner, alive but still, keeps its lock (no race with its end)
    ros.start("second", *args, node="sequencer")
    assert ros.wait_exit("second", 60) == 2
    lines = [line for line in ros.log("second").splitlines() if line.strip()]
    assert lines[-1].startswith("error: ") and f"in use by the session of PID {owner.pid} " in lines[-1]
    assert "Traceback" not in ros.log("second")
    assert owner.poll() is None
    owner.send_signal(signal.SIGKILL)
    owner.wait()
    ros.start("resumed", *args, node="sequencer")
    assert ros.wait_exit("resumed", 120) == 0, ros.log("resumed")[-3000:]
    assert "resuming" in ros.log("resumed") and rows(out / "samples.csv") == 3
