"""Arm backend for Dynamixel X-series servos over Protocol 2.0 (dynamixel_sdk).

Joint reading and servo ticks are related per joint by

    q = (ticks - zero_ticks) / ticks_per_rad        [rad]

and joint velocity is Present Velocity (0.229 rev/min per unit of the servo
shaft, 4096 ticks/rev) divided by ticks_per_rad [rad/s]. Arrays are (N,) in the
order of ``DynamixelConfig.joints``.

A servo whose torque is off (switched off from outside, or rebooted) takes goals silently and
never moves: it is found on each ``command()``, and on a ``read()`` that finds a servo still,
off its goal (at most every TORQUE_CHECK_PERIOD, so a servo holding a few ticks short costs
little), and reported as a fault.

Every communication failure stops the arm (torque off, best effort) and raises
:class:`DynamixelError` with one line naming the servo and the fault; the packet
exchange, its retries and status checks are dynamixel_bus.DynamixelBus's. Sync
writes get no status packets, so a dead servo shows up on the next ``read()``,
not on ``command()``.
"""

from __future__ import annotations

import fcntl
import logging
import time
from dataclasses import dataclass
from types import TracebackType
from typing import Sequence

import dynamixel_sdk as dxl
import numpy as np

from laser_calib.hardware.dynamixel_bus import DynamixelBus, DynamixelError, DynamixelPortError, DynamixelSettingError
from laser_calib.hardware.dynamixel_table import (ADDR_GOAL_POSITION, ADDR_PRESENT_POSITION, ADDR_PRESENT_VELOCITY,
                                                  ADDR_PROFILE_VELOCITY, ADDR_TORQUE_ENABLE, int32, model_problem,
                                                  setting_problem)

logger = logging.getLogger(__name__)

# Present Velocity (128..131) and Present Position (132..135) are adjacent: one sync read gets both.
STATE_ADDRESS = ADDR_PRESENT_VELOCITY
STATE_LENGTH = 8

VELOCITY_UNIT = 0.229 * 4096 / 60.0  # [ticks/s] per Present Velocity unit
ARRIVAL_TOLERANCE = 2  # [ticks] about the settle rule's 0.003 rad at 4096 ticks/rev
STILL_VELOCITY = 1  # [Present Velocity units] a unit of jitter allowed
TORQUE_CHECK_PERIOD = 1.0  # [s] between two checks of Torque Enable while a servo is still off its goal


@dataclass(frozen=True)
class DynamixelJointConfig:
    """One joint: servo ``id``, q = (ticks - zero_ticks) / ticks_per_rad, limits min <= q <= max [rad]."""

    id: int
    ticks_per_rad: float
    zero_ticks: int
    min: float
    max: float


@dataclass(frozen=True)
class DynamixelConfig:
    """Bus and joints; ``profile_velocity`` in Profile Velocity units (0.229 rev/min, 0 = no limit);
    ``latency_timer_ms`` the USB adapter's latency timer, of which the SDK waits twice for a reply."""

    port: str
    baudrate: int
    joints: tuple[DynamixelJointConfig, ...]
    profile_velocity: int
    latency_timer_ms: float = 16.0  # FTDI's default, the SDK's assumption

    def __post_init__(self) -> None:
        ids = [joint.id for joint in self.joints]
        if not ids:
            raise ValueError("Dynamixel config: no joints")
        if len(set(ids)) != len(ids):
            raise ValueError(f"Dynamixel config: duplicate servo IDs in {ids}")
        for joint in self.joints:
            if not 0 <= joint.id <= dxl.MAX_ID:
                raise ValueError(f"Dynamixel config: servo ID {joint.id} outside 0..{dxl.MAX_ID}")
            if joint.ticks_per_rad == 0 or not joint.min < joint.max:
                raise ValueError(f"Dynamixel config: servo {joint.id} needs ticks_per_rad != 0 and min < max")


class DynamixelArm(DynamixelBus):
    """N Dynamixel servos as one arm; use as a context manager or call open() and close().

    Thread-safe: a lock serialises bus access, so a node may call read(),
    command() and stop() from different callbacks.
    """

    def __init__(self, config: DynamixelConfig, joint_names: Sequence[str] | None = None):
        n = len(config.joints)
        self.config = config
        self.joint_names: tuple[str, ...] = (
            tuple(joint_names) if joint_names is not None else tuple(f"joint{i + 1}" for i in range(n))
        )
        if len(self.joint_names) != n:
            raise ValueError(f"{len(self.joint_names)} joint names for {n} joints")
        self._ticks_per_rad = np.array([joint.ticks_per_rad for joint in config.joints], dtype=float)
        self._zero_ticks = np.array([joint.zero_ticks for joint in config.joints], dtype=float)
        dxl.port_handler.LATENCY_TIMER = config.latency_timer_ms  # where ROBOTIS has it set: the SDK's module
        super().__init__(config.port, [joint.id for joint in config.joints])
        self._reader = dxl.GroupSyncRead(self._port, self._packet, STATE_ADDRESS, STATE_LENGTH)
        for servo_id in self._ids:
            self._reader.addParam(servo_id)
        self._writer = dxl.GroupSyncWrite(self._port, self._packet, ADDR_GOAL_POSITION, 4)
        self._goal_ticks = np.full(len(self._ids), np.nan)  # NaN: no goal yet, nothing to arrive at
        self._torque_checked = -np.inf  # time.monotonic() of the last check while still off the goal

    def __enter__(self) -> "DynamixelArm":
        try:
            self.open()
        except BaseException:
            # __exit__ is not called when __enter__ raises: release the port here.
            self.close()
            raise
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        log_unconfirmed("close", self.close())

    def open(self) -> None:
        """Open the port, ping every servo (its model must be one of dynamixel_table.MODELS), check
        its settings, set the profile velocity and enable torque. A fault
        stops the arm (_fail); anything else that ends it early (a Ctrl-C between two servos'
        torque on) closes the arm first: the caller never gets it, so nobody else would turn
        the torque of the servos already enabled off."""
        with self._lock:
            try:
                # setBaudRate opens (or reopens) the port at that rate; False means an unsupported rate.
                if not self._port.setBaudRate(self.config.baudrate):
                    raise DynamixelPortError(
                        f"Dynamixel port {self.config.port}: unsupported baud rate {self.config.baudrate}"
                    )
            except OSError as exc:
                raise DynamixelPortError(f"Dynamixel port {self.config.port}: cannot open ({exc})") from exc
            self._claim_port()
        try:
            self._enable()
        except DynamixelError:
            raise
        except BaseException:
            log_unconfirmed("open interrupted", self.close())
            raise

    def _claim_port(self) -> None:
        """An exclusive lock on the open port (flock, as pyserial's exclusive=True takes it): a second
        driver on the bus interleaved its packets with the first's and both sessions failed, one with
        'arm not settled', a cause that blamed the arm. The kernel releases it when the process ends."""
        try:
            fcntl.flock(self._port.ser.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._port.closePort()
            raise DynamixelError(f"Dynamixel port {self.config.port}: in use by another process (another "
                                 "arm_driver or session on this bus?); two drivers on one bus corrupt each other's "
                                 "packets") from None

    def _enable(self) -> None:
        with self._lock:
            with self._io_errors():
                for servo_id in self._ids:
                    problem = model_problem(self._ping(servo_id))
                    if problem:
                        raise self._servo_fault(servo_id, problem, DynamixelSettingError)
                for servo_id, joint, name in zip(self._ids, self.config.joints, self.joint_names):
                    ends = sorted(joint.zero_ticks + q * joint.ticks_per_rad for q in (joint.min, joint.max))
                    problem = setting_problem(lambda address, length: self._read(servo_id, address, length),
                                              name, *ends, self.config.profile_velocity)
                    if problem:
                        raise self._servo_fault(servo_id, problem, DynamixelSettingError)
                ticks, _ = self._read_state()
                # Goal = present before torque on, so enabling torque cannot jump to a stale goal.
                self._write_goal(ticks)
                for servo_id in self._ids:
                    self._write(servo_id, ADDR_PROFILE_VELOCITY, 4, self.config.profile_velocity)
                for servo_id in self._ids:
                    self._write(servo_id, ADDR_TORQUE_ENABLE, 1, 1)

    def command(self, q: np.ndarray) -> None:
        """Send goal joint positions ``q`` (N,) [rad]; ValueError naming the joint if outside its limits."""
        q = np.asarray(q, dtype=float)
        if q.shape != self._ticks_per_rad.shape:
            raise ValueError(f"command has shape {q.shape}, expected {self._ticks_per_rad.shape}")
        for name, value, joint in zip(self.joint_names, q, self.config.joints):
            if not joint.min <= value <= joint.max:  # also refuses NaN
                limits = f"[{joint.min:.6g}, {joint.max:.6g}]"
                raise ValueError(f"{name}: command {value:.6g} rad outside limits {limits}")
        ticks = np.rint(self._zero_ticks + q * self._ticks_per_rad).astype(np.int64)
        with self._lock:
            self._require_open()
            with self._io_errors():
                self._check_torque()
                self._write_goal(ticks)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """Joint positions q (N,) [rad] and velocities (N,) [rad/s], from one sync read."""
        with self._lock:
            self._require_open()
            with self._io_errors():
                ticks, velocity_units = self._read_state()
                if self._stopped_short(ticks, velocity_units):
                    self._torque_checked = time.monotonic()
                    self._check_torque()
        q = (ticks - self._zero_ticks) / self._ticks_per_rad
        return q, velocity_units * VELOCITY_UNIT / self._ticks_per_rad

    def close(self) -> list[int]:
        """Torque off (best effort) and release the port; idempotent. The ids of the servos
        that did not confirm torque off (stop())."""
        unconfirmed = self.stop()
        with self._lock:
            if self._port.is_open:
                self._port.closePort()
        return unconfirmed

    def _require_open(self) -> None:
        if not self._port.is_open:
            raise DynamixelError(f"Dynamixel port {self.config.port}: not open")

    def _stopped_short(self, ticks: np.ndarray, velocity_units: np.ndarray) -> bool:
        """Whether a servo stands still off its goal, where a servo without torque ends up, and
        Torque Enable was not checked in the last TORQUE_CHECK_PERIOD."""
        short = (np.abs(ticks - self._goal_ticks) > ARRIVAL_TOLERANCE) & (np.abs(velocity_units) <= STILL_VELOCITY)
        return bool(short.any()) and time.monotonic() - self._torque_checked >= TORQUE_CHECK_PERIOD

    def _write_goal(self, ticks: np.ndarray) -> None:
        """Sync write Goal Position ``ticks`` (N,) to all servos; no status packets come back."""
        self._goal_ticks = np.asarray(ticks, dtype=float)
        self._writer.clearParam()
        for servo_id, goal in zip(self._ids, ticks):
            self._writer.addParam(servo_id, list(int(goal).to_bytes(4, "little", signed=True)))
        result = self._writer.txPacket()
        if result != dxl.COMM_SUCCESS:
            fault = self._comm_fault(result)
            raise self._fail(f"Dynamixel bus {self.config.port}: goal sync write failed: {fault}")

    def _read_state(self) -> tuple[np.ndarray, np.ndarray]:
        """Present Position [ticks] and Present Velocity [units], each (N,), from one sync read."""
        replies = self._sync_read(self._reader)
        ticks = [int32(data, ADDR_PRESENT_POSITION - STATE_ADDRESS) for data in replies]
        velocity = [int32(data, ADDR_PRESENT_VELOCITY - STATE_ADDRESS) for data in replies]
        return np.array(ticks, dtype=float), np.array(velocity, dtype=float)


def log_unconfirmed(where: str, unconfirmed: list[int]) -> None:
    """An ERROR line naming the servos that did not confirm torque off, where no caller is
    handed their ids (the end of a with block, an open that never returned the arm)."""
    if unconfirmed:
        logger.error("Dynamixel %s: servo(s) %s did not confirm torque off", where, ", ".join(map(str, unconfirmed)))
