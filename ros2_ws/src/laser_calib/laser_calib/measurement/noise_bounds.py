"""The noise levels a sensor can have. A value beyond them is a unit mistake, not
a sensor: millimetres typed as metres, degrees as radians. Every place a noise
level comes in refuses it the same way: the command line (cli.arguments), the
robot file's rated noise (model.robot_file), the estimate options of the ROS
requests and parameters (session.estimate)."""

from __future__ import annotations

import math

# A spot or position noise outside 1 nm .. 1 m is no sensor.
SIGMA_LENGTH = (1e-9, 1.0)
# A spot sigma is a camera's noise on a screen: sub-millimetre to a few millimetres (the paper's +-2 mm
# uniform is 1.15 mm; a 640-pixel camera framing a 4 m wall sees 6 mm a pixel). Over 50 mm (a spot
# scattered over a hand's width) it is no camera but millimetres typed as metres (0.5 for 0.5 mm).
MAX_SPOT_SIGMA = 0.05
# A joint-reading noise is an encoder's: a 12-bit one steps 0.09 deg, a hobby servo's potentiometer
# reads within about 1 deg. Over 0.035 rad (2 deg) it is no encoder but degrees typed as radians (0.1
# for 0.1 deg: 5.7 deg, which weighed every pose by a noise its spots did not show).
MAX_SIGMA_ANGLE = 0.035
# The ROS parameters' and requests' joint sigma that is not given (a ROS parameter cannot be None): as the
# command line without --joint-sigma, estimated from the residual (with the spot sigma, or at the one given).
JOINT_SIGMA_NOT_GIVEN = -1.0


def spot_sigma_problem(value: float) -> str | None:
    """Why ``value`` (m) is no spot sigma, or None."""
    if math.isfinite(value) and SIGMA_LENGTH[0] <= value <= MAX_SPOT_SIGMA:
        return None
    return (f"{value:g} m is not a plausible spot noise for a camera on a screen (expected {SIGMA_LENGTH[0]:g} .. "
            f"{MAX_SPOT_SIGMA:g} m; lengths are in metres)")


def spot_sigma_or_zero_problem(value: float) -> str | None:
    """Why ``value`` (m) is neither 0 (the spot sigma estimated) nor a spot sigma, or None: the
    rule of the ROS requests' and parameters' spot sigma."""
    problem = None if value == 0 else spot_sigma_problem(value)
    return problem and f"{problem}, or 0 to estimate it"


def joint_sigma_problem(value: float) -> str | None:
    """Why ``value`` (rad) is no joint-reading sigma, or None."""
    if math.isfinite(value) and 0 < value <= MAX_SIGMA_ANGLE:
        return None
    return (f"{value:g} rad is not a plausible joint-reading noise (expected more than 0, at most "
            f"{MAX_SIGMA_ANGLE:g} rad; angles are in radians)")


def joint_sigma_or_unset_problem(value: float) -> str | None:
    """Why ``value`` (rad) is neither JOINT_SIGMA_NOT_GIVEN (-1), 0 (no joint-reading noise) nor a
    joint-reading sigma, or None: the rule of the ROS requests' and parameters' joint sigma."""
    problem = None if value in (JOINT_SIGMA_NOT_GIVEN, 0.0) else joint_sigma_problem(value)
    return problem and (f"{problem}, or 0 for none, or {JOINT_SIGMA_NOT_GIVEN:g} for not given (estimated with "
                        "the spot sigma when that is estimated, else 0)")
