"""The sequencer's bag keeps every joint state and spot frame when its executor falls behind. A
segment roll-over (close, fsync, metadata.yaml) holds the executor thread: measured 40-100 ms, with
record_images 70-400 ms, while a ros2_control arm publishes joint_states at 100-1000 Hz. The
recorder kept the last 200 messages of each topic: at 500 Hz with record_images, 104 of 2371
joint states were missing from the bag (85 behind one 388 ms roll-over), with no line in the log.
Here a burst as fast as the client publishes (2000 joint states, 400 spot frames) across
roll-overs every 0.2 s: the old recorder kept about 1430 of the 2000 joint states; all must be in
the bag. The publishers keep every message until it is taken (history 5 * FRAMES): with a
replay's keep-last 100, a CI machine's other test processes once held the sequencer's DDS
thread long enough for the publisher to overwrite 299 unacknowledged joint states (1701 of 2000
in the bag; 1932 another time), which no subscriber can get back; and the client waits until every
message is acknowledged before it exits, as replay does (946 of 2000 once in CI's full run with
the deeper history alone: a client that exits takes its unacknowledged messages with it). What
is tested is the recorder's part, behind the executor's roll-over stalls."""

from __future__ import annotations

from collections import Counter

from ros_harness import ROBOT

FRAMES = 400  # stream-replay publishes 5 joint states per spot frame


def test_a_burst_across_segment_roll_overs_loses_nothing_in_the_bag(ros, tmp_path):
    from laser_calib.io import bag
    out = tmp_path / "out"
    # no arm listens to joint_trajectory: the sequencer records the burst and waits
    ros.start("sequencer", "-p", f"robot:={ROBOT}", "-p", f"output_dir:={out}", "-p", "poses:=1",
              "-p", "bag.max_segment_seconds:=0.2", "-p", "wait_timeout:=60.0", "-p", "estimate.mode:=none")
    # once both subscriptions of each topic (the sequencer's and its recorder's) have matched
    ros.client("stream-replay", str(ROBOT), str(FRAMES), "100", "2", str(5 * FRAMES))
    assert ros.stop("sequencer") == 0, ros.log("sequencer")[-2000:]
    counts = Counter(topic for topic, *_ in bag.read_messages(out / "bag", ["/joint_states", "/spots"]))
    segments = len(list((out / "bag").glob("*.mcap")))
    assert counts == {"/joint_states": 5 * FRAMES, "/spots": FRAMES}, (counts, segments)
    assert segments > 2, segments  # the burst did cross roll-overs
