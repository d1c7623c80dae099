"""What the sensor side can plausibly be off by, per sensor kind (docs/effects.md).

Sensor-side effects (the length scale of a point or pose sensor, the residual
distortion of the camera that watches the screen, the shape of the screen)
are estimated like every effect, but a value no such sensor can have is not
a cause, however well it fits: it is another error in disguise (on real
laser-tracker data a 'sensor scale' of +0.18 % stood in for a joint term).
Each has a limit on the absolute value of every parameter, in the
parameter's unit, set by the robot file's optional keys:

- ``sensor_kind``: what measures the arm, one of KIND_LIMITS (default
  ``unspecified``, whose limits only exclude what no working sensor does);
- ``sensor_limits``: a mapping overriding any of ``scale`` (1),
  ``distortion`` (m at the screen edge) and ``screen`` (m at the screen edge).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from laser_calib.effects.base import Effect, positive_number
from laser_calib.io.errors import InputError
from laser_calib.io.read import known_keys
from laser_calib.model.robot import Robot

# Per kind: limits on |scale| (1), on each residual distortion coefficient (m at the
# screen edge) and on each screen-shape coefficient (m at the screen edge).
# - laser tracker: interferometer / ADM with weather compensation, +-20 ppm;
# - total station: EDM +-(1.5 ppm + atmosphere), angles 1": +-50 ppm;
# - motion capture: a wand-calibrated volume, +-0.2 %;
# - camera (a pose from a calibrated camera and a target of known size): +-0.5 %;
# - calibrated camera on the screen: what a lens calibration leaves, 0.5 mm at the
#   edge of a 1 m screen (0.25 px at 2 px/mm); an uncalibrated one (the default of
#   the laser-spot rig) up to 5 mm;
# - screen: a flat screen sags or bows by less than 5 cm over its half size.
KIND_LIMITS: dict[str, dict[str, float]] = {
    "unspecified": {"scale": 0.01, "distortion": 5e-3, "screen": 0.05},
    "laser_tracker": {"scale": 20e-6},
    "total_station": {"scale": 50e-6},
    "motion_capture": {"scale": 2e-3},
    "camera": {"scale": 5e-3},
    "calibrated_camera": {"distortion": 0.5e-3},
}
# Which limit each sensor-side effect kind obeys.
LIMITED = {"sensor_scale": "scale", "camera_distortion": "distortion", "screen_shape": "screen",
           "screen_surface": "screen", "screen_spline": "screen"}


@dataclass(frozen=True)
class Limit:
    """|value| <= limit for every parameter of an effect; ``who`` names the sensor
    ('the laser tracker'), ``quantity`` the limit ('scale')."""

    limit: float
    who: str
    quantity: str

    def describe(self, value: float) -> str:
        if self.quantity == "scale":
            return f"{value * 100:+.3g} % is outside {self.who}'s +-{self.limit * 100:.3g} %"
        return f"{value * 1e3:+.3g} mm is outside {self.who}'s +-{self.limit * 1e3:.3g} mm"


def sensor_kind(robot: Robot, source: str = "robot") -> str:
    kind = robot.extra.get("sensor_kind", "unspecified")
    if kind not in KIND_LIMITS:
        raise InputError(f"{source}: sensor_kind", f"expected one of {', '.join(KIND_LIMITS)}, got {kind!r}")
    return kind


def _given_limits(robot: Robot, source: str) -> Mapping[str, Any]:
    """The robot file's sensor_limits: a mapping of known quantities (KIND_LIMITS['unspecified'])."""
    given: Mapping[str, Any] = robot.extra.get("sensor_limits", {})
    where = f"{source}: sensor_limits"
    if not isinstance(given, Mapping):
        raise InputError(where, f"expected a mapping, got {type(given).__name__}")
    known_keys(where, given, tuple(KIND_LIMITS["unspecified"]))
    return given


def check_sensor_keys(robot: Robot, source: str) -> None:
    """The robot file's sensor_kind and sensor_limits, checked when it is read (model/robot_file.py):
    only a sensor-side effect reads them, after a whole diagnosis, and a typo was taken silently
    until then."""
    sensor_kind(robot, source)
    given = _given_limits(robot, source)
    for quantity in given:
        positive_number(f"{source}: sensor_limits", given, quantity)


def limit_of(effect: Effect, robot: Robot, source: str = "robot") -> Limit | None:
    """The limit of a sensor-side effect on this robot's sensor, None for the arm's own effects."""
    quantity = LIMITED.get(effect.kind)
    if quantity is None:
        return None
    kind = sensor_kind(robot, source)
    given = _given_limits(robot, source)
    if quantity in given:
        return Limit(positive_number(f"{source}: sensor_limits", given, quantity), "the robot file", quantity)
    limits = {**KIND_LIMITS["unspecified"], **KIND_LIMITS[kind]}
    who = f"the {kind.replace('_', ' ')}" if kind != "unspecified" and quantity in KIND_LIMITS[kind] else \
        "any working sensor"
    return Limit(limits[quantity], who, quantity)
