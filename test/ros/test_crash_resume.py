"""The sequencer killed (SIGKILL) mid-session: the bag stays readable with every
completed pose, and the resumed session does not measure those poses again."""

from __future__ import annotations

import shutil
import signal
import time

import numpy as np

from ros_harness import ROBOT, start_sim

POSES = 12


def csv_rows(path) -> int:
    try:
        return max(0, len(path.read_text().strip().splitlines()) - 1)
    except OSError:
        return 0


def test_kill_and_resume(ros, tmp_path):
    from laser_calib.io.samples import load_samples
    from laser_calib.io import bag
    from rosbags.rosbag2 import Reader
    out = tmp_path / "out"
    out.mkdir()
    start_sim(ros, out)
    args = ("-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", f"poses:={POSES}", "-p", "span:=small",
            "-p", "seed:=5")
    proc = ros.start("sequencer", *args)
    deadline = time.monotonic() + 120
    while csv_rows(out / "samples.csv") < 4:
        assert proc.poll() is None, ros.log("sequencer")
        assert time.monotonic() < deadline, "no progress:\n" + ros.log("sequencer")
        time.sleep(0.05)
    # the next pose is under way now (its segment open): kill
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    rows_at_kill = csv_rows(out / "samples.csv")

    # the bag is readable as it is (metadata lists only closed, complete segments)
    import yaml
    meta = yaml.safe_load((out / "bag" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert all((out / "bag" / name).exists() for name in meta["relative_file_paths"])
    with Reader(out / "bag") as reader:
        count = sum(1 for c, _, _ in reader.messages() if c.topic == "/samples")
    before = bag.read_samples(out / "bag")
    k = len(before)
    assert count == k and k >= rows_at_kill >= 4
    assert list(before.pose) == list(range(k))
    assert k < POSES

    # resume: same output directory
    proc = ros.start("sequencer_resumed", *args, node="sequencer")
    assert ros.wait_exit("sequencer_resumed", 180) == 0, ros.log("sequencer_resumed")
    log = ros.log("sequencer_resumed")
    assert f"resuming {out}: {k} of {POSES} poses already measured" in log
    measured = [line for line in log.splitlines() if "measured in" in line]
    assert len(measured) == POSES - k                  # only the missing poses were measured
    assert f"pose {k + 1}/{POSES}" in measured[0]

    after = bag.read_samples(out / "bag")
    assert list(after.pose) == list(range(POSES))      # every pose exactly once
    np.testing.assert_array_equal(after.stamp[:k], before.stamp)  # the first k were not measured again
    np.testing.assert_array_equal(after.q[:k], before.q)
    csv = load_samples(out / "samples.csv")
    np.testing.assert_array_equal(csv.stamp, after.stamp)
    assert (out / "report.md").exists() and (out / "robot_calibrated.yaml").exists()
    info = yaml.safe_load((out / "session.yaml").read_text())
    assert info["state"] == "finished"
    # the resume and what it mended are in the session's record and its report: they were said in the
    # log only, and the report read as one run's
    [resume] = info["resumes"]
    assert resume["measured"] == k, info
    report = (out / "report.md").read_text()
    said = f"with {k} of {POSES} poses measured" + (f"; repaired: {'; '.join(resume['repairs'])}"
                                                       if resume["repairs"] else "")
    assert "Measured in 2 runs" in report and said in report, report

    # the estimator (which lived through the crash) has every pose once, in order: the online EKF
    # equals the offline one over samples.csv
    from laser_calib.estimation.online import OnlineEkf
    from laser_calib.model.robot_file import load_robot
    from laser_calib.session.estimate import online_options
    published = ros.client("params", str(POSES))
    assert published["sample_count"] == POSES
    ekf = OnlineEkf(load_robot(ROBOT), online_options(0.0))
    for k in range(len(csv)):
        ekf.update(csv.q[k], csv.spots[k])
    # Seen once in a full suite under load (passing on rerun): all 33 differed with sample_count 12; the
    # logs say which samples the estimator took when it happens again.
    np.testing.assert_allclose(published["errors"], ekf.errors, rtol=1e-9, atol=1e-15,
                               err_msg=f"estimator:\n{ros.log('estimator')}\nfirst sequencer:\n{ros.log('sequencer')}"
                                       f"\nresumed:\n{log}")

    # a finished session is not measured again
    proc = ros.start("sequencer_again", *args, node="sequencer")
    assert ros.wait_exit("sequencer_again", 60) == 2
    lines = [line for line in ros.log("sequencer_again").splitlines() if line.strip()]
    assert lines[-1].startswith("error: ") and "finished session" in lines[-1]


def test_a_disk_that_refuses_the_bag_ends_the_session_in_one_line_and_keeps_the_poses(ros, tmp_path):
    """A full disk under the session (seen on a 300 KB file system: 'No space left on device') ended
    in three tracebacks and exit 1: the executor's recording callback raised, and the sequencer's
    own 'failed' line raised again writing to the same bag. Now one line naming the bag and the
    cause, exit 1, the poses measured before kept in samples.csv and the bag; made room, the
    session resumes. Without a small file system (it needs root), the bag's working folder is
    made a file: the next segment cannot be opened there."""
    from laser_calib.io import bag
    out = tmp_path / "out"
    out.mkdir()
    start_sim(ros, out)
    args = ("-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "poses:=6", "-p", "span:=small",
            "-p", "estimate.mode:=none")
    proc = ros.start("sequencer", *args)
    deadline = time.monotonic() + 120
    while csv_rows(out / "samples.csv") < 2:
        assert proc.poll() is None and time.monotonic() < deadline, ros.log("sequencer")
        time.sleep(0.05)
    work = out / ".recording"
    while not work.is_file():   # the open segment goes with the folder, as a disk fault loses it
        shutil.rmtree(work, ignore_errors=True)
        try:
            work.write_text("")
        except (IsADirectoryError, FileExistsError):
            pass   # the sequencer opened its next segment meanwhile
    assert ros.wait_exit("sequencer", 60) == 1, ros.log("sequencer")
    log = ros.log("sequencer")
    assert "Traceback" not in log, log
    errors = [line for line in log.splitlines() if "ERROR" in line]
    assert len(errors) == 1 and f"recording into {out / 'bag'} failed" in errors[0] \
        and "make room and run again to resume" in errors[0], log
    kept = csv_rows(out / "samples.csv")
    assert kept >= 2 and len(bag.read_samples(out / "bag")) == kept, log
    work.unlink()   # room made
    ros.start("resumed", *args, node="sequencer")
    assert ros.wait_exit("resumed", 120) == 0, ros.log("resumed")
    assert csv_rows(out / "samples.csv") == 6 and len(bag.read_samples(out / "bag")) == 6


def test_a_bag_that_cannot_be_closed_at_the_stop_is_said_with_exit_1(ros, tmp_path):
    """The recording can also fail at the stop, when the open segment is closed: the node said
    nothing and exited 0, and the segment's messages were gone. Now the same one line as during the
    session, exit 1. The open segment's folder is made a file, as in the test above, while the
    sequencer waits for an arm with the streamed joint states in its open segment."""
    out = tmp_path / "out"
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "poses:=1",
              "-p", "wait_timeout:=60.0", "-p", "estimate.mode:=none")
    ros.client("stream-replay", str(ROBOT), "10", "1", "2")
    work = out / ".recording"
    shutil.rmtree(work)
    work.write_text("")
    assert ros.stop("sequencer") == 1, ros.log("sequencer")
    log = ros.log("sequencer")
    errors = [line for line in log.splitlines() if "ERROR" in line]
    assert "Traceback" not in log and len(errors) == 1 and f"recording into {out / 'bag'} failed" in errors[0], log
