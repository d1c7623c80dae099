"""The arm's state on /diagnostics (diagnostic_msgs/DiagnosticArray), where ROS drivers report
their hardware: arm_driver says OK once a second while it runs and ERROR, with the cause, when a
fault makes it stop the arm; the sequencer ends its wait for the arm when an ERROR came and the
joint states stopped after it. A driver that stopped on a servo fault left the sequencer waiting
out settle.timeout, to say 'arm not settled ... has the arm driver stopped?': the cause was in the
driver's own log only, in another terminal when each node runs in its own (`ros2 run`)."""

from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

DIAGNOSTICS = "/diagnostics"  # absolute, as diagnostic_updater publishes and the aggregator subscribes
DIAGNOSTICS_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
PERIOD = 1.0     # s between OK reports: diagnostic_updater's default period
ACK_WAIT = 1.0   # s the fault report waits for its subscribers' acknowledgement before the driver exits


class ArmStatus:
    """The driver's side: its status named '<node>: arm', for the hardware ``hardware_id``."""

    def __init__(self, node, hardware_id: str):
        self.node, self.hardware_id = node, hardware_id
        self.name = f"{node.get_fully_qualified_name()}: arm"
        self.publisher = node.create_publisher(DiagnosticArray, DIAGNOSTICS, DIAGNOSTICS_QOS)
        self.next_ok = 0.0   # monotonic s

    def ok(self, message: str) -> None:
        """An OK report, at most once per PERIOD (called at the joint state rate)."""
        now = time.monotonic()
        if now >= self.next_ok:
            self.next_ok = now + PERIOD
            self.publish(DiagnosticStatus.OK, message)

    def fault(self, message: str) -> None:
        """The ERROR report, sent before the node exits: awaited until its subscribers have it, or
        ACK_WAIT s (a report still in the writer's queue would die with the process)."""
        self.publish(DiagnosticStatus.ERROR, message)
        self.publisher.wait_for_all_acked(Duration(seconds=ACK_WAIT))

    def publish(self, level: bytes, message: str) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.status = [DiagnosticStatus(level=level, name=self.name, message=message, hardware_id=self.hardware_id)]
        self.publisher.publish(msg)


class ArmFaults:
    """The sequencer's side: the last ERROR status on /diagnostics, from any node (a ros2_control
    driver names its statuses its own way), as (monotonic s received, 'name: message')."""

    def __init__(self, node):
        self.last: tuple[float, str] | None = None
        node.create_subscription(DiagnosticArray, DIAGNOSTICS, self.on_diagnostics, DIAGNOSTICS_QOS)

    def on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.level == DiagnosticStatus.ERROR:
                self.last = (time.monotonic(), f"{status.name}: {status.message}")

    def stopped(self, last_state: float, stale: float) -> str | None:
        """'NAME: MESSAGE' of an ERROR received after the last joint state (monotonic s
        ``last_state``), or at most ``stale`` s before it (the two topics keep no order between
        them), when none came for ``stale`` s since: the arm stopped on that fault.
        None otherwise: an ERROR while the states go on (a hot servo a real driver reports)
        ends nothing, and states that stop without one are said by the timeout."""
        if self.last is None or self.last[0] < last_state - stale or time.monotonic() - last_state < stale:
            return None
        return self.last[1]
