"""The checks of a session's launch arguments (name:=value strings) that refuse, in one line
naming the argument (InputError), what the nodes would misread or each refuse in turn, before
any node starts. ROS-free, as graph, which calls them."""

from __future__ import annotations

import difflib
import math
import os
import re

from laser_calib.io.errors import InputError
from laser_calib.io.read import load_yaml
from laser_calib.io.samples import check_lasers
from laser_calib.measurement.noise_bounds import joint_sigma_or_unset_problem, spot_sigma_or_zero_problem
from laser_calib.model.robot_file import load_robot
from laser_calib.session.folder import PLAN_DEFAULTS


def integer(values: dict, name: str) -> int:
    try:
        return int(values[name])
    except ValueError:
        raise InputError(name, f"expected an integer, got {values[name]!r}") from None


def number(values: dict, name: str) -> float:
    try:
        return float(values[name])
    except ValueError:
        raise InputError(name, f"expected a number, got {values[name]!r}") from None


# rcl's namespace rules (rmw_validate_namespace): /-separated tokens of letters, digits and
# underscores, none starting with a digit, no '__'
_NAMESPACE = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")


def namespace(values: dict) -> str:
    """The namespace argument (relative to an including file's, or absolute), '' for none; one
    that breaks rcl's rules is refused here, in one line, before the folder is taken."""
    given = values.get("namespace", "").rstrip("/")   # '/' is the root: none
    if given and (not _NAMESPACE.fullmatch(given) or "__" in given):
        raise InputError("namespace", f"expected a ROS namespace such as rig2 (letters, digits, '_' and '/'), got "
                                      f"{values['namespace']!r}")
    return given


def positive_number(values: dict, name: str) -> float:
    try:
        value = float(values[name])
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise InputError(name, f"expected a positive number, got {values[name]!r}")
    return value


# The noise arguments and the rule of each: the nodes' own for their parameters (the estimator's
# parameters.SPOT_SIGMA and JOINT_SIGMA, the sequencer's estimate options), so that the launch refuses
# what a node would.
NOISE_ARGUMENTS = {"spot_sigma": spot_sigma_or_zero_problem, "joint_sigma": joint_sigma_or_unset_problem}


def noise_params(values: dict) -> tuple[dict, dict]:
    """The estimator's and the sequencer's parameters of the noise arguments given (spot_sigma m,
    joint_sigma rad; an empty one, the parameter file's, is left out). A value the nodes' rule
    refuses: InputError naming it. The estimator gets them too: the sequencer's "not given" (spot
    0, joint -1) goes in its Estimate request as 0, which is the estimator's parameter (a parameter
    file may set another), and the estimator's online EKF then takes the noise stated."""
    noise = {}
    for name, problem_of in NOISE_ARGUMENTS.items():
        if not values[name]:
            continue
        value = number(values, name)
        if problem := problem_of(value):
            raise InputError(name, problem)
        noise[name] = value
    return noise, {f"estimate.{name}": value for name, value in noise.items()}


def existing_files(values: dict, *names: str) -> None:
    """Refuse a file argument naming no file: launch_ros only warns of a missing parameter file
    and starts the nodes with their defaults, a session of other settings than the user's."""
    for name in names:
        if values[name] and not os.path.isfile(values[name]):
            raise InputError(name, f"no such file: {values[name]}")


def loadable_robot(values: dict) -> None:
    """Refuse a robot file that does not load, or has no lasers (InputError naming it), before
    any node starts: each node would refuse it in turn, after the launch had made the session
    folder and its lock. A file completed by robot_description_topic is checked by the nodes,
    with the URDF."""
    if values["robot"] and not values["robot_description_topic"]:
        check_lasers(load_robot(values["robot"]), f"robot: {values['robot']}")


def arm_section(path: str) -> None:
    """Refuse (InputError naming arm_params) a parameter file with no section the arm_driver
    reads: ROS takes nothing from it, and the driver ran on its defaults (a file keyed 'arm:'
    gave a session whose servos never had torque, 'measured' by nobody)."""
    with open(path, encoding="utf-8") as handle:
        data = load_yaml(handle.read(), path)
    sections = [key for key in (data if isinstance(data, dict) else {})
                if key in ("arm_driver", "/arm_driver", "/**") and isinstance(data[key], dict)
                and "ros__parameters" in data[key]]
    if not sections:
        keys = ", ".join(map(str, data)) if isinstance(data, dict) and data else "none"
        raise InputError("arm_params", f"{path} has no 'arm_driver: ros__parameters:' section (its top-level keys: "
                                       f"{keys}): the arm_driver would take none of it")


# The sequencer's parameters besides the pose plan (PLAN_DEFAULTS) and the robot: a launch file
# passes some as its arguments (method, spot_sigma, ...); the others go in its parameter file.
# test_param_dump.py holds this list to the running sequencer's.
SEQUENCER_PARAMETERS = (
    "output_dir", "resume", "joint_names", "move.joint_speed", "settle.position_tolerance",
    "settle.velocity_tolerance", "settle.hold_time", "settle.timeout", "frames", "frame_timeout", "sync_tolerance",
    "wait_timeout", "owner_watch", "unseen_limit", "record_images", "bag.max_segment_seconds", "truth",
    "estimate.method", "estimate.spot_sigma", "estimate.joint_sigma", "estimate.prior", "estimate.robust",
    "estimate.diagnose", "estimate.mode", "estimate.shared_filesystem", "estimate.timeout")


MISSPELT = 0.85  # difflib's similarity from which a name not taken is taken for a misspelt argument


def refuse_ignored_arguments(argv: list[str], spec: dict) -> None:
    """Refuse a name:=value on the command line that names a pose plan argument or a sequencer
    parameter the launch file (its arguments: spec) does not take: `ros2 launch` drops an
    undeclared argument silently, so hardware.launch.py test_poses:=5 (before it took
    test_poses) measured a session without the held-out poses asked for, and record_images:=true
    recorded no image; and a name within MISSPELT of an argument (arm_param). Only those names:
    argv also holds the arguments of a launch file that includes this one."""
    for item in argv:
        name = item.partition(":=")[0]
        if name in spec:
            continue
        if name in PLAN_DEFAULTS:
            raise InputError(name, f"not an argument of this launch file, it would be ignored (its arguments: "
                                   f"{', '.join(spec)})")
        if name in SEQUENCER_PARAMETERS:
            raise InputError(name, "a parameter of the sequencer, not an argument of this launch file: it would be "
                                   "ignored; set it in the sequencer's section of a parameter file given as "
                                   "params:=FILE (as config/session.yaml)")
        # a misspelt argument: hardware.launch.py arm_param:=arm.yaml ran the example Dynamixel file (its
        # port, ids, zero ticks) on whatever adapter was there; an including file's own arguments are
        # rarely this close to one of ours
        close = difflib.get_close_matches(name, list(spec), n=1, cutoff=MISSPELT)
        if close:
            raise InputError(name, f"not an argument of this launch file (did you mean {close[0]}?): it would be "
                                   "ignored")

