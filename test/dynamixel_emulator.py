"""Dynamixel Protocol 2.0 servo emulator on a pseudo-terminal, for tests.

A background thread plays several X-series servos (Model Number ``model_number``, by default an
XM430-W350's, as a ping reports it) on the master side of a pty;
clients open ``emulator.port`` (the slave device) as if it were a USB-serial
adapter. Supported instructions: PING, READ, WRITE, SYNC READ, SYNC WRITE, with
CRC-16 and byte stuffing both ways; an instruction carrying an unstuffed
FF FF FD is dropped, as a real servo would resynchronise on it. The present
position moves toward the goal position at the profile velocity while torque
is enabled, so motion takes time and settles.

Fault switches, set from the test thread on ``emulator.servos[id]``:
``silent`` (the servo never answers), ``corrupt_crc`` (every status packet it
sends carries a wrong CRC), ``lost_torque_offs`` (that many of the next
WRITE instructions of Torque Enable = 0 reaching it, broadcast included, are
lost before the servo, as on a noisy line: not executed and, as Protocol 2.0
has it for an instruction never received, not answered); ``emulator.glitch(id, reads,
ticks)`` (its next reads of Present Position report it off while it stays put: a glitch of
its encoder or of the bus), ``short_reads`` (that many of its next replies to a read
carry half the bytes asked for, with a valid CRC), ``damaged_instructions`` (that many of
the next instructions addressed to it arrive damaged, as by noise: answered with a CRC
error, not executed); and
``emulator.set_hardware_error(id, status)``
(its status packets carry the alert bit 0x80, as a real servo's do after a
hardware fault); ``emulator.switch_torque_off(id)`` (Torque Enable 0 written by
someone else, e.g. Dynamixel Wizard, or a servo that rebooted: no alert bit, and,
as a real servo, it no longer moves toward its goal).

The control table holds an X-series servo's defaults where the driver reads them
(Operating Mode 3, position control; Min/Max Position Limit 0 and 4095; Velocity
Limit 265), and in position control a Goal Position beyond the limits is not
taken, as a real servo refuses it: a WRITE answers Data Limit Error, a SYNC WRITE
(no status) leaves the old goal.

The CRC and stuffing are written independently of dynamixel_sdk, so the tests
that run the SDK against this emulator cross-check both sides.
"""

from __future__ import annotations

import math
import os
import re
import select
import threading
import time
import tty
from collections import deque
from dataclasses import dataclass, field
from types import TracebackType
from typing import Iterable

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
UNSTUFFED_HEADER = re.compile(rb"\xff\xff\xfd(?!\xfd)")  # inside a packet, a protocol violation
LOG_LENGTH = 64  # packets kept in DynamixelEmulator.requests and .replies
MAX_PACKET_LENGTH = 1024  # the SDK's own limit; a longer length field means a misread header

INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_STATUS = 0x55
INST_SYNC_READ = 0x82
INST_SYNC_WRITE = 0x83

# Error field of a status packet (Protocol 2.0).
ERR_INSTRUCTION = 0x02
ERR_CRC = 0x03
ERR_DATA_LENGTH = 0x05
ERR_DATA_LIMIT = 0x06
ERR_ACCESS = 0x07
ERRBIT_ALERT = 0x80

# X-series control table (e.g. XM430-W350), from the ROBOTIS e-Manual. Written here again, not imported
# from laser_calib.hardware.dynamixel_table: the emulator stands for the servo, and an address wrong
# in the driver's table must not be mirrored by the servo it is tested against.
ADDR_MODEL_NUMBER = 0
ADDR_FIRMWARE_VERSION = 6
ADDR_ID = 7
ADDR_OPERATING_MODE = 11
ADDR_VELOCITY_LIMIT = 44
ADDR_MAX_POSITION_LIMIT = 48
ADDR_MIN_POSITION_LIMIT = 52
ADDR_TORQUE_ENABLE = 64
ADDR_HARDWARE_ERROR_STATUS = 70
ADDR_PROFILE_VELOCITY = 112
ADDR_GOAL_POSITION = 116
ADDR_MOVING = 122
ADDR_PRESENT_VELOCITY = 128
ADDR_PRESENT_POSITION = 132
TABLE_SIZE = 147  # through Present Temperature (146)
# Torque Enable, LED, Profile Acceleration, Profile Velocity, Goal Position.
WRITABLE = frozenset(range(64, 66)) | frozenset(range(108, 120))

MODEL_NUMBER = 1020  # XM430-W350
FIRMWARE_VERSION = 6
TICKS_PER_REV = 4096
VELOCITY_UNIT_RPM = 0.229  # Profile Velocity and Present Velocity units
VELOCITY_LIMIT = 265  # Velocity Limit default: the speed when Profile Velocity is 0 (no profile)
POSITION_CONTROL = 3  # Operating Mode default; its goals must lie within Min/Max Position Limit
EXTENDED_POSITION_CONTROL = 4  # multi-turn: the limits do not apply
MIN_POSITION_LIMIT, MAX_POSITION_LIMIT = 0, 4095  # defaults: one turn


def crc16(data: bytes) -> int:
    """CRC-16 of Protocol 2.0 (polynomial 0x8005, initial value 0, not reflected)."""
    crc = 0
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005 if crc & 0x8000 else crc << 1) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Byte stuffing of instruction + parameters: FF FF FD -> FF FF FD FD.

    The pattern cannot overlap itself, so a plain replace is exact.
    """
    return body.replace(b"\xff\xff\xfd", b"\xff\xff\xfd\xfd")


def unstuff(body: bytes) -> bytes:
    """Inverse of :func:`stuff`."""
    return body.replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")


def status_packet(servo_id: int, error: int, params: bytes = b"", corrupt_crc: bool = False) -> bytes:
    """A complete status packet on the wire: header, ID, length, 0x55, error, params, CRC."""
    body = stuff(bytes([INST_STATUS, error]) + params)
    frame = HEADER + bytes([servo_id]) + (len(body) + 2).to_bytes(2, "little") + body
    crc = crc16(frame) ^ (0xFFFF if corrupt_crc else 0)
    return frame + crc.to_bytes(2, "little")


def take_frames(buffer: bytearray) -> list[bytes]:
    """Remove and return the complete packets at the start of ``buffer`` (still stuffed)."""
    frames = []
    while True:
        start = buffer.find(HEADER)
        if start < 0:
            del buffer[: max(0, len(buffer) - (len(HEADER) - 1))]  # keep a possibly split header
            return frames
        del buffer[:start]
        if len(buffer) < 7:
            return frames
        length = int.from_bytes(buffer[5:7], "little")
        if length > MAX_PACKET_LENGTH:
            del buffer[:1]
            continue
        if len(buffer) < 7 + length:
            return frames
        frames.append(bytes(buffer[: 7 + length]))
        del buffer[: 7 + length]


@dataclass
class EmulatedServo:
    """One servo: control table, exact position [ticks] and fault switches.

    ``position`` is continuous; Present Position reports it rounded.
    """

    id: int
    position: float
    table: bytearray = field(default_factory=lambda: bytearray(TABLE_SIZE))
    silent: bool = False
    corrupt_crc: bool = False
    lost_torque_offs: int = 0
    glitched_reads: int = 0
    glitch_ticks: int = 0
    short_reads: int = 0
    damaged_instructions: int = 0

    def get(self, address: int, length: int, signed: bool = False) -> int:
        return int.from_bytes(self.table[address : address + length], "little", signed=signed)

    def put(self, address: int, length: int, value: int, signed: bool = False) -> None:
        self.table[address : address + length] = value.to_bytes(length, "little", signed=signed)

    def reported(self, address: int, length: int) -> bytes:
        """Control-table bytes as a READ or SYNC READ returns them: Present Position off by
        ``glitch_ticks`` in the next ``glitched_reads`` reads that include it; the next
        ``short_reads`` replies carry half the bytes asked for (a bridge or firmware at fault)."""
        data = bytearray(self.table[address : address + length])
        if self.short_reads:
            self.short_reads -= 1
            return bytes(data[: length // 2])
        start = ADDR_PRESENT_POSITION - address
        if self.glitched_reads and 0 <= start and start + 4 <= length:
            self.glitched_reads -= 1
            ticks = int.from_bytes(data[start : start + 4], "little", signed=True) + self.glitch_ticks
            data[start : start + 4] = ticks.to_bytes(4, "little", signed=True)
        return bytes(data)

    def advance(self, dt: float) -> None:
        """Move toward the goal for ``dt`` seconds at the profile velocity, then refresh the table."""
        goal = self.get(ADDR_GOAL_POSITION, 4, signed=True)
        units = self.get(ADDR_PROFILE_VELOCITY, 4) or VELOCITY_LIMIT
        if self.get(ADDR_TORQUE_ENABLE, 1):
            speed = units * VELOCITY_UNIT_RPM / 60.0 * TICKS_PER_REV  # ticks/s
            error = goal - self.position
            self.position += math.copysign(min(abs(error), speed * dt), error)
        moving = self.get(ADDR_TORQUE_ENABLE, 1) and self.position != goal
        direction = 1 if goal > self.position else -1
        self.put(ADDR_MOVING, 1, int(moving))
        self.put(ADDR_PRESENT_VELOCITY, 4, direction * units if moving else 0, signed=True)
        self.put(ADDR_PRESENT_POSITION, 4, round(self.position), signed=True)


class DynamixelEmulator:
    """Several Protocol 2.0 servos behind one pty; use as a context manager or call close()."""

    def __init__(self, ids: Iterable[int] = (1, 2, 3), initial_ticks: int = 2048, model_number: int = MODEL_NUMBER):
        self.servos: dict[int, EmulatedServo] = {}
        for servo_id in ids:
            servo = EmulatedServo(id=servo_id, position=float(initial_ticks))
            servo.put(ADDR_MODEL_NUMBER, 2, model_number)
            servo.put(ADDR_FIRMWARE_VERSION, 1, FIRMWARE_VERSION)
            servo.put(ADDR_ID, 1, servo_id)
            servo.put(ADDR_OPERATING_MODE, 1, POSITION_CONTROL)
            servo.put(ADDR_VELOCITY_LIMIT, 4, VELOCITY_LIMIT)
            servo.put(ADDR_MAX_POSITION_LIMIT, 4, MAX_POSITION_LIMIT)
            servo.put(ADDR_MIN_POSITION_LIMIT, 4, MIN_POSITION_LIMIT)
            servo.put(ADDR_GOAL_POSITION, 4, initial_ticks, signed=True)
            servo.advance(0.0)
            self.servos[servo_id] = servo
        # Raw bytes of recent instructions received and status packets sent, newest last, to check stuffing.
        self.requests: deque[bytes] = deque(maxlen=LOG_LENGTH)
        self.replies: deque[bytes] = deque(maxlen=LOG_LENGTH)
        self._lock = threading.Lock()
        self._clock = time.monotonic()
        self._master, self._slave = os.openpty()
        # Raw before any client opens it: no echo, no newline translation. The emulator keeps its own
        # slave fd open so the master never reads EIO while no client has the port open.
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="dynamixel-emulator", daemon=True)
        self._thread.start()

    def __enter__(self) -> "DynamixelEmulator":
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Stop the thread and release the pty; idempotent."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=2.0)
        os.close(self._master)
        os.close(self._slave)

    def read(self, servo_id: int, address: int, length: int, signed: bool = False) -> int:
        """Control-table value of one servo, as the servo would report it now."""
        with self._lock:
            self._advance()
            return self.servos[servo_id].get(address, length, signed)

    def torque_enabled(self, servo_id: int) -> bool:
        return bool(self.read(servo_id, ADDR_TORQUE_ENABLE, 1))

    def present_position(self, servo_id: int) -> int:
        """Present Position [ticks]."""
        return self.read(servo_id, ADDR_PRESENT_POSITION, 4, signed=True)

    def glitch(self, servo_id: int, reads: int, ticks: int) -> None:
        """The servo's next ``reads`` reads of Present Position report it ``ticks`` off; it stays put."""
        with self._lock:
            servo = self.servos[servo_id]
            servo.glitched_reads, servo.glitch_ticks = reads, ticks

    def set_hardware_error(self, servo_id: int, status: int) -> None:
        """Latch a Hardware Error Status (bit 0x20 = overload, ...); the servo drops torque like a real one."""
        with self._lock:
            self._advance()
            servo = self.servos[servo_id]
            servo.put(ADDR_HARDWARE_ERROR_STATUS, 1, status)
            servo.put(ADDR_TORQUE_ENABLE, 1, 0)
            servo.advance(0.0)

    def switch_torque_off(self, servo_id: int) -> None:
        """Torque off from outside the driver; the servo stays where it is and takes goals without moving."""
        with self._lock:
            self._advance()
            servo = self.servos[servo_id]
            servo.put(ADDR_TORQUE_ENABLE, 1, 0)
            servo.advance(0.0)

    def _advance(self) -> None:
        now = time.monotonic()
        for servo in self.servos.values():
            servo.advance(now - self._clock)
        self._clock = now

    def _run(self) -> None:
        buffer = bytearray()
        while not self._stop.is_set():
            # A short select timeout bounds how long close() waits for this thread.
            ready, _, _ = select.select([self._master], [], [], 0.02)
            if not ready:
                continue
            buffer += os.read(self._master, 4096)
            for frame in take_frames(buffer):
                with self._lock:
                    self._advance()
                    replies = self._handle(frame)
                for reply in replies:
                    os.write(self._master, reply)

    def _handle(self, frame: bytes) -> list[bytes]:
        """Status packets answering one instruction packet (``frame`` as on the wire)."""
        self.requests.append(frame)
        target = frame[4]
        servo = self.servos.get(target)
        if servo is not None and servo.damaged_instructions:  # noise on the line: the servo sees a bad CRC
            servo.damaged_instructions -= 1
            return self._reply(target, ERR_CRC)
        if crc16(frame[:-2]) != int.from_bytes(frame[-2:], "little"):
            return self._reply(target, ERR_CRC)
        if UNSTUFFED_HEADER.search(frame[7:-2]):
            # A real servo would take this for the header of a new packet: the instruction is lost.
            return []
        body = unstuff(frame[7:-2])
        instruction, params = body[0], body[1:]
        if instruction == INST_PING:
            targets = self.servos if target == BROADCAST_ID else [target]
            return [r for servo_id in targets for r in self._reply(servo_id, 0, self._ping_params(servo_id))]
        if instruction == INST_READ:
            return self._read(target, params)
        if instruction == INST_WRITE:
            return self._write(target, params)
        if instruction == INST_SYNC_READ:
            return self._sync_read(params)
        if instruction == INST_SYNC_WRITE:
            self._sync_write(params)
            return []
        return self._reply(target, ERR_INSTRUCTION)

    def _reply(self, servo_id: int, error: int, params: bytes = b"") -> list[bytes]:
        """The status packet of one servo, or none if it is absent, silent or addressed by broadcast."""
        servo = self.servos.get(servo_id)
        if servo is None or servo.silent:
            return []
        if servo.get(ADDR_HARDWARE_ERROR_STATUS, 1):
            error |= ERRBIT_ALERT
        packet = status_packet(servo_id, error, params, corrupt_crc=servo.corrupt_crc)
        self.replies.append(packet)
        return [packet]

    def _ping_params(self, servo_id: int) -> bytes:
        servo = self.servos.get(servo_id)
        if servo is None:
            return b""
        model = servo.table[ADDR_MODEL_NUMBER : ADDR_MODEL_NUMBER + 2]
        return bytes(model + servo.table[ADDR_FIRMWARE_VERSION : ADDR_FIRMWARE_VERSION + 1])

    def _read(self, servo_id: int, params: bytes) -> list[bytes]:
        servo = self.servos.get(servo_id)
        if len(params) != 4:
            return self._reply(servo_id, ERR_DATA_LENGTH)
        address, length = int.from_bytes(params[:2], "little"), int.from_bytes(params[2:], "little")
        if servo is None or address + length > TABLE_SIZE:
            return self._reply(servo_id, ERR_ACCESS)
        return self._reply(servo_id, 0, servo.reported(address, length))

    def _write(self, target: int, params: bytes) -> list[bytes]:
        if len(params) < 3:
            return self._reply(target, ERR_DATA_LENGTH)
        address, data = int.from_bytes(params[:2], "little"), params[2:]
        if not set(range(address, address + len(data))) <= WRITABLE:
            return self._reply(target, ERR_ACCESS)
        targets = self.servos if target == BROADCAST_ID else [target]
        lost = [servo_id for servo_id in targets if self._lost(servo_id, address, data)]
        stored = [self._store(servo_id, address, data) for servo_id in targets if servo_id not in lost]
        return [] if target == BROADCAST_ID or lost else self._reply(target, 0 if all(stored) else ERR_DATA_LIMIT)

    def _lost(self, servo_id: int, address: int, data: bytes) -> bool:
        """Whether this torque-off write to the servo is one of its ``lost_torque_offs``."""
        servo = self.servos.get(servo_id)
        if servo is None or not servo.lost_torque_offs or address != ADDR_TORQUE_ENABLE or data[:1] != b"\x00":
            return False
        servo.lost_torque_offs -= 1
        return True

    def _sync_read(self, params: bytes) -> list[bytes]:
        address, length = int.from_bytes(params[:2], "little"), int.from_bytes(params[2:4], "little")
        if address + length > TABLE_SIZE:
            return []
        # Servos answer one after the other, in the order the instruction lists them.
        return [
            reply
            for servo_id in params[4:]
            if servo_id in self.servos
            for reply in self._reply(servo_id, 0, self.servos[servo_id].reported(address, length))
        ]

    def _sync_write(self, params: bytes) -> None:
        address, length = int.from_bytes(params[:2], "little"), int.from_bytes(params[2:4], "little")
        if not set(range(address, address + length)) <= WRITABLE:
            return
        records = params[4:]
        for start in range(0, len(records) - length, length + 1):
            self._store(records[start], address, records[start + 1 : start + 1 + length])

    def _store(self, servo_id: int, address: int, data: bytes) -> bool:
        """Whether the servo took the data: a Profile Velocity above its Velocity Limit, or in
        Position Control Mode a Goal Position beyond its Min/Max Position Limit, is not taken (a
        WRITE answers Data Limit Error, a SYNC WRITE nothing)."""
        servo = self.servos.get(servo_id)
        if servo is None or servo.silent:
            return True
        if (address == ADDR_PROFILE_VELOCITY and len(data) == 4
                and int.from_bytes(data, "little") > servo.get(ADDR_VELOCITY_LIMIT, 4)):
            return False
        if (address == ADDR_GOAL_POSITION and len(data) == 4
                and servo.get(ADDR_OPERATING_MODE, 1) == POSITION_CONTROL
                and not servo.get(ADDR_MIN_POSITION_LIMIT, 4) <= int.from_bytes(data, "little", signed=True)
                <= servo.get(ADDR_MAX_POSITION_LIMIT, 4)):
            return False
        servo.table[address : address + len(data)] = data
        servo.advance(0.0)
        return True
