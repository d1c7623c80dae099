"""The warnings that say an estimate is no calibration. The console prints them as
error lines and the command exits with status 3 (cli.arguments.print_warnings); the
files are still written (they show where the fit went) but a script must not take
them for a calibration."""

NOT_CONVERGED = "NOT CONVERGED"          # the fit stopped before a minimum
NOT_A_CALIBRATION = "NOT A CALIBRATION"  # a minimum the fit reached by dropping measurements
FAILURES = (NOT_CONVERGED, NOT_A_CALIBRATION)


def is_failure(warning: str) -> bool:
    """The warning says the estimate is no calibration: it starts with one of FAILURES."""
    return warning.startswith(FAILURES)
