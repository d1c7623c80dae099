"""The warnings that say an estimate is no calibration. The console prints them as
error lines and the command exits with status 3 (cli.arguments.print_warnings); the
files are still written (they show where the fit went) but a script must not take
them for a calibration."""

from __future__ import annotations

NOT_CONVERGED = "NOT CONVERGED"          # the fit stopped before a minimum
NOT_A_CALIBRATION = "NOT A CALIBRATION"  # a minimum the fit reached by dropping measurements
FAILURES = (NOT_CONVERGED, NOT_A_CALIBRATION)


def is_failure(warning: str) -> bool:
    """The warning says the estimate is no calibration: it starts with one of FAILURES."""
    return warning.startswith(FAILURES)


def first_failure(warnings) -> str | None:
    """The first of an estimate's warnings that says it is no calibration, None when none does."""
    return next((w for w in warnings if is_failure(w)), None)
