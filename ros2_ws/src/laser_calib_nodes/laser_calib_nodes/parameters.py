"""Parameter declaration: every parameter with its description, checked when declared
(one line, exit 2), the run-time ones validated when set; a checked one's rule is in its
descriptor (`ros2 param describe`: "Additional constraints")."""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass
from typing import Any, Callable

from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.node import Node
from rclpy.parameter import Parameter

from laser_calib.measurement.noise_bounds import (JOINT_SIGMA_NOT_GIVEN, MAX_SIGMA_ANGLE, MAX_SPOT_SIGMA,
                                                  SIGMA_LENGTH, joint_sigma_or_unset_problem,
                                                  spot_sigma_or_zero_problem)


class NodeError(RuntimeError):
    """A fatal condition a node reports in one line before exiting non-zero."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Rule:
    """What a parameter's values must be: ``constraint`` in words (its descriptor's), and
    rule(value) -> the problem in one line, or None."""

    constraint: str
    problem: Callable[[Any], str | None]

    def __call__(self, value: Any) -> str | None:
        return self.problem(value)


# each node's run-time parameters (declared with read_only=False) and their rules, for dynamic()
_RUNTIME: weakref.WeakKeyDictionary[Node, dict[str, Rule | None]] = weakref.WeakKeyDictionary()


def declare(node: Node, name: str, default: Any, description: str, read_only: bool = True, type_=None,
            rule: Rule | None = None) -> Any:
    """Declare a parameter with its description (and ``rule``'s constraint); return its value,
    checked against ``rule`` when given (NodeError, exit 2). A run-time one (read_only=False) is
    checked by the same rule when set (dynamic()).

    An integer given for a floating-point parameter is taken as that number
    (``rate:=10`` works); any other type mismatch is a NodeError in one line.
    """
    descriptor = ParameterDescriptor(description=description, read_only=read_only,
                                     additional_constraints=rule.constraint if rule else "")
    if type_ is not None:
        return declare_list(node, name, type_, descriptor)
    descriptor.dynamic_typing = True
    value = node.declare_parameter(name, default, descriptor).value
    if not read_only:
        _RUNTIME.setdefault(node, {})[name] = rule
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    elif type(value) is not type(default):
        raise NodeError(f"parameter {name}: expected {type(default).__name__}, got {type(value).__name__} "
                        f"{value!r}", 2)
    return value if rule is None else checked(name, value, rule)


LIST_ELEMENTS = {Parameter.Type.STRING_ARRAY: str, Parameter.Type.INTEGER_ARRAY: int,
                 Parameter.Type.DOUBLE_ARRAY: float}


def declare_list(node: Node, name: str, type_: Parameter.Type, descriptor: ParameterDescriptor) -> list:
    """A list parameter whose default is empty, its elements checked (NodeError, exit 2; an integer
    is taken for a floating-point element). Declared with a value, an empty list, not as a typed
    parameter without one: rclpy's get_parameters service answers no value at all when one asked
    for has none, so `ros2 param dump` printed `ros__parameters: {}` for the whole node
    (ros2/ros2cli#936). rclpy types an empty list as a byte array, hence dynamic typing, and a
    parameter file's `[]` arrives unset (None)."""
    element = LIST_ELEMENTS[type_]
    descriptor.dynamic_typing = True
    # `ros2 param describe` says 'byte array' for the empty default (rclpy's type of []): say what it takes
    descriptor.additional_constraints = f"a list of {element.__name__} ({type_.name.lower().replace('_', ' ')})"
    value = node.declare_parameter(name, [], descriptor).value
    value = [] if value is None else list(value)
    for item in value:
        if isinstance(item, bool) or not isinstance(item, (int, float) if element is float else element):
            raise NodeError(f"parameter {name}: expected a list of {element.__name__}, got {value!r}", 2)
    return [float(item) for item in value] if element is float else value


def dynamic(node: Node, attributes: dict[str, str]) -> None:
    """Make the node's run-time parameters (declared with read_only=False) settable: attributes
    maps each to the node attribute holding its value. A set request with a wrong type or a
    value the parameter's rule (its declaration's) refuses changes nothing and is answered with
    the reason; an integer for a floating-point parameter is that number."""
    runtime = _RUNTIME.get(node, {})
    if set(attributes) != set(runtime):   # a run-time parameter whose value no attribute would take
        raise ValueError(f"run-time parameters {sorted(runtime)}, attributes given for {sorted(attributes)}")
    rules = {name: (attributes[name], rule or (lambda value: None)) for name, rule in runtime.items()}

    def on_set(params) -> SetParametersResult:
        updates = {}
        for param in params:
            if param.name not in rules:
                continue  # the read-only ones rclpy refuses itself
            attr, check = rules[param.name]
            value, current = param.value, getattr(node, attr)
            if isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            problem = (f"expected {type(current).__name__}, got {type(value).__name__}"
                       if type(value) is not type(current) else check(value))
            if problem:
                return SetParametersResult(successful=False, reason=f"{param.name}: {problem}")
            updates[attr] = value
        for attr, value in updates.items():
            setattr(node, attr, value)
        return SetParametersResult(successful=True)

    def as_declared(params):
        # `ros2 param set NODE spot_sigma 2` sends an integer: stored as given, the parameter turned
        # integer (`param get`: 'Integer value is: 2', `param dump`: 2) while `param describe` still said
        # double. The number is taken as the floating-point value it means, and stored as one.
        out = []
        for param in params:
            if (param.name in rules and param.type_ == Parameter.Type.INTEGER
                    and isinstance(getattr(node, rules[param.name][0]), float)):
                param = Parameter(param.name, Parameter.Type.DOUBLE, float(param.value))
            out.append(param)
        return out

    node.add_pre_set_parameters_callback(as_declared)
    node.add_on_set_parameters_callback(on_set)


def checked(name: str, value: Any, check: Callable[[Any], str | None]) -> Any:
    """value, or a NodeError (exit 2) naming the parameter when check(value) finds a problem."""
    problem = check(value)
    if problem:
        raise NodeError(f"parameter {name}: {problem}", 2)
    return value


non_negative = Rule(">= 0", lambda value: None if math.isfinite(value) and value >= 0
                    else f"expected >= 0, got {value}")
positive = Rule("> 0", lambda value: None if math.isfinite(value) and value > 0 else f"expected > 0, got {value}")


MAX_RATE = 1000.0  # Hz: ros2_control's loop and a Dynamixel bus's fastest reads; above, a timer is a busy loop
rate = Rule(f"> 0 and <= {MAX_RATE:g} Hz", lambda value: None if math.isfinite(value) and 0 < value <= MAX_RATE
            else f"expected > 0 and <= {MAX_RATE:g} Hz, got {value}")


def at_least(minimum: int) -> Rule:
    return Rule(f">= {minimum}", lambda value: None if value >= minimum else f"expected >= {minimum}, got {value}")


def up_to(maximum: float, unit: str, why: str, zero: bool = False) -> Rule:
    """Above 0 (or from 0, with ``zero``) and at most ``maximum`` (in ``unit``); ``why``: what a larger
    value is (units typed wrong)."""
    text = f"{'>=' if zero else '>'} 0 and <= {maximum:g} {unit}"

    def problem(value) -> str | None:
        inside = math.isfinite(value) and (value >= 0 if zero else value > 0) and value <= maximum
        return None if inside else f"expected {text} ({why}), got {value}"
    return Rule(text, problem)


def at_most(maximum: float, unit: str, why: str) -> Rule:
    """0 up to ``maximum`` (in ``unit``)."""
    return up_to(maximum, unit, why, zero=True)


# a joint's noise or disturbance beyond 2 deg is degrees typed as radians (noise_bounds.MAX_SIGMA_ANGLE)
JOINT_NOISE = at_most(MAX_SIGMA_ANGLE, "rad", "more is degrees typed as radians")
# a commanded joint speed: industrial arms' fastest joints turn 3-7 rad/s; 100 was taken, unsaid
JOINT_SPEED = up_to(10.0, "rad/s", "no arm's joints turn faster")
# a frame paired with a joint state half a second away shows another instant of a moving arm
SYNC_TOLERANCE = at_most(0.5, "s", "a pair further apart shows two instants")


def refuse_clock_change(node: Node) -> None:
    """use_sim_time, which rclpy lets any node change at run time: switched on with no /clock, the
    timers of arm_driver and camera_sim stopped, joint_states and frames with them, and the session
    ended 10 s later blaming the arm driver. Our nodes run on the clock they started with."""
    def on_set(params) -> SetParametersResult:
        if any(param.name == "use_sim_time" for param in params):
            return SetParametersResult(successful=False, reason="use_sim_time: set it when the node starts "
                                                                "(-p use_sim_time:=true), not while it runs")
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)


def inside(low: float, high: float) -> Rule:
    """Between low and high, both excluded."""
    return Rule(f"{low:g} < value < {high:g}",
                lambda value: None if low < value < high else f"expected {low:g}..{high:g}, got {value}")


SPOT_SIGMA = Rule(f"0 (estimated) or {SIGMA_LENGTH[0]:g} .. {MAX_SPOT_SIGMA:g} m", spot_sigma_or_zero_problem)
JOINT_SIGMA = Rule(f"{JOINT_SIGMA_NOT_GIVEN:g} (not given), 0 (none) or up to {MAX_SIGMA_ANGLE:g} rad",
                   joint_sigma_or_unset_problem)


def noise(node: Node) -> tuple[float, float]:
    """Declare the estimator's noise parameters, spot_sigma (m) and joint_sigma (rad), run-time (held in
    the node's attributes of the same names: NOISE_ATTRIBUTES for dynamic()), and return their values:
    the command line's --spot-sigma and --joint-sigma, 'not given' written 0 and -1 (a ROS parameter
    cannot be None), for the requests that leave theirs 0 (sample_rows.request_options) and the online
    EKF (session.estimate.online_options)."""
    spot = declare(node, "spot_sigma", 0.0, "Spot sigma, m, for requests with spot_sigma 0 and the online EKF "
                                            "(from its next reset); 0: estimate it (batch) / 1 mm (online).",
                   read_only=False, rule=SPOT_SIGMA)
    joint = declare(node, "joint_sigma", JOINT_SIGMA_NOT_GIVEN,
                    f"Joint-reading sigma, rad (at most {MAX_SIGMA_ANGLE:g}), for requests with joint_sigma 0 and "
                    "the online EKF "
                    "(from its next reset); 0: no joint-reading noise; -1: not given, as laser-calib estimate "
                    "without --joint-sigma: estimated from the residual (batch) "
                    "/ 0 (online).", read_only=False, rule=JOINT_SIGMA)
    return spot, joint


NOISE_ATTRIBUTES = {"spot_sigma": "spot_sigma", "joint_sigma": "joint_sigma"}
