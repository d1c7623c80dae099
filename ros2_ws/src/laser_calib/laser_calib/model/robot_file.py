"""Robot model YAML (conventions.md), read and written with validation."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

import yaml

from laser_calib.io.errors import InputError
from laser_calib.io.read import finite_number, known_keys, load_yaml, read_text, yaml_number
from laser_calib.model.robot import CONVENTIONS, PAPER, Joint, Laser, Robot, Screen, Slm

_KNOWN_KEYS = ("name", "joints", "slm", "lasers", "screen", "gravity", "convention")
# Keys other modules read: effects/catalog.py, measurement/frames.py, diagnosis/verdict.py (rated noise).
EXTRA_KEYS = ("effects", "frames", "spot_sigma", "joint_reading_sigma")
JOINT_KEYS = ("a", "d", "alpha", "theta0", "min", "max", "type")
SLM_KEYS = ("a", "d", "alpha", "theta", "beta")
LASER_KEYS = ("gamma", "beta")
SCREEN_KEYS = ("half_y", "half_z")
# Units check: no arm has a link over 100 m, no fixed angle over 4 pi rad; such a
# value is a length in mm or an angle in degrees.
MAX_LENGTH = 100.0
MAX_ANGLE = 4 * math.pi
LIMIT_ANGLE = 100.0  # joint limits: several turns are possible, 100 rad (5730 deg) is degrees


def _mapping(where: str, value: Any, known: tuple[str, ...]) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise InputError(where, f"expected a mapping, got {type(value).__name__}")
    known_keys(where, value, known)
    return value


def _length(where: str, mapping: Mapping[str, Any], key: str, default: float | None = None) -> float:
    value = yaml_number(where, mapping, key, default)
    if abs(value) > MAX_LENGTH:
        raise InputError(f"{where}.{key}", f"{value:g} m is not a plausible length: lengths are in metres "
                                           "(this looks like millimetres)")
    return value


def _angle(where: str, mapping: Mapping[str, Any], key: str, default: float | None = None,
           limit: float = MAX_ANGLE) -> float:
    value = yaml_number(where, mapping, key, default)
    if abs(value) > limit:
        raise InputError(f"{where}.{key}", f"{value:g} rad is not a plausible angle: angles are in radians "
                                           "(this looks like degrees)")
    return value


def robot_from_dict(data: Any, source: str = "<robot>") -> Robot:
    data = _mapping(source, data, _KNOWN_KEYS + EXTRA_KEYS)
    for key in ("name", "joints"):
        if key not in data:
            raise InputError(source, f"missing key '{key}'")
    if not isinstance(data["name"], str):
        raise InputError(f"{source}: name", f"expected a string, got {type(data['name']).__name__}")
    if not isinstance(data["joints"], list) or not data["joints"]:
        raise InputError(f"{source}: joints", "expected a non-empty list of joints")
    joints = []
    for i, entry in enumerate(data["joints"]):
        where = f"{source}: joints[{i}] (joint {i + 1})"
        entry = _mapping(where, entry, JOINT_KEYS)
        kind = entry.get("type", "revolute")
        if kind not in ("revolute", "prismatic"):
            raise InputError(f"{where}.type", f"expected revolute or prismatic, got {kind!r}")
        prismatic = kind == "prismatic"
        # a prismatic joint's limits are lengths
        limit = (lambda key: _length(where, entry, key)) if prismatic else \
            (lambda key: _angle(where, entry, key, limit=LIMIT_ANGLE))
        joint = Joint(_length(where, entry, "a"), _length(where, entry, "d"), _angle(where, entry, "alpha"),
                      _angle(where, entry, "theta0"), limit("min"), limit("max"), prismatic=prismatic)
        if joint.min >= joint.max:
            raise InputError(where, f"min {joint.min} is not below max {joint.max}")
        joints.append(joint)
    # No slm: a robot without lasers (other sensors) and without SLM parameters.
    slm = None
    if "slm" in data:
        where = f"{source}: slm"
        slm_map = _mapping(where, data["slm"], SLM_KEYS)
        slm = Slm(_length(where, slm_map, "a"), _length(where, slm_map, "d"), _angle(where, slm_map, "alpha"),
                  _angle(where, slm_map, "theta"), beta=_angle(where, slm_map, "beta", 0.0))
    # No lasers: an arm measured by another sensor (sensors/); with an SLM, exactly two.
    laser_list = data.get("lasers", [])
    if not isinstance(laser_list, list) or len(laser_list) not in (0, 2):
        raise InputError(f"{source}: lasers", "expected a list of exactly two lasers")
    if laser_list and slm is None:
        raise InputError(source, "missing key 'slm' (the lasers' module)")
    lasers = []
    for j, entry in enumerate(laser_list):
        where = f"{source}: lasers[{j}]"
        entry = _mapping(where, entry, LASER_KEYS)
        lasers.append(Laser(_angle(where, entry, "gamma"), _angle(where, entry, "beta", 0.0)))
    screen = Screen()
    if "screen" in data:
        where = f"{source}: screen"
        screen_map = _mapping(where, data["screen"], SCREEN_KEYS)
        screen = Screen(_length(where, screen_map, "half_y", 1.0), _length(where, screen_map, "half_z", 1.0))
        if screen.half_y <= 0 or screen.half_z <= 0:
            raise InputError(where, "half sizes must be positive")
    gravity = (0.0, 0.0, -1.0)
    if "gravity" in data:
        g = data["gravity"]
        if not isinstance(g, list) or len(g) != 3:
            raise InputError(f"{source}: gravity", "expected a list of three numbers")
        g = [finite_number(v, f"{source}: gravity[{i}]") for i, v in enumerate(g)]
        norm = math.sqrt(sum(v * v for v in g))
        if not math.isfinite(norm) or norm == 0:
            raise InputError(f"{source}: gravity", "expected a non-zero finite vector")
        gravity = tuple(float(v) / norm for v in g)
    convention = data.get("convention", PAPER)
    if convention not in CONVENTIONS:
        raise InputError(f"{source}: convention", f"expected one of {', '.join(CONVENTIONS)}, got {convention!r}")
    extra = {k: v for k, v in data.items() if k in EXTRA_KEYS}
    return Robot(name=data["name"], joints=tuple(joints), slm=slm, lasers=tuple(lasers), screen=screen,
                 gravity=gravity, convention=convention, extra=extra)


def load_robot(path: str | Path) -> Robot:
    return robot_from_dict(load_yaml(read_text(path), str(path)), str(path))


def robot_to_dict(robot: Robot) -> dict[str, Any]:
    if robot.chain is not None:
        raise ValueError(f"robot '{robot.name}' comes from a URDF: write it with report.urdf_export, not as YAML")
    data: dict[str, Any] = {"name": robot.name}
    if robot.convention != PAPER:
        data["convention"] = robot.convention
    data["joints"] = [
        {"a": j.a, "d": j.d, "alpha": j.alpha, "theta0": j.theta0, "min": j.min, "max": j.max}
        | ({"type": "prismatic"} if j.prismatic else {})
        for j in robot.joints
    ]
    s = robot.slm
    if s is not None:
        data["slm"] = {"a": s.a, "d": s.d, "alpha": s.alpha, "theta": s.theta, "beta": s.beta}
    if robot.lasers:
        data["lasers"] = [{"gamma": laser.gamma, "beta": laser.beta} for laser in robot.lasers]
    data["screen"] = {"half_y": robot.screen.half_y, "half_z": robot.screen.half_z}
    data["gravity"] = list(robot.gravity)
    data.update(robot.extra)
    return _plain(data)


def _plain(value: Any) -> Any:
    """numpy scalars and tuples to plain YAML types, floats at full precision."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "item"):
        return value.item()
    return value


class _FlowListDumper(yaml.SafeDumper):
    """Joints and lasers one per line, as in the shared robot files."""


def _represent_dict(dumper: yaml.SafeDumper, data: dict) -> yaml.Node:
    flow = all(not isinstance(v, (dict, list)) for v in data.values())
    return dumper.represent_mapping("tag:yaml.org,2002:map", data.items(), flow_style=flow)


def _represent_list(dumper: yaml.SafeDumper, data: list) -> yaml.Node:
    flow = all(isinstance(v, (int, float)) for v in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_FlowListDumper.add_representer(dict, _represent_dict)
_FlowListDumper.add_representer(list, _represent_list)


def dump_robot(robot: Robot, header: str = "") -> str:
    text = yaml.dump(robot_to_dict(robot), Dumper=_FlowListDumper, sort_keys=False, width=200)
    comment = "".join(f"# {line}\n" for line in header.splitlines())
    return comment + text


def save_robot(robot: Robot, path: str | Path, header: str = "") -> None:
    Path(path).write_text(dump_robot(robot, header))
