"""The estimator's 'stream' input loses no still frame when its callbacks fall behind (a replay
at --rate 10, or a stall of the process). Its joint_states and spots subscriptions kept the last
50 messages: of 200 still frames replayed 10 times faster, 20 to 84 were counted and the rest
dropped, the spots finding no joint state to pair with, with no line in the log. Then, with
every message kept until taken (KEEP_ALL_QOS), the stamp pairing still dropped
about 65 in the burst: the spots ran ahead of the joint states (five per frame) past its bound
of 100 waiting frames, now 10000. A frame the pairing drops is said in a WARN line with the
count so far, so counted plus said dropped is every frame; here none may be dropped."""

from __future__ import annotations

import re

from ros_harness import ROBOT

FRAMES = 200


def test_a_stream_replayed_fast_loses_no_frame_unsaid(ros):
    ros.start("estimator", "-p", f"robot:={ROBOT}", "-p", "input:=stream", "-p", "markers:=false")
    ros.wait_log("estimator", "input 'stream'", 60)
    got = ros.client("stream-replay", str(ROBOT), str(FRAMES), "10")
    said = [int(n) for n in re.findall(r"stream: (\d+) spot frames dropped so far", ros.log("estimator"))]
    dropped = said[-1] if said else 0
    # every frame (here each a pose of its own) either counted or said dropped, and none dropped; the
    # last pose is counted once the arm moves on from it (its still frames averaged into one sample)
    assert got["sample_count"] + dropped == FRAMES - 1, (got, said, ros.log("estimator")[-2000:])
    assert dropped == 0, said
    assert ros.stop("estimator") == 0
