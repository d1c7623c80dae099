"""Does the learned compensator help these data? The same fit without it, compared.

A compensator is a regression of what one diagnosis's model left on its data
(diagnosis/compensator.py). Applied to data it does not describe (another unit of
the arm, another session, a hand-edited file), its offsets are fixed errors the
fit cannot remove, and the calibration is worse than without it: on another unit
without the effect, a 4-DOF arm's calibration error rose from 0.43 to 0.65 mm and
nothing was said. The fit is run again without the compensator and the two are
compared over the spots both count, on the calibration set (what the same free
parameters fit with and without the fixed offsets) and on the test set.
"""

from __future__ import annotations

from dataclasses import replace

from laser_calib.effects.base import Effect
from laser_calib.estimation.estimate import EstimateOptions, estimate
from laser_calib.io.samples import Samples
from laser_calib.model.robot import Robot
from laser_calib.report.calibration import SetEvaluation, evaluate, spot_model
from laser_calib.report.statistics import rms_where_both


def compensator_warnings(robot: Robot, samples: Samples, options: EstimateOptions, effects: tuple[Effect, ...],
                         start, sets: dict[str, SetEvaluation], source: str) -> list[str]:
    """The warning when the calibration with the compensator ``source`` (sets: its evaluation)
    misses a set by more in RMS than the same fit without it, [] otherwise."""
    quiet = replace(options, lm=replace(options.lm, progress=None), ekf=replace(options.ekf, progress=None))
    plain = estimate(robot, samples, quiet, spot_model(robot, samples, effects), start)
    test = sets["test"].samples if "test" in sets else None
    without = evaluate(robot, samples, plain, test, effects, None, start)
    worse = []
    for name, evaluation in sets.items():
        compared = rms_where_both(without[name].distances("calibrated", without[name].counted),
                                  evaluation.distances("calibrated", evaluation.counted))
        if compared is not None and compared[1] > compared[0]:
            worse.append(f"{name} RMS {compared[0] * 1e3:.3g} mm without it -> {compared[1] * 1e3:.3g} mm with it "
                         f"({compared[2]} spots)")
    if not worse:
        return []
    return [f"the compensator {source} makes the calibration worse than the same fit without it: "
            f"{'; '.join(worse)}: it does not describe these data (made on another unit or session, or edited?); "
            "calibrate without --compensator, or diagnose these data for one of their own"]
