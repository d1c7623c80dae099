"""Argument types of the command line: each checks one text and returns its
value, or raises argparse.ArgumentTypeError (argparse then prints one line and
exits with status 2)."""

from __future__ import annotations

import argparse
import math


def _number(text: str, allow_zero: bool) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise argparse.ArgumentTypeError(f"expected a {'non-negative' if allow_zero else 'positive'} number, "
                                         f"got {text}")
    return value


def positive(text: str) -> float:
    return _number(text, allow_zero=False)


def non_negative(text: str) -> float:
    return _number(text, allow_zero=True)


def _integer(text: str, minimum: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"expected an integer of at least {minimum}, got {text}")
    return value


def non_negative_int(text: str) -> int:
    return _integer(text, 0)


def positive_int(text: str) -> int:
    return _integer(text, 1)


def add_robot_arguments(parser: argparse.ArgumentParser) -> None:
    """--robot (a robot YAML, or a URDF / xacro file with --base and --tip)."""
    parser.add_argument("--robot", required=True, help="robot YAML, or URDF / xacro (then --base and --tip)")
    parser.add_argument("--base", default=None, help="URDF link the chain starts from (the robot's frame {0})")
    parser.add_argument("--tip", nargs="+", default=None,
                        help="URDF link(s) measured: one tip, or several of a tree sharing joints")


def fraction(text: str) -> float:
    """A number strictly between 0 and 1."""
    value = _number(text, allow_zero=False)
    if value >= 1:
        raise argparse.ArgumentTypeError(f"expected a fraction between 0 and 1, got {text}")
    return value
