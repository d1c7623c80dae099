"""The packet exchange with the Dynamixel Protocol 2.0 servos of one bus (dynamixel_sdk), the
base of :class:`laser_calib.hardware.dynamixel_arm.DynamixelArm`.

Every exchange is bounded by the SDK's packet timeout and retried at most ``ATTEMPTS`` times,
so no call hangs; each status packet's error byte is checked. A fault stops the servos (torque
off, best effort: stop()) and raises :class:`DynamixelError` with one line naming the servo and
the fault.
"""

from __future__ import annotations

import logging
import termios
import threading
from contextlib import contextmanager
from typing import Callable, Iterator

import dynamixel_sdk as dxl

from laser_calib.hardware.dynamixel_table import (ADDR_HARDWARE_ERROR_STATUS, ADDR_TORQUE_ENABLE,
                                                  ERR_INSTRUCTION_CRC, ERRBIT_ALERT, HARDWARE_ERRORS,
                                                  INSTRUCTION_ERRORS)

logger = logging.getLogger(__name__)

ATTEMPTS = 3  # per exchange; only a fault persisting through all of them is reported
STOP_LOCK_TIMEOUT = 2.0  # [s] longer than any exchange in flight on another thread


class StuffedPacketHandler(dxl.Protocol2PacketHandler):
    """Protocol2PacketHandler whose instruction packets really are byte-stuffed.

    In dynamixel_sdk 4.1.0, addStuffing returns a new list when stuffing lengthens the packet, but
    txPacket ignores the return value and sends the unstuffed original: an instruction whose data holds
    FF FF FD (e.g. Goal Position -131073 ticks) would break the protocol. Stuffing in place fixes that.
    """

    def addStuffing(self, packet: list[int]) -> list[int]:
        packet[:] = super().addStuffing(packet)
        return packet


class DynamixelError(RuntimeError):
    """A communication failure, in one line naming the servo (when one is at fault) and the fault."""

    def __init__(self, message: str, servo_id: int | None = None):
        super().__init__(message)
        self.servo_id = servo_id


class DynamixelPortError(DynamixelError, ValueError):
    """The configured port cannot be opened at the configured baud rate: a setting to correct (a
    ValueError, as the other bad settings), not a fault of the bus."""


class DynamixelSettingError(DynamixelError, ValueError):
    """A servo's own setting (Operating Mode, position limits) or model the arm cannot run with: a
    setting to correct, found before its torque is on (dynamixel_table.setting_problem, model_problem)."""


class DynamixelBus:
    """The servos ``ids`` on the serial port ``port``. Thread-safe: a lock serialises bus access."""

    def __init__(self, port: str, ids: list[int]):
        self.port_name = port
        self._ids = ids
        self._port = dxl.PortHandler(port)
        self._packet = StuffedPacketHandler()
        self._lock = threading.RLock()
        self._torque_reader = dxl.GroupSyncRead(self._port, self._packet, ADDR_TORQUE_ENABLE, 1)
        for servo_id in ids:
            self._torque_reader.addParam(servo_id)

    def stop(self) -> list[int]:
        """Torque off on every servo, best effort: never raises (it runs on error paths and must
        not mask the fault being reported), returns within about N * ATTEMPTS packet timeouts.
        Returns the ids of the servos that did not confirm torque off, each after ATTEMPTS writes
        (all of them when the bus could not be used): the caller reports them, since a servo that
        may still hold torque is a safety matter, not a detail of the cleanup."""
        if not self._lock.acquire(timeout=STOP_LOCK_TIMEOUT):
            logger.error("Dynamixel stop: bus still busy after %.1f s; torque left as is", STOP_LOCK_TIMEOUT)
            return list(self._ids)
        try:
            if not self._port.is_open:
                return []
            # The lock means no exchange is in flight; one aborted by an exception may have left the SDK's
            # busy flag set, which would make every packet below fail with "port busy".
            self._port.is_using = False
            # One broadcast first: it reaches every servo that hears the bus, whatever its replies do.
            self._packet.write1ByteTxOnly(self._port, dxl.BROADCAST_ID, ADDR_TORQUE_ENABLE, 0)
            return [servo_id for servo_id in self._ids if not self._torque_off(servo_id)]
        except Exception as exc:
            logger.warning("Dynamixel stop failed: %s", exc)
            return list(self._ids)
        finally:
            self._lock.release()

    def _torque_off(self, servo_id: int) -> bool:
        """Whether the servo confirmed torque off (a status packet) within ATTEMPTS writes: a
        status packet lost to noise must not leave a servo reported as possibly live."""
        for _ in range(ATTEMPTS):
            result, _ = self._packet.write1ByteTxRx(self._port, servo_id, ADDR_TORQUE_ENABLE, 0)
            if result == dxl.COMM_SUCCESS:
                return True
        return False

    def _check_torque(self) -> None:
        """Raise, the servos stopped, naming those whose torque is off, from one sync read: torque
        switched off by someone else (Dynamixel Wizard), a brown-out reboot or an overload shutdown
        the status packets did not flag leaves a servo taking goals silently and never moving."""
        off = [servo_id for servo_id, data in zip(self._ids, self._sync_read(self._torque_reader)) if not data[0]]
        if off:
            servos = f"servo {off[0]}" if len(off) == 1 else f"servos {', '.join(map(str, off))}"
            raise self._fail(f"Dynamixel {servos}: torque is off (switched off from outside this driver, or the "
                             "servo rebooted)", off[0] if len(off) == 1 else None)

    def _fail(self, message: str, servo_id: int | None = None, kind: type[DynamixelError] = DynamixelError
              ) -> DynamixelError:
        """Stop the servos, then return the error (of ``kind``) for the caller to raise."""
        self.stop()
        return kind(message, servo_id)

    def _servo_fault(self, servo_id: int, fault: str, kind: type[DynamixelError] = DynamixelError) -> DynamixelError:
        return self._fail(f"Dynamixel servo {servo_id}: {fault}", servo_id, kind)

    @contextmanager
    def _io_errors(self) -> Iterator[None]:
        """Turn an error of the serial port (e.g. adapter unplugged) into a DynamixelError."""
        try:
            yield
        except (OSError, termios.error) as exc:  # pyserial raises both, termios.error from tcflush
            raise self._fail(f"Dynamixel port {self.port_name}: serial I/O error ({exc})") from exc

    def _comm_fault(self, result: int) -> str:
        if result == dxl.COMM_RX_TIMEOUT:
            return "no answer (status packet timeout)"
        if result == dxl.COMM_RX_CORRUPT:
            return "corrupt status packet (CRC mismatch or truncated)"
        return self._packet.getTxRxResult(result).removeprefix("[TxRxResult] ")

    def _check_status(self, servo_id: int, error: int) -> None:
        """Raise if a status packet's error byte reports a hardware alert or a refused instruction."""
        if error & ERRBIT_ALERT:
            status, result, _ = self._packet.read1ByteTxRx(self._port, servo_id, ADDR_HARDWARE_ERROR_STATUS)
            if result == dxl.COMM_SUCCESS:
                names = ", ".join(name for bit, name in HARDWARE_ERRORS.items() if status & bit) or "unknown"
                detail = f"Hardware Error Status 0x{status:02X} ({names})"
            else:
                detail = f"Hardware Error Status unreadable ({self._comm_fault(result)})"
            raise self._servo_fault(servo_id, f"hardware error bit set in status packet, {detail}")
        if error:
            fault = INSTRUCTION_ERRORS.get(error, f"error 0x{error:02X}")
            raise self._servo_fault(servo_id, f"instruction refused ({fault})")

    def _exchange(self, servo_id: int, what: str, send: Callable[[], tuple], length: int = 0):
        """One instruction to one servo (``send``: the SDK call, giving (data, result, error); a
        ping's data is the model number) and the data of its status packet (``length`` bytes asked
        for, 0: none), once its error byte is checked. A lost, short or corrupt
        reply, or a packet noise damaged on its way to the servo (its CRC error), is sent again,
        up to ATTEMPTS times; ``what`` names the instruction in the fault."""
        for attempt in range(ATTEMPTS):
            data, result, error = send()
            if result == dxl.COMM_SUCCESS and length and len(data) < length:  # the SDK takes a short reply whole
                result = dxl.COMM_RX_CORRUPT
            if result == dxl.COMM_SUCCESS and (error != ERR_INSTRUCTION_CRC or attempt == ATTEMPTS - 1):
                self._check_status(servo_id, error)
                return data
        raise self._servo_fault(servo_id, f"{what} failed: {self._comm_fault(result)}")

    def _ping(self, servo_id: int) -> int:
        """The servo's model number."""
        return self._exchange(servo_id, "ping", lambda: self._packet.ping(self._port, servo_id))

    def _read(self, servo_id: int, address: int, length: int) -> int:
        """One register of one servo (unsigned)."""
        data = self._exchange(servo_id, f"read of address {address}",
                              lambda: self._packet.readTxRx(self._port, servo_id, address, length), length)
        return int.from_bytes(bytes(data), "little")

    def _write(self, servo_id: int, address: int, length: int, value: int) -> None:
        data = list(value.to_bytes(length, "little", signed=value < 0))
        self._exchange(servo_id, f"write of address {address}",
                       lambda: ((), *self._packet.writeTxRx(self._port, servo_id, address, length, data)))

    def _sync_read(self, reader: dxl.GroupSyncRead) -> list[bytes]:
        """The bytes ``reader`` asks of each servo, in the order of the ids, from one sync read (up
        to ATTEMPTS), every status packet's error byte checked."""
        for _ in range(ATTEMPTS):
            failed_id, result, replies = self._sync_read_once(reader)
            if result == dxl.COMM_SUCCESS:
                break
        else:
            where = f"Dynamixel bus {self.port_name}" if failed_id is None else f"Dynamixel servo {failed_id}"
            raise self._fail(f"{where}: sync read failed: {self._comm_fault(result)}", failed_id)
        for servo_id, _, error in replies:
            self._check_status(servo_id, error)
        return [data for _, data, _ in replies]

    def _sync_read_once(self, reader: dxl.GroupSyncRead) -> tuple[int | None, int, list[tuple[int, bytes, int]]]:
        """One sync read: (failed servo ID or None, SDK result, [(servo ID, data, error byte)])."""
        result = reader.txPacket()
        if result != dxl.COMM_SUCCESS:
            return None, result, []
        # GroupSyncRead.rxPacket drops each status packet's error byte and does not say which servo
        # failed, so the status packets are collected here, one servo after the other.
        replies = []
        for servo_id in self._ids:
            data, result, error = self._packet.readRx(self._port, servo_id, reader.data_length)
            if result == dxl.COMM_SUCCESS and len(data) != reader.data_length:  # the SDK takes a short reply whole
                result = dxl.COMM_RX_CORRUPT
            if result != dxl.COMM_SUCCESS:
                return servo_id, result, replies
            replies.append((servo_id, bytes(data), error))
        return None, result, replies
