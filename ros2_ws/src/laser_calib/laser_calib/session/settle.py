"""Has the arm settled at its goal? (ROS-free; the sequencer feeds it joint states.)

Settled: every |reading - goal| below ``position_tolerance`` (rad) and, when the
arm reports velocities, every |velocity| below ``velocity_tolerance`` (rad/s),
both held without a break for ``hold_time`` seconds of reading stamps. Readings
stamped before the command are ignored: they show the arm before it moved.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SettleRule:
    position_tolerance: float = 0.003
    velocity_tolerance: float = 0.002
    hold_time: float = 0.2

    def __post_init__(self) -> None:
        for name in ("position_tolerance", "velocity_tolerance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"settle.{name}: must be positive, got {getattr(self, name)}")
        if not self.hold_time >= 0:
            raise ValueError(f"settle.hold_time: must be >= 0, got {self.hold_time}")


class SettleDetector:
    """Settling at one goal (N,) commanded at stamp ``after`` (s)."""

    def __init__(self, goal: np.ndarray, rule: SettleRule, after: float):
        self.goal = np.asarray(goal, dtype=float)
        self.rule = rule
        self.after = float(after)
        self.since: float | None = None   # stamp of the first reading of the current calm stretch
        self.last_q: np.ndarray | None = None
        self.early, self.early_stamp = 0, 0.0   # readings stamped before the command: count, latest stamp

    def update(self, stamp: float, q: np.ndarray, velocity: np.ndarray | None) -> bool:
        """Feed one joint state (q (N,), velocity (N,) or None); True once settled."""
        if stamp < self.after:
            self.early, self.early_stamp = self.early + 1, float(stamp)
            return False
        self.last_q = np.asarray(q, dtype=float)
        calm = self.at_goal(self.last_q)
        if velocity is not None:
            calm = calm and bool(np.all(np.abs(velocity) < self.rule.velocity_tolerance))
        if not calm:
            self.since = None
            return False
        if self.since is None:
            self.since = stamp
        return stamp - self.since >= self.rule.hold_time

    def at_goal(self, q: np.ndarray) -> bool:
        """Every reading of q (N,) within the position tolerance of the goal."""
        return bool(np.all(np.abs(q - self.goal) < self.rule.position_tolerance))

    def off_goal(self, q: np.ndarray, names: list[str]) -> str:
        """'<joint> at <reading> rad, goal <goal>' for the joint of q (N,) farthest from its goal."""
        worst = int(np.argmax(np.abs(q - self.goal)))
        return f"{names[worst]} at {q[worst]:.5f} rad, goal {self.goal[worst]:.5f}"

    def worst_joint(self, names: list[str]) -> str:
        """'<joint> at <reading> rad, goal <goal>' for the joint farthest from its goal."""
        if self.last_q is None and self.early:  # readings came, stamped in the past: said, not 'none came'
            return (f"{self.early} joint states since the command, every one stamped before it (the latest "
                    f"{self.after - self.early_stamp:.3f} s before: a driver stamping 0, or on another clock?)")
        if self.last_q is None:
            return "no joint state since the command"
        return self.off_goal(self.last_q, names)
