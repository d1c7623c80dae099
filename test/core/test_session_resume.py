"""What a crash can leave in a session folder, and the resume that repairs it; one owner per folder.

The three ways a killed sequencer leaves bag and samples.csv disagreeing by the pose in flight
(session/folder.py): killed after the bag segment closed but before the CSV row (bag ahead);
the pose's bag segment lost while its row was written (CSV ahead); killed while appending the
row (torn last line, with the next pose's segment unfinished in .recording).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from laser_calib.io import bag
from laser_calib.io.bag_writer import SegmentedBagWriter
from laser_calib.io.errors import InputError
from laser_calib.io.samples import Samples, load_samples
from laser_calib.model.robot_file import load_robot
from laser_calib.session.folder import SAMPLES_FILE, TEST_SAMPLES_FILE, SessionDir
from laser_calib.session.lock import SessionLock
from laser_calib.session.poses import generate_poses, with_test_poses

ROBOT = Path(__file__).resolve().parents[2] / "config" / "robots" / "humanoid_arm_7dof.yaml"
SAMPLE = "laser_calib_interfaces/msg/Sample"


def started(tmp_path: Path, n: int = 6, test: int = 0):
    robot = load_robot(ROBOT)
    poses = with_test_poses(generate_poses(robot, n, "small", 1), robot, test, 1)
    session = SessionDir(tmp_path / "session")
    session.start(robot, poses, {"robot": str(ROBOT)})
    return robot, poses, session


def sample(poses, step: int) -> Samples:
    spots = np.array([[[0.1 + 0.01 * step, 0.2], [np.nan, np.nan]]])
    return Samples(np.array([poses.pose[step]]), np.array([100.0 + step]), poses.q[step][None], spots)


class Journal:
    """The bag the sequencer writes: one closed segment per pose (io.bag_writer)."""

    def __init__(self, session: SessionDir, namespace: str = ""):
        self.store, self.namespace = bag.typestore(), namespace
        topics = {namespace + t: (SAMPLE, [bag.qos(True, True, 100)])
                  for t in (bag.SAMPLES_TOPIC, bag.TEST_SAMPLES_TOPIC)}
        self.writer = SegmentedBagWriter(session.bag_dir, session.work_dir, topics, self.store)

    def write(self, s: Samples, topic: str = bag.SAMPLES_TOPIC, close: bool = True, reverse: bool = False) -> None:
        """The sample on ``topic`` in the journal's namespace (a session launched with namespace:=rig2
        records /rig2/samples); reverse: joint_names and joint_positions listed tip to base (another
        tool's order)."""
        T = self.store.types
        order = slice(None, None, -1 if reverse else 1)
        names, q = [f"joint{i + 1}" for i in range(s.n_joints)][order], np.ascontiguousarray(s.q[0][order])
        spots = [T["laser_calib_interfaces/msg/Spot"](float(y), float(z), bool(np.isfinite(y)))
                 for y, z in s.spots[0]]
        stamp = T["builtin_interfaces/msg/Time"](int(s.stamp[0]), int(round((s.stamp[0] % 1) * 1e9)))
        msg = T[SAMPLE](T["std_msgs/msg/Header"](stamp, "screen"), int(s.pose[0]), names, q, spots, 3)
        self.writer.write(self.namespace + topic, int(s.stamp[0] * 1e9), self.store.serialize_cdr(msg, SAMPLE))
        if close:
            self.writer.rotate()


def measured(session, poses, journal, steps, csv=True):
    for step in steps:
        s = sample(poses, step)
        journal.write(s)
        if csv:
            session.append_sample(s)


def test_bag_ahead_of_the_csv_restores_the_row(tmp_path):
    robot, poses, session = started(tmp_path)
    journal = Journal(session)
    measured(session, poses, journal, range(3))
    measured(session, poses, journal, [3], csv=False)        # killed before the row
    journal.writer.close()
    found = session.reconcile(robot, poses)
    assert list(found.done) == [True] * 4 + [False] * 2
    assert len(found.to_bag) == 0 and any("pose 3 restored from the bag" in r for r in found.repairs)
    csv = load_samples(session.path / SAMPLES_FILE)
    np.testing.assert_array_equal(csv.pose, poses.pose[:4])
    np.testing.assert_array_equal(csv.stamp, bag.read_samples(session.bag_dir).stamp)


def test_a_session_in_a_namespace_restores_its_rows_from_its_own_topics(tmp_path):
    """A session launched with namespace:=rig2 records /rig2/samples. Its bag read as none
    ('no topic /samples'): a resume lost sight of the poses only the bag held, and
    `estimate --bag` refused the bag. Another namespace's resume is refused: the poses to come
    would go to other topics than the ones measured."""
    robot, poses, session = started(tmp_path)
    session.set_info(namespace="/rig2")
    journal = Journal(session, "/rig2")
    measured(session, poses, journal, range(2))
    measured(session, poses, journal, [2], csv=False)        # killed before the row
    journal.writer.close()
    found = session.reconcile(robot, poses)
    assert list(found.done) == [True] * 3 + [False] * 3 and len(found.to_bag) == 0
    assert found.repairs == [f"{SAMPLES_FILE}: pose {poses.pose[2]} restored from the bag (a crash before its row)"]
    np.testing.assert_array_equal(bag.read_samples(session.bag_dir).pose, poses.pose[:3])
    session.check_namespace("/rig2")
    with pytest.raises(InputError, match=r"recorded in ROS namespace /rig2, resumed in /; resume it in /rig2 "
                                         r"\(the launch's namespace:=rig2\)"):
        session.check_namespace("/")


def test_a_bag_with_the_samples_of_two_namespaces_is_refused(tmp_path):
    """`ros2 bag record` of two sessions, each in its namespace: their poses are not one session's."""
    robot, poses, session = started(tmp_path)
    for step, namespace in enumerate(("/rig1", "/rig2")):
        journal = Journal(session, namespace)
        journal.write(sample(poses, step))
        journal.writer.close()
    with pytest.raises(InputError, match=r"holds the samples of 2 sessions \(/rig1/samples, /rig2/samples\): give "
                                         "one session's bag"):
        bag.read_samples(session.bag_dir)


def test_the_bags_samples_are_read_by_joint_name(tmp_path):
    """A resume reads the bag by each sample's joint_names, as estimate --bag and the estimator
    do (io/joint_names.py): samples listed tip to base are restored in the robot's order."""
    robot, poses, session = started(tmp_path)
    journal = Journal(session)
    for step in range(3):
        journal.write(sample(poses, step), reverse=True)     # bag only: the CSV rows come from it
    journal.writer.close()
    found = session.reconcile(robot, poses)
    np.testing.assert_array_equal(found.fit.q, poses.q[:3])
    np.testing.assert_array_equal(load_samples(session.path / SAMPLES_FILE).q, poses.q[:3])


def test_csv_ahead_of_the_bag_gives_the_sample_back_to_the_bag(tmp_path):
    robot, poses, session = started(tmp_path)
    journal = Journal(session)
    measured(session, poses, journal, [0, 1])
    session.append_sample(sample(poses, 2))                  # its bag segment lost
    measured(session, poses, journal, [3])                   # and the session went on (the case)
    journal.writer.close()
    found = session.reconcile(robot, poses)
    assert list(found.done) == [True] * 4 + [False] * 2
    assert list(found.to_bag.pose) == [poses.pose[2]]        # the node writes it back into the bag
    np.testing.assert_array_equal(found.to_bag.q, sample(poses, 2).q)
    assert list(found.fit.pose) == list(poses.pose[:4])       # in measurement order
    # written back, the next resume finds bag and CSV agreeing, whatever their order
    journal = Journal(session)
    journal.write(found.to_bag.subset([0]))
    journal.writer.close()
    again = session.reconcile(robot, poses)
    assert list(again.done) == list(found.done) and again.repairs == [] and len(again.to_bag) == 0


def test_a_listed_segment_deleted_is_struck_from_the_bags_list_on_resume(tmp_path):
    """bag_2.mcap deleted after a stop: the resume restored its pose from samples.csv, but
    metadata.yaml still listed the file, and the finished bag could not be replayed ('Some database
    files are missing', a new user's probe). The resumed writer strikes it from the list and counts
    what is there: rosbags reads the bag, every sample once."""
    from rosbags.rosbag2 import Reader
    robot, poses, session = started(tmp_path)
    journal = Journal(session)
    measured(session, poses, journal, range(4))
    journal.writer.close()
    (session.bag_dir / "bag_2.mcap").unlink()
    resumed = Journal(session)
    assert resumed.writer.missing == ["bag_2.mcap"]
    found = session.reconcile(robot, poses)
    assert list(found.to_bag.pose) == [poses.pose[2]]
    resumed.write(found.to_bag.subset([0]))
    resumed.writer.close()
    with Reader(session.bag_dir) as reader:   # it refused the bag with a listed file missing
        assert reader.message_count == 4
    assert sorted(p.name for p in session.bag_dir.glob("*.mcap")) == ["bag_0.mcap", "bag_1.mcap", "bag_3.mcap",
                                                                      "bag_4.mcap"]
    assert sorted(bag.read_samples(session.bag_dir).pose) == sorted(poses.pose[:4])


def test_torn_row_and_unfinished_segment(tmp_path):
    robot, poses, session = started(tmp_path, test=2)
    journal = Journal(session)
    measured(session, poses, journal, range(6))
    journal.write(sample(poses, 6), bag.TEST_SAMPLES_TOPIC)     # test pose 1: bag and CSV
    session.append_sample(sample(poses, 6), test=True)
    journal.write(sample(poses, 7), bag.TEST_SAMPLES_TOPIC, close=False)   # test pose 2: killed mid-segment
    with open(session.path / TEST_SAMPLES_FILE, "a") as handle:
        handle.write("7,107.0,0.01,0.0")                    # ... and mid-row
    del journal                                              # no close: as SIGKILL leaves it
    journal = Journal(session)                               # the next sequencer discards the open segment
    assert journal.writer.discarded
    journal.writer.close()
    found = session.reconcile(robot, poses)
    assert list(found.done) == [True] * 7 + [False]
    assert any("torn last line" in r for r in found.repairs)
    assert list(load_samples(session.path / TEST_SAMPLES_FILE).pose) == [poses.pose[6]]
    assert len(load_samples(session.path / SAMPLES_FILE)) == 6


def test_another_sessions_bag_is_refused(tmp_path):
    robot, poses, session = started(tmp_path)
    journal = Journal(session)
    other = sample(poses, 0)
    journal.write(Samples(np.array([99]), other.stamp, other.q, other.spots))
    journal.writer.close()
    with pytest.raises(InputError, match="pose 99, which the pose list does not hold"):
        session.reconcile(robot, poses)


HOLDER = textwrap.dedent("""
    import sys, time
    from laser_calib.session.lock import SessionLock
    SessionLock(sys.argv[1]).acquire()
    print("locked", flush=True)
    time.sleep(60)
""")


def test_one_owner_per_folder_and_no_stale_lock_after_sigkill(tmp_path):
    env_path = str(Path(__file__).resolve().parents[2] / "ros2_ws" / "src" / "laser_calib")
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                              env={"PYTHONPATH": env_path, "PATH": "/usr/bin:/bin"})
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(InputError, match=f"in use by the session of PID {holder.pid} "):
            SessionLock(tmp_path).acquire()
    finally:
        holder.kill()
        holder.wait()
    lock = SessionLock(tmp_path)
    lock.acquire()                                         # the killed owner left no stale lock
    with pytest.raises(InputError, match="in use"):
        SessionLock(tmp_path).acquire()                    # a second owner in this very process too
    lock.release()
    SessionLock(tmp_path).acquire()


def test_resume_with_another_robot_is_refused(tmp_path):
    robot, _, session = started(tmp_path)
    session.check_robot(load_robot(ROBOT), str(ROBOT))          # the same model: resumed
    own = session.path / "robot.yaml"                             # the session's copy, read back: too
    session.check_robot(load_robot(own), str(own))
    other = ROBOT.parent / "manipulator_4dof.yaml"
    with pytest.raises(InputError) as exc:
        session.check_robot(load_robot(other), str(other))
    line = str(exc.value)
    assert "\n" not in line and line.startswith(f"{session.path}: ")
    assert f"'{robot.name}'" in line and f"'{load_robot(other).name}'" in line and str(other) in line
    # the same name, one length changed: a different model all the same
    changed = tmp_path / "changed.yaml"
    text = ROBOT.read_text()
    changed.write_text(text.replace("d: 0.", "d: 0.01", 1))
    assert load_robot(changed).name == robot.name and load_robot(changed) != robot
    with pytest.raises(InputError, match=r"same name is another model \(its 'joints' differs\)"):
        session.check_robot(load_robot(changed), str(changed))
