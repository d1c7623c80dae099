"""What a fit says of itself at the top of the robot files it writes, and its reading back.

A fit that is no calibration (estimation/failures.py) still writes its files, so that
they can be examined; a caution (the test poses missed by more than the nominal model,
or large corrections the data barely determine) goes with a calibration. Both open the
file: comment lines of the robot YAML (report.files, cli.sensors) and XML comments
before <robot> in the calibrated URDF (report.urdf_export). Those lines are the only
mark such a file carries, so a file marked NO CALIBRATION is refused as a nominal model,
and a URDF rewritten from a calibrated one drops the marks of the fit that wrote it.
"""

from __future__ import annotations

import re

from laser_calib.io.errors import InputError

NO_CALIBRATION = "NO CALIBRATION:"
CAUTION = "CAUTION:"

_FAILED_YAML = f"# {NO_CALIBRATION}"
_FAILED_URDF = re.compile(rf"<!--\s*{NO_CALIBRATION}(.*?)-->", re.S)


def fit_marks(failure: str | None, caution: str | None) -> list[str]:
    """The lines a calibrated robot file opens with: why the fit is no calibration, and its caution."""
    return [f"{NO_CALIBRATION} {failure}"] * bool(failure) + [f"{CAUTION} {caution}"] * bool(caution)


def is_fit_mark(comment: str) -> bool:
    """The text of an XML comment is one a fit wrote about itself."""
    return comment.strip().startswith((NO_CALIBRATION, CAUTION))


def refuse_failed_fit(text: str, where: str) -> None:
    """A robot YAML written by a fit that failed is no robot model: read as a nominal model it would
    pass the failure on silently. Its mark is in the comment lines the file opens with."""
    for number, line in enumerate(text.splitlines(), 1):
        if not line.startswith("#"):
            return
        if line.startswith(_FAILED_YAML):
            raise InputError(where, f"line {number}: written by a fit that is no calibration "
                                    f"({line[len(_FAILED_YAML):].strip()[:120]}); give the nominal model")


def refuse_failed_urdf(text: str, where: str) -> None:
    """As refuse_failed_fit, for a URDF: its mark is a comment before <robot>."""
    failed = _FAILED_URDF.search(text[:text.find("<robot")] if "<robot" in text else "")
    if failed:
        raise InputError(where, f"written by a fit that is no calibration ({' '.join(failed[1].split())[:120]}); "
                                "give the nominal model")
