"""The Dynamixel X-series control table as the arm backend uses it (ROBOTIS e-manual), and
the servo settings it checks when it opens the arm.

A servo's own settings decide whether it follows a goal at all: in velocity, current or PWM
control (Operating Mode) it ignores Goal Position, and in position control (mode 3) it
ignores a goal beyond its Min/Max Position Limit (a SYNC WRITE gets no status back). Either
way the arm never reaches the pose, and the session ended in "arm not settled" naming a joint
but not why. So each servo's mode, and in position control its limits against the joint's
range in ticks, are read before its torque is enabled, and its Velocity Limit against the
profile velocity the driver would write (refused as "data limit error", no register named).

Before that, each servo's model number (a ping's reply) must be one of MODELS: a servo of
another family (MX(2.0), PRO, AX) answers a ping too, but its registers lie elsewhere, so the
writes below would land on other registers of it.
"""

from __future__ import annotations

from typing import Callable

ADDR_OPERATING_MODE = 11
ADDR_VELOCITY_LIMIT = 44
ADDR_MAX_POSITION_LIMIT = 48
ADDR_MIN_POSITION_LIMIT = 52
ADDR_TORQUE_ENABLE = 64
ADDR_HARDWARE_ERROR_STATUS = 70
ADDR_PROFILE_VELOCITY = 112
ADDR_GOAL_POSITION = 116
ADDR_PRESENT_VELOCITY = 128
ADDR_PRESENT_POSITION = 132

# Model Number -> name of the servos whose control table has the addresses above: ROBOTIS e-Manual
# control tables, Dynamixel2Arduino src/actuator.h and dynamixel-workbench dynamixel_item.h; the XL330s
# (the small arms' servo) as LeRobot drives them, with its X-series table; the XC330s and the XD430-T350
# as ROBOTIS's dynamixel_hardware_interface lists them (param/dxl_model/dynamixel.model) and its control
# tables for them put each address above where it is here. The XD540-T270 (1101) is left out: its table
# was not seen.
MODELS = {
    1190: "XL330-M077", 1200: "XL330-M288",
    1210: "XC330-T181", 1220: "XC330-T288", 1230: "XC330-M181", 1240: "XC330-M288",
    1060: "XL430-W250", 1090: "2XL430-W250", 1070: "XC430-W150", 1080: "XC430-W240", 1160: "2XC430-W250",
    1030: "XM430-W210", 1020: "XM430-W350", 1130: "XM540-W150", 1120: "XM540-W270",
    1010: "XH430-W210", 1000: "XH430-W350", 1050: "XH430-V210", 1040: "XH430-V350",
    1110: "XH540-W150", 1100: "XH540-W270", 1150: "XH540-V150", 1140: "XH540-V270",
    1001: "XD430-T350", 1011: "XD430-T210", 1111: "XD540-T150",
    1280: "XW430-T200", 1270: "XW430-T333", 1180: "XW540-T140", 1170: "XW540-T260",
}

POSITION_CONTROL = 3  # the only mode whose goals Min/Max Position Limit bound (one turn)
# Operating Mode values; the three position modes follow Goal Position
MODES = {0: "current control", 1: "velocity control", 3: "position control", 4: "extended position control",
         5: "current-based position control", 16: "PWM control"}
GOAL_MODES = (3, 4, 5)

ERRBIT_ALERT = 0x80
ERR_INSTRUCTION_CRC = 3  # the servo got our packet damaged (line noise): worth sending again
INSTRUCTION_ERRORS = {
    1: "result fail",
    2: "instruction error",
    3: "CRC error in the instruction packet",
    4: "data range error",
    5: "data length error",
    6: "data limit error",
    7: "access error",
}
HARDWARE_ERRORS = {
    0x01: "input voltage",
    0x04: "overheating",
    0x08: "motor encoder",
    0x10: "electrical shock",
    0x20: "overload",
}


def int32(data: bytes, offset: int) -> int:
    """The signed 4-byte little-endian register at ``offset`` of ``data``."""
    return int.from_bytes(data[offset : offset + 4], "little", signed=True)


def setting_problem(read: Callable[[int, int], int], joint_name: str, low_ticks: float, high_ticks: float,
                    profile_velocity: int) -> str | None:
    """Why a servo cannot drive the joint ``joint_name`` over its range [low_ticks, high_ticks]
    at ``profile_velocity`` (dynamixel.profile_velocity), or None; ``read(address, length)``
    reads one register of the servo (unsigned)."""
    limit = read(ADDR_VELOCITY_LIMIT, 4)
    if profile_velocity > limit:  # the servo refuses the write: a Data Limit Error naming no register
        return (f"dynamixel.profile_velocity {profile_velocity} is above the servo's Velocity Limit {limit} "
                "(0.229 rev/min units): lower it, or 0 for the limit itself")
    mode = read(ADDR_OPERATING_MODE, 1)
    if mode not in GOAL_MODES:
        return (f"Operating Mode {mode} ({MODES.get(mode, 'unknown')}) ignores goal positions: set it to "
                f"{POSITION_CONTROL} (position control) with the servo's torque off (Dynamixel Wizard)")
    if mode != POSITION_CONTROL:
        return None
    minimum, maximum = read(ADDR_MIN_POSITION_LIMIT, 4), read(ADDR_MAX_POSITION_LIMIT, 4)
    if minimum <= low_ticks and high_ticks <= maximum:
        return None
    return (f"{joint_name}'s range is ticks {low_ticks:.0f} .. {high_ticks:.0f}, beyond the servo's Min/Max Position "
            f"Limit {minimum} .. {maximum}, where it ignores a goal (the arm would not settle there): narrow "
            "dynamixel.min/max or the robot's joint range, or widen the servo's limits")


def model_problem(model_number: int) -> str | None:
    """Why a servo of ``model_number`` cannot be driven with this control table, or None."""
    if model_number in MODELS:
        return None
    return (f"model number {model_number} is not an X-series servo of the control table this driver uses "
            "(laser_calib.hardware.dynamixel_table.MODELS): its registers lie elsewhere, so nothing was written to it")
