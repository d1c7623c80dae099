"""The frames of one pose and their average (ROS-free; the sequencer feeds it messages).

From the instant the arm settled, spot frames are paired by stamp with joint
states (sync.StampSynchronizer); the first ``frames`` pairs make the pose's
sample: joint readings averaged over the pairs, and each laser's spot averaged
over the frames that saw it, provided it was seen in at least half of them (a
laser seen in fewer is a flicker at the screen edge or a false detection, and is
reported as not seen rather than as a doubtful value). A joint reading off the goal
while the frames are taken starts them again once the arm has settled anew.
"""

from __future__ import annotations

import numpy as np

from laser_calib.io.samples import Samples
from laser_calib.session.settle import SettleDetector
from laser_calib.session.sync import Pair, StampSynchronizer


def average_frames(pose_id: int, q_frames: np.ndarray, spot_frames: np.ndarray, stamp: float) -> Samples:
    """One sample from F frames: q_frames (F,N) joint readings, spot_frames (F,2,2) NaN where not seen."""
    q_frames = np.asarray(q_frames, dtype=float)
    spot_frames = np.asarray(spot_frames, dtype=float)
    spots = np.full((2, 2), np.nan)
    for j in range(2):
        seen = ~np.isnan(spot_frames[:, j]).any(axis=1)
        if seen.sum() * 2 >= len(spot_frames):
            spots[j] = spot_frames[seen, j].mean(axis=0)
    return Samples(np.array([pose_id]), np.array([stamp]), q_frames.mean(axis=0)[None], spots[None])


class FrameCollector:
    """Pairs of (joint state, spot frame) of one pose, from the settle instant on, while every
    reading stays at the goal.

    Joint state items are (q (N,), velocity (N,) or None); frame items are spots (2,2). A reading
    off the goal (beyond the settle rule's position tolerance) while the frames are taken is a
    disturbance: a glitch of a servo's encoder or bus, or the arm pushed. The pairs so far are
    dropped, since their readings or spots may not be of the pose, and pairing starts again
    once the arm has settled anew by the same rule (``disturbed``: each one's (stamp, q)).
    Averaged in, a glitch of 0.15 rad for two reads of a 50 Hz driver's made a sample 0.15 rad off.
    Velocities are not checked again: one count of a servo's velocity reading (0.024 rad/s on a
    Dynamixel X) is above the settle rule's tolerance, and a moving arm leaves the goal anyway.
    """

    def __init__(self, frames: int, tolerance: float, settle: SettleDetector, settled_stamp: float, settled_state):
        if frames < 1:
            raise ValueError(f"frames: must be at least 1, got {frames}")
        self.frames = frames
        self.tolerance = tolerance
        self.settle = settle                 # the detector that found the arm settled: its goal and rule
        self.resettle: SettleDetector | None = None   # settling anew after a disturbance
        self.disturbed: list[tuple[float, np.ndarray]] = []
        self.early = 0                       # frames stamped before the settle instant
        self.dropped = 0                     # frames without a joint state within the tolerance
        self.last_frame: float | None = None  # the stamp of the newest frame
        self._start(settled_stamp, settled_state)

    def _start(self, stamp: float, state) -> None:
        self.after = float(stamp)
        self.sync = StampSynchronizer(self.tolerance)
        self.pairs: list[Pair] = []
        self.add_state(stamp, state)  # a frame of this very instant pairs with it

    def add_state(self, stamp: float, state) -> None:
        self.last_state = float(stamp)
        q = np.asarray(state[0], dtype=float)
        if self.resettle is not None:
            if self.resettle.update(stamp, q, state[1]):
                self.resettle = None
                self._start(stamp, state)
            return
        if not self.settle.at_goal(q):
            self.disturbed.append((float(stamp), q))
            self.resettle = SettleDetector(self.settle.goal, self.settle.rule, stamp)
            self.resettle.update(stamp, q, state[1])
            self.dropped += self.sync.dropped
            self.pairs, self.sync = [], StampSynchronizer(self.tolerance)
            return
        self.pairs.extend(self.sync.add_a(stamp, state))

    def add_frame(self, stamp: float, spots: np.ndarray) -> None:
        self.last_frame = float(stamp)
        if self.resettle is not None:
            return  # the arm is settling anew
        if stamp >= self.after:  # an earlier frame shows the arm still moving
            self.pairs.extend(self.sync.add_b(stamp, spots))
        elif not self.disturbed:  # before a new start, it is the frame of a disturbed stretch
            self.early += 1

    def shortfall(self, names: list[str]) -> str:
        """Why the frames are not complete, in words naming the stamps (a camera stamping 0, or
        on another clock, looked like a camera too slow) and the joints (``names``, the robot's
        order) that left the goal."""
        if self.last_frame is None:
            return "no spot frame came since the arm settled"
        said = f"{len(self.pairs)} paired"
        if self.disturbed:
            said += (f", the joint readings left the goal {len(self.disturbed)} time(s) while the frames were taken "
                     f"(the last: {self.settle.off_goal(self.disturbed[-1][1], names)})")
            if self.resettle is not None:
                said += f" and have not settled since ({self.resettle.worst_joint(names)})"
        if self.early:
            said += (f", {self.early} stamped before the arm settled (the last {self.after - self.last_frame:.3f} s "
                     f"before: a camera stamping 0, or on another clock?)")
        dropped = self.dropped + self.sync.dropped
        if dropped:
            said += f", {dropped} without a joint state within the tolerance"
        if self.last_frame > self.last_state:
            said += (f"; the newest frame is stamped {self.last_frame - self.last_state:.3f} s after the newest "
                     "joint state (a camera clock ahead?)")
        return said

    @property
    def complete(self) -> bool:
        return len(self.pairs) >= self.frames

    def sample(self, pose_id: int) -> Samples:
        used = self.pairs[:self.frames]
        return average_frames(pose_id, np.array([p.a[0] for p in used]), np.array([p.b for p in used]),
                              used[-1].b_stamp)


class StillPoses:
    """A stream's (joint state, spot frame) pairs grouped into the still poses they show, each
    averaged into one sample (average_frames), as the sequencer averages the frames of a pose.
    The frames of one still pose share its joint disturbance (backlash, compliance, the servo's
    resting error) and its true spots: they are one measurement, not one each. Counted as poses,
    20 poses of a stream were 222 in the estimate, its stds 3-4 times too small and errors 5-8 of
    them off (a new user's probe). A pose ends at a pair whose arm moves (``still`` false) or whose
    reading leaves the pose's first by more than ``tolerance`` (rad or m, per joint)."""

    def __init__(self, tolerance: float):
        self.tolerance = tolerance
        self.count = 0                          # poses closed, each one's id
        self.q: list[np.ndarray] = []           # the open pose's frames: readings (N,), spots (2,2), stamps
        self.spots: list[np.ndarray] = []
        self.stamps: list[float] = []

    def add(self, stamp: float, q: np.ndarray, spots: np.ndarray, still: bool) -> Samples | None:
        """One pair; the pose it ends, as a sample, or None."""
        q = np.asarray(q, dtype=float)
        ended = self.close() if self.q and (not still or np.max(np.abs(q - self.q[0])) > self.tolerance) else None
        if still:
            self.q.append(q)
            self.spots.append(np.asarray(spots, dtype=float))
            self.stamps.append(float(stamp))
        return ended

    def pending(self) -> Samples | None:
        """The open pose's sample so far (a request asks before the arm moves on), None without one."""
        return average_frames(self.count, np.array(self.q), np.array(self.spots), self.stamps[0]) if self.q else None

    def close(self) -> Samples | None:
        """The open pose's sample, None without one; the next pair starts a new pose."""
        sample = self.pending()
        if sample is not None:
            self.count += 1
            self.q, self.spots, self.stamps = [], [], []
        return sample
