"""Pairing of two message streams by stamp (ROS-free).

message_filters is not on PyPI, so this is the synchronizer the estimator and
the sequencer use: stream A (joint states, high rate) and stream B (spot frames)
are paired by their header stamps. Each B item is paired with the A item nearest
in time, provided it lies within ``tolerance`` seconds. A pair is emitted as soon
as it is certain: when an A item at or after the B stamp has arrived (nothing
nearer can come, stamps within a stream being increasing), or when the newest A
is already beyond ``tolerance``. A B item with no A item within the tolerance is
dropped and counted in ``dropped``. Pairs come out in B order.
"""

from __future__ import annotations

from bisect import bisect_left
from collections import deque
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

A = TypeVar("A")
B = TypeVar("B")


@dataclass(frozen=True)
class Pair(Generic[A, B]):
    a_stamp: float
    a: Any
    b_stamp: float
    b: Any

    @property
    def skew(self) -> float:
        """b_stamp - a_stamp in seconds."""
        return self.b_stamp - self.a_stamp


class StampSynchronizer:
    """Nearest-stamp pairing of stream A to stream B within a tolerance (s).

    ``history`` bounds how many A items are kept (older ones are forgotten);
    ``max_pending`` bounds the B items waiting for A (the oldest is dropped).
    When both streams back up behind a busy subscriber, B runs ahead of A: an
    executor takes one message of each topic per round, and A has several per B
    item (five joint states per spot frame). A bound of 100 then dropped
    measured frames of any backlog of more than about 125 (a replay at --rate 10:
    65 of 200); 10000 B items (a pair of spots each, about 1 MB) only bound the
    memory of a B stream whose A stream has died.
    """

    def __init__(self, tolerance: float, history: int = 1000, max_pending: int = 10000):
        if not tolerance >= 0:
            raise ValueError(f"tolerance must be >= 0, got {tolerance}")
        self.tolerance = float(tolerance)
        self.history = int(history)
        self.max_pending = int(max_pending)
        self._a_stamps: deque[float] = deque()
        self._a_items: deque[Any] = deque()
        self._pending: deque[tuple[float, Any]] = deque()
        self.dropped = 0
        self.out_of_order = 0

    def reset(self) -> None:
        self._a_stamps.clear()
        self._a_items.clear()
        self._pending.clear()
        self.dropped = 0
        self.out_of_order = 0

    def add_a(self, stamp: float, item: Any) -> list[Pair]:
        stamp = float(stamp)
        if self._a_stamps and stamp < self._a_stamps[-1]:
            self.out_of_order += 1  # a stream going back in time (replay restart): start over
            self._a_stamps.clear()
            self._a_items.clear()
        self._a_stamps.append(stamp)
        self._a_items.append(item)
        while len(self._a_stamps) > self.history:
            self._a_stamps.popleft()
            self._a_items.popleft()
        return self._resolve()

    def add_b(self, stamp: float, item: Any) -> list[Pair]:
        self._pending.append((float(stamp), item))
        while len(self._pending) > self.max_pending:
            self._pending.popleft()
            self.dropped += 1
        return self._resolve()

    def _resolve(self) -> list[Pair]:
        out: list[Pair] = []
        stamps = self._a_stamps
        while self._pending and stamps:
            b_stamp, b_item = self._pending[0]
            if stamps[-1] < b_stamp:
                break  # a later A item could still be nearer: wait for it
            self._pending.popleft()
            best = self._nearest(b_stamp)
            if best is None:
                self.dropped += 1
                continue
            out.append(Pair(stamps[best], self._a_items[best], b_stamp, b_item))
        return out

    def _nearest(self, stamp: float) -> int | None:
        stamps = list(self._a_stamps)
        i = bisect_left(stamps, stamp)
        candidates = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
        if not candidates:
            return None
        best = min(candidates, key=lambda j: (abs(stamps[j] - stamp), -j))
        return best if abs(stamps[best] - stamp) <= self.tolerance else None
