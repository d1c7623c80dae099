"""The warnings that say an estimate is no calibration. The console prints them as
error lines and the command exits with status 3 (cli.arguments.print_warnings); the
files are still written (they show where the fit went) but a script must not take
them for a calibration. And the errors of a fit that has nothing to fit at its start:
no spot there (NoSpotToFit), or none because the fit it starts from moved the beams
off the screen (FitMovedBeams)."""

from __future__ import annotations

from laser_calib.io.errors import InputError

NOT_CONVERGED = "NOT CONVERGED"          # the fit stopped before a minimum
NOT_A_CALIBRATION = "NOT A CALIBRATION"  # a minimum the fit reached by dropping measurements
FAILURES = (NOT_CONVERGED, NOT_A_CALIBRATION)


def is_failure(warning: str) -> bool:
    """The warning says the estimate is no calibration: it starts with one of FAILURES."""
    return warning.startswith(FAILURES)


def first_failure(warnings) -> str | None:
    """The first of an estimate's warnings that says it is no calibration, None when none does."""
    return next((w for w in warnings if is_failure(w)), None)


class NoSpotToFit(ValueError):
    """No measured spot at the start of a fit (estimate_model): every one missing, refused,
    or its beam misses the screen there."""

    def __init__(self):
        super().__init__("no measured spot to fit (every spot missing, refused, or its beam misses the screen)")


class FitMovedBeams(InputError):
    """The nominal model's beams meet the screen at ``nominal`` measured spots, but a fit
    moved them off it: one started from its errors keeps ``kept`` spots, too few for
    ``n_free`` parameters. A wrong robot model does this (a revolute joint marked
    prismatic, an axis, units), not the data; the command names the robot file."""

    def __init__(self, nominal: int, kept: int, n_free: int):
        moved = "every beam off it" if kept == 0 else f"all but {kept} beams off it, too few to fit {n_free} parameters"
        super().__init__("robot", f"the nominal model's beams meet the screen at {nominal} measured spots, but the "
                                  f"fit moved {moved}: the robot model is likely wrong; check its joint types, axes "
                                  "and units")
