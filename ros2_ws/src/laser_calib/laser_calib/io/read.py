"""Reading input files: the checks every reader needs, once.

read_text: the file as UTF-8 text (a byte-order mark accepted), or one line
naming the file. csv_rows: its CSV rows, or one line naming the line.
parse_number / parse_int: one CSV field, plain decimal notation only (Python
would read `0_1` as 1 and accepts 10^30 as an id). load_yaml: YAML without
aliases (no recursive anchors, no billion-laughs bombs), duplicated keys or
deep nesting. yaml_number: one number of a YAML mapping. known_keys: unknown
keys refused, naming the nearest known one.
"""

from __future__ import annotations

import csv
import difflib
import io
import math
import re
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import yaml

from laser_calib.io.errors import InputError

# Larger magnitudes are no measurement in SI units (a stamp in ns since 1970 is
# 1.8e18 but our stamps are seconds): refused before they overflow a square.
MAX_MAGNITUDE = 1e12
MAX_ID = 2 ** 53          # ids survive a float round trip
MAX_DEPTH = 32            # YAML nesting; robot files use 3
_DECIMAL = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?(nan|inf|infinity)", re.IGNORECASE)
_INTEGER = re.compile(r"[+-]?\d+")


def read_text(path: str | Path) -> str:
    """The whole file as text; a UTF-8 byte-order mark is dropped."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(str(path), f"cannot read ({exc.strerror or exc})") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise InputError(f"{path}: line {line}", f"not UTF-8 text (byte 0x{data[exc.start]:02x})") from None


def csv_rows(text: str, source: str) -> list[list[str]]:
    reader = csv.reader(io.StringIO(text))
    try:
        return list(reader)
    except csv.Error as exc:
        raise InputError(f"{source}: line {reader.line_num}", f"not valid CSV ({exc})") from None


def looks_numeric(cell: str) -> bool:
    """Whether a CSV field is written as a decimal number (what parse_number reads)."""
    return _DECIMAL.fullmatch(cell.strip()) is not None


def parse_number(cell: str, where: str) -> float:
    """A finite number of plausible size from one CSV field, or one line naming ``where``."""
    text = cell.strip()
    if not _DECIMAL.fullmatch(text):
        raise InputError(where, f"not a number: {cell[:40]!r}" + ("..." if len(cell) > 40 else ""))
    value = float(text)
    if not math.isfinite(value):
        raise InputError(where, f"not finite ({text})")
    if abs(value) > MAX_MAGNITUDE:
        raise InputError(where, f"{text} is beyond {MAX_MAGNITUDE:.0e} (not a plausible SI value)")
    return value


# The first fields of the lines, one per line: each a plain integer of at most 20 digits (the pose id).
_IDS = re.compile(r"(?:[ \t]*[+-]?\d{1,20}[ \t]*\n)*[ \t]*[+-]?\d{1,20}[ \t]*")


def plain_table(text: str) -> tuple[str, np.ndarray] | None:
    """The header line and every data field as a number (P, C) by numpy's C
    reader, when the file is plain: no quotes, underscores or '\\r' in the data, every field
    a finite number of plausible size, the first an integer id; else None (the
    csv module and the checks per column or per field then read it, and name
    the first bad field)."""
    head, _, body = text.partition("\n")
    body = body.rstrip("\n")
    if not body or "\r" in head or any(mark in body for mark in '"_\r'):
        return None
    lines = body.split("\n")
    first = [line.partition(",") for line in lines]
    if not all(comma for _, comma, _ in first) or not _IDS.fullmatch("\n".join(field for field, _, _ in first)):
        return None
    try:
        values = np.loadtxt(lines, delimiter=",", dtype=float, comments=None, ndmin=2)
    except ValueError:  # an empty field, a word, a changing number of fields
        return None
    if (len(values) != len(lines)                            # numpy skips blank lines, the csv module does not
            or not np.isfinite(values).all() or np.any(np.abs(values) > MAX_MAGNITUDE)
            or np.any(np.abs(values[:, 0]) > MAX_ID)):
        return None
    return head, values


def number_column(cells: tuple[str, ...], may_be_empty: bool = False) -> np.ndarray | None:
    """One CSV column (P,) as parse_number reads each field (NaN where empty, if
    ``may_be_empty``), at C speed; None when any field would not pass, so that the
    caller reads it field by field for the one line naming the field. float()
    takes what the plain decimal notation takes, and also underscores and
    nan / inf, which are refused here."""
    if "_" in "".join(cells):
        return None
    try:
        values = np.array(list(map(float, cells)))
    except ValueError:  # an empty field, or no number
        if not may_be_empty:
            return None
        try:
            values = np.array([float(c) if c.strip() else np.nan for c in cells])
        except ValueError:
            return None
    unfinite = ~np.isfinite(values)
    if unfinite.any() and not (may_be_empty and all(not cells[i].strip() for i in np.flatnonzero(unfinite))):
        return None   # nan or inf written out
    if np.any(np.abs(values) > MAX_MAGNITUDE):
        return None
    return values


def integer_column(cells: tuple[str, ...]) -> np.ndarray | None:
    """One CSV column (P,) as parse_int reads each field, or None (number_column)."""
    if "_" in "".join(cells) or max(map(len, (c.strip() for c in cells))) > 20:
        return None
    try:
        values = list(map(int, cells))
    except ValueError:
        return None
    if max(values) > MAX_ID or min(values) < -MAX_ID:
        return None
    return np.array(values, dtype=int)


def parse_int(cell: str, where: str) -> int:
    text = cell.strip()
    if not _INTEGER.fullmatch(text):
        raise InputError(where, f"not an integer: {cell[:40]!r}" + ("..." if len(cell) > 40 else ""))
    if len(text) > 20 or abs(int(text)) > MAX_ID:
        raise InputError(where, f"integer {text[:24]}{'...' if len(text) > 24 else ''} beyond {MAX_ID}")
    return int(text)


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses aliases, duplicated keys and deep nesting."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            mark = self.peek_event().start_mark
            raise yaml.constructor.ConstructorError(None, None, "aliases (*name) are not accepted", mark)
        depth = getattr(self, "_depth", 0)
        if depth > MAX_DEPTH:
            raise yaml.constructor.ConstructorError(None, None, f"nested deeper than {MAX_DEPTH} levels",
                                                    self.peek_event().start_mark)
        self._depth = depth + 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth = depth

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"duplicated key '{key}'", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep)


def load_yaml(text: str, source: str) -> Any:
    try:
        return yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{source}: line {mark.line + 1}" if mark else source
        raise InputError(where, f"not valid YAML ({getattr(exc, 'problem', None) or exc})") from None
    except (ValueError, RecursionError) as exc:  # an int beyond Python's digit limit; pathological nesting
        raise InputError(source, f"not valid YAML ({str(exc)[:80]})") from None


def yaml_number(where: str, mapping: Mapping[str, Any], key: str, default: float | None = None) -> float:
    """mapping[key] as a finite float (ints of any length refused beyond MAX_MAGNITUDE)."""
    if key not in mapping:
        if default is not None:
            return default
        raise InputError(where, f"missing key '{key}'")
    return finite_number(mapping[key], f"{where}.{key}")


def finite_number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(where, f"expected a number, got {type(value).__name__} {str(value)[:40]!r}")
    if isinstance(value, int) and abs(value) > MAX_MAGNITUDE:
        raise InputError(where, f"integer of {len(str(abs(value)))} digits is beyond {MAX_MAGNITUDE:.0e}")
    if not math.isfinite(value):
        raise InputError(where, f"not finite ({value})")
    if abs(value) > MAX_MAGNITUDE:
        raise InputError(where, f"{value:g} is beyond {MAX_MAGNITUDE:.0e} (not a plausible SI value)")
    return float(value)


def length_units(magnitude: float, bound: float) -> str:
    """The units a length of ``magnitude`` beyond ``bound`` (m) was likely written in:
    millimetres, and centimetres as well when the value in cm is within the bound
    (150 typed for a 1.5 m link could be either; 2000 for a 0.3 m spot is not cm)."""
    return "millimetres or centimetres" if abs(magnitude) * 1e-2 <= bound else "millimetres"


def known_keys(where: str, mapping: Mapping[str, Any], known: Iterable[str]) -> None:
    """One line for the first key not in ``known``, naming the nearest known key."""
    known = list(known)
    for key in mapping:
        if key not in known:
            near = difflib.get_close_matches(str(key), known, n=1)
            hint = f"; did you mean '{near[0]}'?" if near else f"; known keys: {', '.join(known)}"
            raise InputError(where, f"unknown key '{key}'{hint}")
