"""The session's measurement logic, ROS-free: settle detection, frame averaging, pose lists,
the trajectory acceptance rules of joint_trajectory_controller, joint name mapping."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from laser_calib.hardware.trajectory import TrajectoryPoint, joint_order, move_time, trajectory_goal
from laser_calib.model.robot_file import load_robot
from laser_calib.session.average import FrameCollector, StillPoses, average_frames
from laser_calib.session.poses import format_poses, generate_poses, load_poses, save_poses, with_test_poses
from laser_calib.session.settle import SettleDetector, SettleRule

ROBOT = Path(__file__).resolve().parents[2] / "config" / "robots" / "humanoid_arm_7dof.yaml"
NAN = np.nan


def test_settled_only_after_holding_both_tolerances():
    rule = SettleRule(position_tolerance=0.01, velocity_tolerance=0.01, hold_time=0.2)
    goal = np.zeros(2)
    s = SettleDetector(goal, rule, after=1.0)
    assert not s.update(0.9, goal, np.zeros(2))          # before the command: ignored
    assert not s.update(1.0, goal, np.zeros(2))          # calm from 1.0 ...
    assert not s.update(1.1, goal, np.array([0.02, 0]))  # ... broken by a velocity
    assert not s.update(1.2, goal + 0.005, np.zeros(2))  # calm again from 1.2
    assert not s.update(1.39, goal, None)                # no velocities reported: position alone
    assert s.update(1.41, goal, np.zeros(2))             # held over 0.2 s
    s = SettleDetector(goal, rule, after=0.0)
    s.update(0.0, np.array([0.0, 0.5]), None)
    assert s.worst_joint(["a", "b"]) == "b at 0.50000 rad, goal 0.00000"
    with pytest.raises(ValueError, match="position_tolerance"):
        SettleRule(position_tolerance=0.0)


def test_a_spot_counts_when_seen_in_at_least_half_the_frames():
    q = np.array([[0.0, 1.0], [0.2, 1.0], [0.4, 1.0], [0.6, 1.0]])
    spots = np.array([[[0.1, 0.2], [NAN, NAN]],
                      [[0.3, 0.4], [0.5, 0.5]],
                      [[NAN, NAN], [NAN, NAN]],
                      [[0.5, 0.6], [NAN, NAN]]])
    sample = average_frames(7, q, spots, 12.5)
    np.testing.assert_allclose(sample.q[0], [0.3, 1.0])
    np.testing.assert_allclose(sample.spots[0, 0], [0.3, 0.4])      # 3 of 4 frames
    assert np.isnan(sample.spots[0, 1]).all()                         # 1 of 4: not seen
    assert sample.pose[0] == 7 and sample.stamp[0] == 12.5
    two = average_frames(1, q[:2], spots[:2], 0.0)                     # 1 of 2: half counts
    np.testing.assert_allclose(two.spots[0, 1], [0.5, 0.5])


def settled(goal: np.ndarray, rule: SettleRule = SettleRule()) -> SettleDetector:
    """The detector of an arm settled at goal (N,) (what the sequencer hands FrameCollector)."""
    return SettleDetector(np.asarray(goal, dtype=float), rule, after=0.0)


def test_collector_pairs_frames_from_the_settle_instant():
    c = FrameCollector(frames=2, tolerance=0.01, settle=settled([0.0]), settled_stamp=1.0,
                       settled_state=(np.zeros(1), None))
    c.add_frame(0.99, np.zeros((2, 2)))            # before the arm settled: ignored
    c.add_frame(1.0, np.ones((2, 2)))              # pairs with the settle instant
    assert not c.complete
    c.add_frame(1.1, np.full((2, 2), 3.0))
    c.add_state(1.1, (np.array([0.002]), None))    # within the settle rule's 0.003 rad of the goal
    assert c.complete
    sample = c.sample(4)
    np.testing.assert_allclose(sample.spots[0], np.full((2, 2), 2.0))
    np.testing.assert_allclose(sample.q[0], [0.001])
    assert sample.stamp[0] == 1.1


def test_a_joint_reading_off_the_goal_while_the_frames_are_taken_starts_them_again():
    """A servo's reading glitched by 0.15 rad for two reads of a 50 Hz driver once the arm had
    settled (its bus or encoder; the arm did not move, its spots were right): averaged into the
    pose's frames, the sample was 0.05 rad off, and nothing was said. The frames so far are now
    dropped, and taken again once the arm has settled anew by the settle rule (0.2 s held)."""
    goal = np.array([0.3, -0.2])
    c = FrameCollector(frames=3, tolerance=0.005, settle=settled(goal), settled_stamp=1.0,
                       settled_state=(goal, None))
    glitched = {1.04: goal + [0.0, 0.15], 1.06: goal + [0.0, 0.15]}
    paired_from = None
    for stamp in np.round(1.0 + 0.02 * np.arange(0, 40), 2):    # joint states at 50 Hz, a frame with every other
        c.add_state(stamp, (glitched.get(stamp, goal), None))
        if round(stamp * 50) % 2 == 0:
            c.add_frame(stamp, np.full((2, 2), 0.1))
        if c.complete:
            break
        paired_from = c.after
    assert c.complete and len(c.disturbed) == 1
    assert c.disturbed[0][0] == 1.04 and c.disturbed[0][1][1] == pytest.approx(-0.05)
    assert paired_from >= 1.06 + 0.2                          # after the glitch and a whole hold time
    np.testing.assert_allclose(c.sample(0).q[0], goal)
    assert c.shortfall(["a", "b"]).startswith(
        "3 paired, the joint readings left the goal 1 time(s) while the frames were taken (the last: b at "
        "-0.05000 rad, goal -0.20000)")


def test_a_joint_that_leaves_its_goal_for_good_is_named_in_the_shortfall():
    """An arm that sags after settling (torque off) or is held off its goal: no frame is used,
    and the timeout's line names the joint, not the camera."""
    goal = np.zeros(2)
    c = FrameCollector(frames=3, tolerance=0.005, settle=settled(goal), settled_stamp=1.0, settled_state=(goal, None))
    for k in range(1, 30):
        stamp = 1.0 + 0.02 * k
        c.add_state(stamp, (np.array([0.0, -0.01 * k]), None))    # joint b sags
        c.add_frame(stamp, np.zeros((2, 2)))
    assert not c.complete
    assert c.shortfall(["a", "b"]) == ("0 paired, the joint readings left the goal 1 time(s) while the frames were "
                                       "taken (the last: b at -0.01000 rad, goal 0.00000) and have not settled since "
                                       "(b at -0.29000 rad, goal 0.00000)")


def test_one_pose_list_writer_round_trips_with_test_poses(tmp_path):
    robot = load_robot(ROBOT)
    fit = generate_poses(robot, 5, "small", 3, repeats=1)
    poses = with_test_poses(fit, robot, 4, 3)
    assert list(poses.pose) == [0, 1, 2, 3, 4, 0, 5, 6, 7, 8]
    assert list(poses.test) == [False] * 6 + [True] * 4
    np.testing.assert_array_equal(poses.q[:6], fit.q)    # adding test poses leaves the fit poses
    save_poses(poses, tmp_path / "poses.csv")
    back = load_poses(tmp_path / "poses.csv", robot)
    np.testing.assert_array_equal(back.q, poses.q)
    np.testing.assert_array_equal(back.pose, poses.pose)
    np.testing.assert_array_equal(back.test, poses.test)
    # without test poses the text is plan's: pose,q1..qN
    assert format_poses(fit.q[:1]).splitlines()[0] == "pose," + ",".join(f"q{i + 1}" for i in range(7))
    (tmp_path / "bad.csv").write_text(format_poses(fit.q[:1], test=np.array([True])).replace(",1\n", ",yes\n"))
    from laser_calib.io.errors import InputError
    with pytest.raises(InputError, match="line 2, field test: expected 0 or 1"):
        load_poses(tmp_path / "bad.csv", robot)
    # a pose id given to another pose (ids renumbered by hand): measured, and said only by the estimate
    renumbered = format_poses(fit.q[:5]).replace("\n4,", "\n2,")
    (tmp_path / "renumbered.csv").write_text(renumbered)
    with pytest.raises(InputError, match=r"renumbered.csv: pose 2: given 2 times with other joint positions \(q"):
        load_poses(tmp_path / "renumbered.csv", robot)


JOINTS = ["a", "b", "c"]
LOW, HIGH = np.full(3, -1.0), np.full(3, 1.0)


def goal(names, points, **kw):
    return trajectory_goal(names, points, JOINTS, LOW, HIGH, **kw)


def test_trajectory_accepted_as_joint_trajectory_controller_does():
    point = TrajectoryPoint([0.1, 0.2, 0.3], 2.0)
    np.testing.assert_array_equal(goal(["c", "a", "b"], [point]), [0.2, 0.3, 0.1])   # any order
    two = [TrajectoryPoint([0, 0, 0], 1.0, [0.1, 0.1, 0.1]), TrajectoryPoint([0.5, 0.5, 0.5], 2.0, [0, 0, 0])]
    np.testing.assert_array_equal(goal(JOINTS, two), [0.5, 0.5, 0.5])                # the last point
    np.testing.assert_array_equal(goal(JOINTS, [point], start_stamp=10.0, now=11.0), [0.1, 0.2, 0.3])


@pytest.mark.parametrize("names, points, kw, message", [
    ([], [TrajectoryPoint([0, 0, 0], 1.0)], {}, "empty joint names"),
    (["a", "b"], [TrajectoryPoint([0, 0], 1.0)], {}, "partial goals"),
    (["a", "b", "x"], [TrajectoryPoint([0, 0, 0], 1.0)], {}, "joint 'x' is not a controller joint"),
    (["a", "a", "b"], [TrajectoryPoint([0, 0, 0], 1.0)], {}, "partial goals"),
    (JOINTS, [], {}, "empty trajectory"),
    (JOINTS, [TrajectoryPoint([0, 0, 0], 1.0), TrajectoryPoint([0, 0, 0], 1.0)], {}, "not strictly increasing"),
    (JOINTS, [TrajectoryPoint([0, 0], 1.0)], {}, "2 positions for 3 joint names"),
    (JOINTS, [TrajectoryPoint([0, 0, 0], 1.0, [0, 0])], {}, "2 velocities"),
    (JOINTS, [TrajectoryPoint([0, 0, 0], 1.0, [0, 0.1, 0])], {}, "velocity is not zero"),
    (JOINTS, [TrajectoryPoint([0, 0, 0], 1.0)], {"start_stamp": 5.0, "now": 7.0}, "ends in the past"),
    (JOINTS, [TrajectoryPoint([0, 1.5, 0], 1.0)], {}, "b = 1.5 rad outside the joint limits"),
    (JOINTS, [TrajectoryPoint([0, NAN, 0], 1.0)], {}, "not finite"),
])
def test_trajectory_refused_as_joint_trajectory_controller_does(names, points, kw, message):
    with pytest.raises(ValueError, match=message):
        goal(names, points, **kw)


def test_joint_order_maps_a_real_arms_joint_states():
    # joint_state_broadcaster publishes every joint, in its own order, grippers included
    assert joint_order(["finger", "b", "a"], ["a", "b"], 2) == [2, 1]
    assert joint_order(["a", "b"], None, 2) == [0, 1]
    with pytest.raises(ValueError, match="give parameter joint_names"):
        joint_order(["finger", "b", "a"], None, 2)
    with pytest.raises(ValueError, match="joint 'c' .* is not in joint_states"):
        joint_order(["a", "b"], ["a", "c"], 2)
    # a robot joint named twice: two readings, and nothing says which one is the joint's (the first was taken)
    with pytest.raises(ValueError, match="joint 'a' .* is named twice in joint_states"):
        joint_order(["a", "b", "a"], ["a", "b"], 2)
    assert joint_order(["finger", "a", "finger", "b"], ["a", "b"], 2) == [1, 3]  # a joint not read: no matter


def test_move_time_from_the_largest_joint_move():
    assert move_time(np.array([0.0, 1.0]), np.array([0.5, -1.0]), 0.5) == 4.0
    assert move_time(np.zeros(2), np.zeros(2), 0.5) == 0.1      # never 0: the controller would jump


def test_a_collector_short_of_frames_says_what_their_stamps_were():
    """A camera stamping 0 (or on another clock) had every frame ignored as taken before the arm
    settled, and the session ended in 'fewer than 3 spot frames paired', as if the camera were
    slow: the line now says how the frames were stamped."""
    state = (np.zeros(1), None)
    c = FrameCollector(frames=3, tolerance=0.01, settle=settled([0.0]), settled_stamp=1000.0, settled_state=state)
    assert c.shortfall([]) == "no spot frame came since the arm settled"
    for k in range(5):
        c.add_state(1000.0 + 0.02 * k, state)
        c.add_frame(0.0, np.zeros((2, 2)))            # unstamped frames
    assert not c.complete
    assert c.shortfall([]) == ("0 paired, 5 stamped before the arm settled (the last 1000.000 s before: a camera "
                             "stamping 0, or on another clock?)")
    ahead = FrameCollector(frames=3, tolerance=0.01, settle=settled([0.0]), settled_stamp=1000.0, settled_state=state)
    ahead.add_frame(1015.0, np.zeros((2, 2)))         # a camera clock 15 s ahead: waits for joint states
    assert ahead.shortfall([]).endswith("the newest frame is stamped 15.000 s after the newest joint state "
                                      "(a camera clock ahead?)")
    between = FrameCollector(frames=3, tolerance=0.001, settle=settled([0.0]), settled_stamp=1000.0,
                             settled_state=state)
    between.add_frame(1000.01, np.zeros((2, 2)))
    between.add_state(1000.02, state)                 # 10 ms from either joint state: tolerance 1 ms
    assert between.shortfall([]) == "0 paired, 1 without a joint state within the tolerance"


def test_a_driver_stamping_its_joint_states_0_is_named_when_the_arm_does_not_settle():
    """joint_states stamped 0 (a driver of the user's that leaves the header empty) are all before
    the command, so none counts: the session ended in 'arm not settled (no joint state since the
    command)' while joint states came at 50 Hz. The line now says they came, stamped before it."""
    s = SettleDetector(np.zeros(2), SettleRule(), after=1000.0)
    assert s.worst_joint(["a", "b"]) == "no joint state since the command"
    for _ in range(3):
        assert not s.update(0.0, np.zeros(2), None)
    assert s.worst_joint(["a", "b"]) == ("3 joint states since the command, every one stamped before it (the "
                                         "latest 1000.000 s before: a driver stamping 0, or on another clock?)")
    s.update(1000.5, np.array([0.0, 0.5]), None)      # one stamped after it: the usual line
    assert s.worst_joint(["a", "b"]) == "b at 0.50000 rad, goal 0.00000"


def test_the_still_frames_of_a_stream_are_one_sample_per_pose():
    """The estimator's 'stream' input took each still frame as a pose: 20 poses were 222 in the
    estimate, the frames of one pose (its joint disturbance and spots shared) counted as independent,
    the stds 3-4 times too small. StillPoses averages a pose's frames into one sample; a moving pair,
    or a reading off the pose's first by more than the tolerance, ends it."""
    poses = StillPoses(tolerance=0.003)
    first, second = np.array([0.1, 0.2]), np.array([0.5, -0.3])
    spots = [np.array([[0.1, 0.2], [0.3, 0.4]]), np.array([[0.1002, 0.2], [np.nan, np.nan]]),
             np.array([[0.0998, 0.2], [0.3, 0.4]])]
    ended = [poses.add(1.0 + 0.1 * k, first + 0.001 * k, spot, True) for k, spot in enumerate(spots)]
    assert ended == [None, None, None] and poses.pending().q[0] == pytest.approx(first + 0.001)
    assert poses.add(1.3, (first + second) / 2, spots[0], False) is not None       # the arm moves: ended
    assert poses.count == 1 and poses.pending() is None
    assert poses.add(1.4, second, spots[0], True) is None
    sample = poses.add(1.5, second + 0.004, spots[2], True)                          # off the pose: a new one
    assert sample.pose.tolist() == [1] and sample.stamp.tolist() == [1.4] and sample.q[0] == pytest.approx(second)
    assert poses.close().pose.tolist() == [2] and poses.close() is None


def test_a_pose_s_sample_averages_its_frames_and_the_spots_seen_in_half():
    poses = StillPoses(tolerance=0.003)
    spots = [np.array([[0.1, 0.2], [0.3, 0.4]]), np.array([[0.1002, 0.2], [np.nan, np.nan]]),
             np.array([[0.0998, 0.2], [0.3, 0.4]])]
    for k, spot in enumerate(spots):
        poses.add(1.0 + 0.1 * k, np.array([0.1, 0.2]), spot, True)
    sample = poses.close()
    assert sample.spots[0] == pytest.approx(np.array([[0.1, 0.2], [0.3, 0.4]]))   # laser 2 seen in 2 of 3
