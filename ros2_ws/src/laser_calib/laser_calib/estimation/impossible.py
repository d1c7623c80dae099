"""Spots that cannot be: refused per pose before a fit (estimate.estimate step 0)."""

from __future__ import annotations

import numpy as np

from laser_calib.io.samples import Samples, check_spot_units
from laser_calib.measurement.base import Residuals
from laser_calib.model.robot import Robot

# A spot given where the nominal beam lands beyond the screen edge by more than
# this fraction of the half size cannot be that laser's: nominal errors move a
# spot by centimetres, not by a fifth of the screen.
MISS_MARGIN = 0.2


def impossible_spots(robot: Robot, samples: Samples, start: Residuals) -> list[tuple[int, int, str]]:
    """(pose index, laser index, reason) of every given spot that cannot be:
    outside the screen, or where the beam misses the screen by far; start: the
    spot model's residuals at zero errors (the nominal model: valid where the beam
    meets the screen plane ahead), or at the minimum a first fit reached (which
    judges again the spots the nominal model refused). Every spot outside the
    screen is a unit error, one line (io.samples.check_spot_units)."""
    # a file's reader has said so naming the file; samples built in code meet the rule here
    check_spot_units(samples.spots, robot, "samples")
    half = np.array([robot.screen.half_y, robot.screen.half_z])
    seen = samples.seen
    out = []
    outside = seen & (np.abs(np.nan_to_num(samples.spots)) > half).any(axis=2)
    beyond = np.abs(start.predicted) - half * (1 + MISS_MARGIN)
    misses = seen & ~outside & ~(start.valid & (beyond <= 0).all(axis=2))
    for p, j in zip(*np.nonzero(outside)):
        y, z = samples.spots[p, j]
        out.append((int(p), int(j), f"outside the screen (y, z = {y:.4g}, {z:.4g} m; half sizes "
                                    f"{half[0]:.4g}, {half[1]:.4g} m)"))
    for p, j in zip(*np.nonzero(misses)):
        out.append((int(p), int(j), "the nominal beam misses the screen by far"))
    return sorted(out)


def judged_again(robot: Robot, samples: Samples, refused: list[tuple[int, int, str]] | tuple,
                 at_minimum: Residuals) -> list[tuple[int, int, str]]:
    """Of the spots ``refused`` at the nominal model, those the minimum a first fit
    reached still finds impossible (its residuals ``at_minimum``): where its beam
    meets the screen, the nominal error was gross, not the spot. It only
    readmits: a beam the minimum moved off the screen, which the nominal one met,
    is the fit's loss (failures.fit_failures), not the spot's fault; refusing it
    would leave a wrong model nothing to fit, and blame the data."""
    units = {(p, c) for p, c, _ in refused}
    return [unit for unit in impossible_spots(robot, samples, at_minimum) if unit[:2] in units]
