"""Robot model YAML (conventions.md), read and written with validation.

Two kinds: a D-H robot (``joints:``), or a robot whose arm is a URDF / xacro
file (``urdf: FILE`` relative to the YAML, ``base:``, ``tip:``, optional
``xacro_args:``) with the laser module, lasers and screen a URDF has no element
for (docs/urdf.md). Written, a URDF robot carries its (calibrated) URDF text
under ``robot_description:``, so the file stands alone; a node that gets the
text from /robot_description gives it to robot_from_dict instead.
"""

from __future__ import annotations

import difflib

import math
from pathlib import Path
from dataclasses import replace
from typing import Any, Mapping, Sequence

import yaml

from laser_calib.io.errors import InputError
from laser_calib.io.read import finite_number, known_keys, load_yaml, read_text, yaml_number
from laser_calib.measurement.frames import robot_frames
from laser_calib.measurement.noise_bounds import joint_sigma_problem, spot_sigma_problem
from laser_calib.model.fit_marks import refuse_failed_fit
from laser_calib.model.robot import (CONVENTIONS, LIMIT_ANGLE, LIMIT_TRAVEL, MAX_ANGLE, MAX_LENGTH, MAX_SLM_OFFSET,
                                     PAPER, Joint, Laser, Robot, Screen, Slm, plausible_angle, plausible_length)
from laser_calib.model.urdf import (calibrated_urdf, check_tips, is_urdf, link_ends, load_urdf_robot,
                                    robot_from_urdf)
from laser_calib.model.urdf_text import urdf_text

_KNOWN_KEYS = ("name", "joints", "slm", "lasers", "screen", "gravity", "convention")
# A URDF robot: the arm from the URDF text (a file, the text itself, or the node's topic).
URDF_KEYS = ("name", "urdf", "robot_description", "xacro_args", "base", "tip", "slm", "lasers", "screen",
             "gravity")
# Keys other modules read: effects/catalog.py, measurement/frames.py, diagnosis/verdict.py (rated noise),
# effects/bounds.py (what the sensor side can plausibly be off by).
EXTRA_KEYS = ("effects", "frames", "spot_sigma", "joint_reading_sigma", "sensor_kind", "sensor_limits", "held")
JOINT_KEYS = ("a", "d", "alpha", "theta0", "min", "max", "type")
SLM_KEYS = ("a", "d", "alpha", "theta", "beta")
LASER_KEYS = ("gamma", "beta")
SCREEN_KEYS = ("half_y", "half_z", "camera")


def _mapping(where: str, value: Any, known: tuple[str, ...]) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise InputError(where, f"expected a mapping, got {type(value).__name__}")
    known_keys(where, value, known)
    return value


def _length(where: str, mapping: Mapping[str, Any], key: str, default: float | None = None,
            bound: float = MAX_LENGTH, what: str = "") -> float:
    return plausible_length(f"{where}.{key}", yaml_number(where, mapping, key, default), bound, what)


def _angle(where: str, mapping: Mapping[str, Any], key: str, default: float | None = None,
           bound: float = MAX_ANGLE) -> float:
    return plausible_angle(f"{where}.{key}", yaml_number(where, mapping, key, default), bound)


def robot_from_dict(data: Any, source: str = "<robot>", folder: Path | None = None,
                    description: str | None = None) -> Robot:
    """A robot from its YAML mapping. ``folder``: where a ``urdf:`` file name is
    looked up (the YAML's folder); ``description``: URDF text from elsewhere
    (the /robot_description topic) for a URDF robot that names no file."""
    if isinstance(data, Mapping) and ("joints" not in data or description is not None):
        robot = _urdf_robot(data, source, folder, description)
    else:
        robot = _dh_robot(data, source)
    robot_frames(robot, source)  # checked here, where the file's name is known (its readers have none)
    _check_held(robot, source)
    _check_sensor(robot, source)
    return robot


def held(robot: Robot) -> tuple[str, ...]:
    """The parameters a calibration that wrote this file could not determine and held at
    nominal (key ``held``): its nominal values are that calibration's, at which those
    parameters lean on others only weakly (d1 and d2 of nearly parallel axes, a 1.3 deg
    alpha1 apart, 57 mm std on a 24-pose set), so a calibration from this file holds
    them too rather than write such a value; deleting the key estimates them."""
    return tuple(robot.extra.get("held", ()))


def held_warnings(robot: Robot, source: str) -> list[str]:
    """The warning of a calibration from the file ``source`` that holds what its key held names, or none."""
    return [f"held at nominal, as the calibration that wrote {source} held them (not determined by its data; "
            f"its key held): {', '.join(held(robot))}"] if held(robot) else []


def with_held(robot: Robot, names) -> Robot:
    """``robot`` whose file says the parameters ``names`` (and those it held already) are held."""
    names = tuple(dict.fromkeys((*held(robot), *names)))
    extra = {k: v for k, v in robot.extra.items() if k != "held"}
    return replace(robot, extra={**extra, "held": list(names)} if names else extra)


# What the robot file says its camera and encoders can do (rated_noise), m and rad.
RATED_NOISE_KEYS = ("spot_sigma", "joint_reading_sigma")


def rated_noise(robot: Robot) -> tuple[float | None, float | None]:
    """What the robot file says its camera and encoders can do: the optional keys spot_sigma (m)
    and joint_reading_sigma (rad), None where absent (the diagnosis's verdict, estimate's warnings)."""
    from laser_calib.effects.base import positive_number  # effects/ reads robots: imported when used

    return tuple(positive_number("robot", robot.extra, key) if key in robot.extra else None
                 for key in RATED_NOISE_KEYS)


def _check_sensor(robot: Robot, source: str) -> None:
    """The keys only a diagnosis reads (rated noise, sensor kind and limits), checked here where the
    file's name is known: their readers run after the work, and some only for some effects."""
    from laser_calib.effects.bounds import check_sensor_keys  # effects/ reads robots: imported when used

    for key, problem in zip(RATED_NOISE_KEYS, (spot_sigma_problem, joint_sigma_problem)):
        if key in robot.extra:
            why = problem(finite_number(robot.extra[key], f"{source}: {key}"))
            if why:
                raise InputError(f"{source}: {key}", why)
    check_sensor_keys(robot, source)


def _check_held(robot: Robot, source: str) -> None:
    value = robot.extra.get("held", [])
    if not isinstance(value, list) or not all(isinstance(name, str) for name in value):
        raise InputError(f"{source}: held", "expected a list of parameter names")
    for i, name in enumerate(value):
        if name not in robot.param_names:
            near = difflib.get_close_matches(name, robot.param_names, n=1)
            raise InputError(f"{source}: held[{i}]", f"'{name}' is no parameter of robot '{robot.name}'"
                                                      + (f"; did you mean '{near[0]}'?" if near else ""))


def _dh_robot(data: Any, source: str) -> Robot:
    """A D-H robot YAML (``joints:``)."""
    data = _mapping(source, data, _KNOWN_KEYS + EXTRA_KEYS)
    for key in ("name", "joints"):
        if key not in data:
            raise InputError(source, f"missing key '{key}'")
    if not isinstance(data["name"], str) or not data["name"].strip():
        raise InputError(f"{source}: name", f"expected the robot's name, got {data['name']!r}")
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
        limit = (lambda key: _length(where, entry, key, bound=LIMIT_TRAVEL, what="prismatic limit")) if prismatic else \
            (lambda key: _angle(where, entry, key, bound=LIMIT_ANGLE))
        joint = Joint(_length(where, entry, "a"), _length(where, entry, "d"), _angle(where, entry, "alpha"),
                      _angle(where, entry, "theta0"), limit("min"), limit("max"), prismatic=prismatic)
        if joint.min >= joint.max:
            raise InputError(where, f"min {joint.min} is not below max {joint.max}")
        joints.append(joint)
    convention = data.get("convention", PAPER)
    if convention not in CONVENTIONS:
        raise InputError(f"{source}: convention", f"expected one of {', '.join(CONVENTIONS)}, got {convention!r}")
    extra = {k: v for k, v in data.items() if k in EXTRA_KEYS}
    return Robot(name=data["name"], joints=tuple(joints), convention=convention, extra=extra,
                 **_lasers_and_screen(data, source))


def _camera(where: str, value: Any) -> tuple[float, float, float] | None:
    """The screen's optional camera centre [x, y, z] (m, frame {0}), off the screen plane."""
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != 3:
        raise InputError(f"{where}.camera", "expected a list of three numbers (the camera centre in metres)")
    named = dict(zip("xyz", value))
    centre = tuple(_length(f"{where}.camera", named, axis) for axis in "xyz")
    if centre[0] == 0:
        raise InputError(f"{where}.camera", "the camera centre lies on the screen plane (x = 0)")
    return centre


def _lasers_and_screen(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """slm, lasers, screen and gravity of a robot mapping (Robot's fields)."""
    # No slm: a robot without lasers (other sensors) and without SLM parameters.
    slm = None
    if "slm" in data:
        where = f"{source}: slm"
        slm_map = _mapping(where, data["slm"], SLM_KEYS)
        a, d = (_length(where, slm_map, key, bound=MAX_SLM_OFFSET) for key in ("a", "d"))
        slm = Slm(a, d, _angle(where, slm_map, "alpha"), _angle(where, slm_map, "theta"),
                  beta=_angle(where, slm_map, "beta", 0.0))
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
    if len(lasers) == 2 and lasers[0] == lasers[1]:  # one beam twice: its spots could not tell the lasers apart
        raise InputError(f"{source}: lasers[1]", "the same gamma and beta as lasers[0]: the two lasers must differ")
    screen = Screen()
    if "screen" in data:
        where = f"{source}: screen"
        screen_map = _mapping(where, data["screen"], SCREEN_KEYS)
        screen = Screen(_length(where, screen_map, "half_y", 1.0), _length(where, screen_map, "half_z", 1.0),
                        _camera(where, screen_map.get("camera")))
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
    return {"slm": slm, "lasers": tuple(lasers), "screen": screen, "gravity": gravity}


def _string(where: str, value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise InputError(where, f"expected a non-empty string, got {value!r}")
    return value


def _urdf_robot(data: Mapping[str, Any], source: str, folder: Path | None, description: str | None) -> Robot:
    """A robot YAML whose arm is a URDF: ``urdf`` (a file), ``robot_description``
    (the text) or ``description`` (given by the caller), exactly one."""
    if "joints" in data:
        raise InputError(source, "is a D-H robot (joints:) and takes no URDF: give a file of base, tip and lasers")
    data = _mapping(source, data, URDF_KEYS + EXTRA_KEYS)
    given = [key for key in ("urdf", "robot_description") if key in data] + (["topic"] if description else [])
    if len(given) != 1:
        raise InputError(source, "missing key 'joints' (a D-H robot) or 'urdf' (a URDF or xacro file)" if not given
                         else f"the URDF is given {len(given)} times ({', '.join(given)}): give it once")
    for key in ("base", "tip"):
        if key not in data:
            raise InputError(source, f"missing key '{key}' (the URDF link the chain "
                                     f"{'starts' if key == 'base' else 'ends'} at)")
    base = _string(f"{source}: base", data["base"])
    tips = data["tip"] if isinstance(data["tip"], list) else [data["tip"]]
    tips = check_tips([_string(f"{source}: tip", tip) for tip in tips], source)
    if "xacro_args" in data and not (isinstance(data.get("urdf"), str) and data["urdf"].lower().endswith(".xacro")):
        raise InputError(f"{source}: xacro_args", "applies to a 'urdf:' file ending in .xacro only")
    if "urdf" in data:
        name = _string(f"{source}: urdf", data["urdf"])
        path = Path(folder or ".") / name
        if not is_urdf(path):
            raise InputError(f"{source}: urdf", f"expected a .urdf, .xacro or .xml file, got {name!r}")
        if not path.is_file():
            raise InputError(f"{source}: urdf", f"no file {path}")
        args = data.get("xacro_args", {})
        if not isinstance(args, Mapping) or not all(isinstance(v, (str, int, float)) for v in args.values()):
            raise InputError(f"{source}: xacro_args", "expected a mapping of argument names to values")
        text = urdf_text(path, {str(k): str(v) for k, v in args.items()}, f"{source}: xacro_args")
        where = str(path)
    else:
        text = description if description is not None else _string(f"{source}: robot_description",
                                                                    data["robot_description"])
        where = source if description is None else f"{source} (robot description)"
    name = data.get("name")
    if name is not None and (not isinstance(name, str) or not name.strip()):
        raise InputError(f"{source}: name", f"expected the robot's name, got {name!r}")
    parts = _lasers_and_screen(data, source)
    if parts["slm"] is not None and len(tips) > 1:
        # the spots follow one chain: the second tip's joints were held unseen, and nothing said why
        raise InputError(f"{source}: tip", f"the laser module is fixed to one link: give that link alone, not "
                                           f"{len(tips)} ({', '.join(tips)}); several tips are for point and pose "
                                           "samples (calibrate-poses, docs/urdf.md)")
    try:
        robot = robot_from_urdf(text, base, tips, where, slm=parts["slm"], lasers=parts["lasers"],
                                screen=parts["screen"], name=name)
    except InputError as exc:  # a link or joint of the URDF: name the robot file that chose it too
        raise InputError(exc.where, f"{exc.problem} (robot file {source})") from None
    extra = {k: v for k, v in data.items() if k in EXTRA_KEYS}
    return replace(robot, gravity=parts["gravity"], extra=extra)


def load_robot(path: str | Path, description: str | None = None, failed_fit: bool = False) -> Robot:
    """A robot YAML; ``description``: the URDF text of a URDF robot whose YAML names none.
    failed_fit: read a fit's output even when it says it is no calibration (to compare it with the truth)."""
    if is_urdf(path):
        raise InputError(str(path), "a URDF has no lasers: give a robot YAML with 'urdf: FILE', 'base:', 'tip:' "
                                    "and 'slm:' / 'lasers:' / 'screen:' (docs/urdf.md)")
    text = read_text(path)
    if not failed_fit:
        refuse_failed_fit(text, str(path))
    return robot_from_dict(load_yaml(text, str(path)), str(path), Path(path).parent, description)


def load_robot_description(path: str | Path, base: str | None = None, tip: Sequence[str] | str | None = None) -> Robot:
    """--robot: a robot YAML, or a URDF / xacro file with its base and tip link(s) (no lasers)."""
    if is_urdf(path):
        if not base or not tip:
            ends = link_ends(urdf_text(path))  # which links to choose from (the file's own errors first)
            raise InputError(str(path), "a URDF robot needs --base LINK and --tip LINK"
                                        + (f" ({ends})" if ends else ""))
        return load_urdf_robot(path, base, tip)
    if base or tip:
        raise InputError(str(path), "--base / --tip apply to a URDF or xacro robot only (a robot YAML names them "
                                    "with 'base:' and 'tip:')")
    return load_robot(path)


def robot_to_dict(robot: Robot) -> dict[str, Any]:
    data: dict[str, Any] = {"name": robot.name}
    if robot.chain is not None:  # its values folded into the joint origins: read back, the same robot
        tips = list(robot.chain.tip_links)
        data.update(base=robot.chain.base, tip=tips[0] if len(tips) == 1 else tips)
    else:
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
    if robot.screen.camera is not None:
        data["screen"]["camera"] = list(robot.screen.camera)
    data["gravity"] = list(robot.gravity)
    data.update(robot.extra)
    if robot.chain is not None:  # last: the long text after the short keys
        data["robot_description"] = calibrated_urdf(robot)
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


def _represent_str(dumper: yaml.SafeDumper, data: str) -> yaml.Node:
    # A URDF text as a block, line by line as in the file.
    return dumper.represent_scalar("tag:yaml.org,2002:str", data, style="|" if "\n" in data else None)


_FlowListDumper.add_representer(dict, _represent_dict)
_FlowListDumper.add_representer(str, _represent_str)
_FlowListDumper.add_representer(list, _represent_list)


def dump_robot(robot: Robot, header: str = "") -> str:
    text = yaml.dump(robot_to_dict(robot), Dumper=_FlowListDumper, sort_keys=False, width=200)
    comment = "".join(f"# {line}\n" for line in header.splitlines())
    return comment + text


def save_robot(robot: Robot, path: str | Path, header: str = "") -> None:
    Path(path).write_text(dump_robot(robot, header))
