"""The warnings that say an estimate is no calibration (fit_failures; implausible, for a geometric
error fitted beyond any manufacturing error; redundancy.sigma_warnings's for a spot sigma estimated
from 1 or 2 residual degrees of freedom). The console
prints them as error lines and the command exits with status 3
(cli.arguments.print_warnings); the files are still written (they show where the fit
went, but for what such a fit kept and does not determine at its values, beyond_data: at
nominal) but a script must not take them for a calibration. And the errors of a fit that
has nothing to fit at its start: no spot there (NoSpotToFit), or none because the fit
it starts from moved the beams off the screen (FitMovedBeams)."""

from __future__ import annotations

import numpy as np

from laser_calib.io.errors import InputError

NOT_CONVERGED = "NOT CONVERGED"          # the fit stopped before a minimum
# a minimum that dropped measurements or misses them (fit_failures), or whose spot sigma, estimated from the
# residual, rests on 1 or 2 residual degrees of freedom (redundancy.sigma_warnings: no std means anything)
NOT_A_CALIBRATION = "NOT A CALIBRATION"
FAILURES = (NOT_CONVERGED, NOT_A_CALIBRATION)
# m: a calibrated model that still misses its measurements by more than this RMS per value
# describes no sensor's data here. A camera locates a laser spot on the screen to tenths of a
# millimetre (a blurred spot on a coarse image to a few), motion capture a marker to about 1 mm,
# a laser tracker to hundredths; data with an effect the geometric model lacks stay below it
# (the effects benchmark's largest screen curvatures: under 5 mm). A wrong robot file (a joint
# type, an axis, units), spots out of step with the joint readings or a joint column holding
# something else leave tens to hundreds of millimetres, and still reach an exit status 0.
MAX_RESIDUAL = 0.01
FAR_SCALES = 10.0  # a fitted error beyond 10 tolerance scales (100 mm, 10 deg) is not a manufacturing error
# ... when the data put it there: beyond FAR_SCALES by more than FAR_SIGMAS of its standard deviation (as
# slm.CHANGE_SIGMAS judges a laser angle). The estimate keeps every direction up to 10 tolerance scales of
# standard deviation (identifiability.STD_FACTOR), so a value's noise alone can reach past FAR_SCALES: on random
# sensible arms (a seeded audit; test_random_arm.py) 6 of 90 sessions exited 3 with a kept angle at 11-18 scales and a
# std of 5-7 (theta7 -0.194 rad, std 0.079, truth +0.007), a correct calibration the old rule called a wrong model.
# A std from a sigma estimated from few residual values (redundancy.sigma_warnings) excuses nothing: the
# estimate passes none, and the old rule holds (the 4-DOF arm from 6 poses: alpha2 12 deg, the truth 1).
FAR_SIGMAS = 5.0


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


def fit_failures(lost: int, level: float) -> list[str]:
    """The warnings saying a fitted minimum is no calibration: ``lost`` measurements
    dropped by moving their beams off the screen, or a residual ``level`` (m RMS per
    value) beyond MAX_RESIDUAL."""
    out = []
    if lost > 0:
        out.append(f"{NOT_A_CALIBRATION}: the fit lost {lost} measurements: at the fitted errors their beams no "
                   "longer reach the screen, so the cost fell by dropping them (a wrong minimum or model)")
    if level > MAX_RESIDUAL:
        out.append(f"{NOT_A_CALIBRATION}: the calibrated model still misses the measurements by {level * 1e3:.3g} mm "
                   f"RMS per value, beyond the {MAX_RESIDUAL * 1e3:g} mm of any sensor here: the model does not "
                   "describe the data (a wrong robot file: a joint type, an axis, units; measurements out of step "
                   "with the joint readings; a column holding something else)")
    return out


def residual_level(model, fit, excluded: np.ndarray | None, sigma: float, joint_noise: bool) -> float:
    """m RMS per value (over the fit's residual degrees of freedom) by which ``fit`` of ``model``
    misses the values it kept (``excluded`` (P,C) left out): the spot sigma its chi^2 says, and with
    joint-reading noise in the model, the raw residual: the spots' motion the estimated joint sigma
    takes as noise is a miss too (a revolute joint marked prismatic, 8 poses of the 4-DOF arm: a
    joint sigma of 5.6 deg took up a mean spot error of 69 mm, the spot sigma said 6.5 mm, the
    exit status was 0)."""
    level = sigma * float(np.sqrt(fit.chi2 / max(fit.dof, 1)))
    if not joint_noise:
        return level
    res = model.residuals(fit.x, jacobian=False)
    kept = res.valid if excluded is None else res.valid & ~excluded
    return max(level, float(np.sqrt(np.sum(res.r[kept] ** 2) / max(fit.dof, 1))))


def implausible(names: tuple[str, ...], x: np.ndarray, scales: np.ndarray, own: np.ndarray,
                geometric_names: tuple[str, ...], std: np.ndarray | None = None,
                carry: np.ndarray | None = None) -> list[str]:
    """The line for the largest fitted value x (n,) beyond FAR_SCALES of its tolerance scale among
    ``own`` (n,) (the free values that have a tolerance), and beyond it by more than FAR_SIGMAS of
    its standard deviation ``std`` (n,; where given and finite). A value that carries held errors'
    combinations (Identifiability.carry (n,), c) stands for its own error plus c times theirs, each
    as large as any manufacturing error: its bound is FAR_SCALES (1 + c) (a random arm's a3 and a4
    carried five held errors, c = 84: both at 33 scales, a4's combination in the truth at 37). The
    estimate passes neither std nor carry when its sigma rests on few residual values: 6 poses of
    the 4-DOF arm hold four errors there and put alpha2 (c = 4) at 12 scales, the truth at 1.
    Of a geometric error (geometric_names, the robot's own), no calibration, since no manufacturing
    error is that large (a column of q7's readings negated was taken up as a 181-scale laser-module
    angle, 1.5 mm in-sample, 154 mm on the test poses; shoulder and elbow columns swapped as a
    93-degree offset, exit 0); of an effect's value, a warning."""
    size = np.abs(x) / scales
    bound = FAR_SCALES * (1.0 + (0.0 if carry is None else np.asarray(carry, float)))
    far = own & (size > bound)
    if std is not None:
        std = np.asarray(std, float)
        known = np.isfinite(std) & (std > 0)
        beyond = (np.abs(x) - bound * scales) / np.where(known, std, 1.0)
        far &= ~known | (beyond > FAR_SIGMAS)
    geometric = far & np.isin(names, geometric_names)
    if geometric.any():
        worst = int(np.argmax(np.where(geometric, size, 0.0)))
        return [f"{NOT_A_CALIBRATION}: {names[worst]} is fitted at {size[worst]:.0f} times its tolerance scale, "
                f"beyond the {FAR_SCALES:g} of any manufacturing error: the nominal model is wrong (a joint's zero "
                "or direction, an axis, the laser module's mounting, lengths in another unit than metres), joint "
                "readings swapped or negated, or the minimum is wrong; correct the robot file or the data"]
    if far.any():
        worst = int(np.argmax(np.where(far, size, 0.0)))
        return [f"implausible: {names[worst]} is fitted at {size[worst]:.0f} times its tolerance scale; a wrong "
                "minimum, a wrong nominal model or data the model cannot explain"]
    return []


def beyond_data(names, kept: np.ndarray, std: np.ndarray, scales: np.ndarray, factor: float | None) -> tuple[str, ...]:
    """The ``names`` a failed fit kept (n,) whose std (n,) at its values is beyond ``factor`` tolerance
    ``scales`` (with a prior, factor None: none, the prior bounds every value). Such a fit is not
    refitted without them (its weak directions are a wrong model's), but its files write them at
    nominal: the 4-DOF arm measured at a point with its second joint's readings negated ran off along
    d3 and the sensor frame together, d3 written 5.45 m with a std of 2400 tolerance scales; the 7-DOF
    arm's spots paired with the previous pose's readings, d1 and d2 over 0.7 m with a std of 130."""
    if factor is None:
        return ()
    beyond = kept & ~within_data(std, scales, factor)
    return tuple(name for name, far in zip(names, beyond) if far)


def within_data(std: np.ndarray, scales: np.ndarray, factor: float | None) -> np.ndarray:
    """(n,) whether each std (n,) is within ``factor`` tolerance ``scales`` (n,): what the data
    determine (factor None, a prior's: every finite std)."""
    return std / scales <= (np.inf if factor is None else factor)


# result.json's note on each of them: its std stays, its value is null
UNDETERMINED = "not determined at the failed fit's values (std beyond the data): nominal in the robot file"


def undetermined_note(names) -> str:
    """The calibrated robot file's header line naming what a failed fit kept but does not determine
    (beyond_data), written at nominal; '' for none."""
    return (f"\nNot determined at its values (std beyond the data), written at nominal: {', '.join(names)}"
            if names else "")
