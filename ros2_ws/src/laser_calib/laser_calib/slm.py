"""Pre-calibration of the laser angles (paper section V, Fig. 6, eq. 16).

The SLM is held on a fixture with its z axis along the screen normal and its
x, y axes along the screen's u, v axes, at known distances D from the screen.
A laser with T_L = Rot(x, gamma) Rot(y, beta) has the direction
(sin b, -sin g cos b, cos g cos b) in the SLM frame, so its spot moves with
the distance as

    u(D) = u0 + D tan(beta) / cos(gamma),     v(D) = v0 - D tan(gamma).

The offsets u0, v0 (where the fixture puts the laser) are unknown; straight-
line fits over two or more distances give the slopes, hence gamma and beta,
and their standard deviations by first-order propagation from the spot sigma:
the --spot-sigma, or one estimated from the residual of all four lines (a
spot sigma is one value for u and v of both lasers, as --spot-sigma is), on
their 2 sum(K - 2) residual degrees of freedom, and judged as estimate judges
its own (redundancy.sigma_warnings): from 4 (three distances) the true sigma
may be 2.9 times larger (95 %), which is said; from 8 (four), no warning.

Nothing is taken on trust (docs: README, slm-calibrate):
- outliers: a spot (u, v) is one unit of two values. Each laser's lines are
  first fitted robustly (repeated medians, scipy.stats.siegelslopes: half the
  spots may be wrong); the scale s is the --spot-sigma, or, without one or
  when it is larger, the spot sigma estimated robustly (slm_lines.py: the
  median distance of a spot off the line through two others of its laser,
  at its std, the spots off those lines left out): a sigma too small must
  not reject good spots. A spot whose squared distance d^2 off those lines
  has d^2 / s^2 > chi^2_2(1 - 0.01 / N) (N spots in the file) is a candidate;
  least squares on the others then judges it as estimation/robust.py does: by
  its residual there against the noise plus the line's uncertainty at its
  distance, beyond chi^2_2's limit at the --spot-sigma, or 2 F_{2,nu}'s at
  those lines' residual (nu degrees of freedom) without one or when the
  residual is larger; a spot within is fitted again;
- a rejection leaves three spots on the laser or more: two fit a line exactly
  and nothing would check it. A laser with fewer to spare is judged whole
  (chi^2 against the --spot-sigma, or F against the other laser's residual):
  off one line, it is refused (exit 2), the wrong spot among three being
  indistinguishable from the others; else its candidates were the robust
  scale's doing and are kept. A laser with more than a third of its spots
  rejected is refused too (then the spots, not one of them, are wrong). A
  laser measured at two distances only (allowed with --spot-sigma) is written
  with a warning that nothing checked it;
- the spots of one laser may be too wrong for that rule to see: at four
  distances one candidate at most is judged (three must stay), by the line
  through the others, which a second wrong spot pulls off and whose residual
  it inflates (two of four spots 30 mm off were readmitted, beta moved by
  0.6 deg and written without a word); and when all of a laser's spots lie
  off its repeated-median lines (two wrong by the same amount at both ends),
  they are half of those the robust scale, pooled over both lasers, takes its
  median of, and none stands out. One camera sees both lasers (one sigma),
  so each laser's residual, its rejected spots left out, is tested against
  the other's (F on their 2 (K - 2) degrees of freedom): beyond
  LASER_MISMATCH_LEVEL (1e-4) the laser is refused (exit 2): more of its
  spots are wrong than can be singled out, and which cannot be told. The
  level makes it a net for gross errors: F is exact for clean spots, so it
  refuses at most 2 in 10000 clean files (none of 5000 at three, four or
  eight distances without --spot-sigma, 1 of 5000 at four and at eight with
  it; the spot rule's rates unchanged). Of files with two of a laser's four
  spots off (0.1 mm noise) it refused all of 1000 at 30 mm, in the pattern
  above or in random places and signs (before: none, and 17 %), at 3 mm 95 %
  and 37 %, at 1 mm 9 % and 2 %: four distances hardly tell those. Spots
  wrong alike in both lasers pass it (with --spot-sigma, the chi^2 warning
  below says them);
- with --spot-sigma, each laser's residual is tested against it (chi^2 on
  2 (K - 2) degrees of freedom): far above what the sigma allows, a warning;
- each fitted angle is compared with the robot file's: a change beyond
  MOUNTING_BOUND_DEG and CHANGE_SIGMAS standard deviations is no mounting
  error but a misread file (u and v swapped, a sign, the lasers' numbering):
  refused naming the likely cause, unless accept_large_change.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
# chi^2 and F quantiles and tails as scipy.stats computes them, without importing scipy.stats (seconds)
from scipy.special import chdtrc, chdtri, fdtrc

from laser_calib.estimation.redundancy import FAMILY_FALSE_REJECTION, outlier_limit, sigma_warnings
from laser_calib.estimation.robust import MAX_REJECTED
from laser_calib.io.errors import InputError
from laser_calib.model.robot import Laser, Robot, plausible_length
from laser_calib.io.read import csv_rows, length_units, parse_int, parse_number, read_text
from laser_calib.io.samples import MAX_DISTANCE
from laser_calib.slm_lines import SCALE_FLOOR, SPOT_VALUES, Spots, deletion, line_fit, robust_scale

COLUMNS = ("laser", "distance", "u", "v")
# A laser diode sits in a machined bore: the paper found its angles 1 to 2.2 deg off the drawing's 30 deg and
# 0 deg. Five degrees is more than twice that; beyond it the module was rebuilt (a new robot file) or the
# measurements were read wrong.
MOUNTING_BOUND_DEG = 5.0
CHANGE_SIGMAS = 5.0  # ... and a change is only implausible when the data determine it this well
# The level of the test of each laser's residual against the other's (_compare_lasers): a net for the gross
# errors the spot rule cannot resolve, set where it refuses no measurable share of clean files (F is exact for
# clean Gaussian spots: at most 2 in 10000 over the two lasers, beside the spot rule's 1 %). At four distances
# it refuses a laser 13 times the other's RMS (F_4,4), at eight 3.3 times (F_12,12).
LASER_MISMATCH_LEVEL = 1e-4


@dataclass(frozen=True)
class Measurements:
    path: str
    lasers: dict[int, Spots]  # laser 1 and 2


@dataclass(frozen=True)
class LaserAngles:
    gamma: float
    beta: float
    gamma_std: float
    beta_std: float
    n: int


@dataclass(frozen=True)
class Rejected:
    """A spot left out: its line, laser and distance, and its (u, v) residual (m) at the line fitted without it."""

    line: int
    laser: int
    distance: float
    residual: np.ndarray


@dataclass(frozen=True)
class SlmCalibration:
    robot: Robot                 # with the fitted angles
    angles: list[LaserAngles]
    rejected: list[Rejected]
    rule: str                    # the outlier rule at the scale used (said with the rejections)
    warnings: list[str]


def _angles(s_u: float, s_v: float) -> tuple[float, float]:
    """(gamma, beta) from the slopes of u and v (the module docstring's lines)."""
    gamma = -math.atan(s_v)
    return gamma, math.atan(s_u * math.cos(gamma))


def fit_laser(distance: np.ndarray, uv: np.ndarray, sigma: float) -> LaserAngles:
    """Angles of one laser from spots uv (K,2) in m at distances (K,) in m; the slopes' std from the spot
    sigma (m)."""
    if len(np.unique(distance)) < 2:
        raise ValueError("the spots must be measured at two or more different distances")
    coef, _, cov_unit = line_fit(distance, uv)
    (s_u, s_v), s_std = coef[0], sigma * math.sqrt(cov_unit[0, 0])
    gamma, beta = _angles(s_u, s_v)
    gamma_std = s_std / (1 + s_v ** 2)
    t = math.tan(beta)
    # d t = cos(gamma) d s_u - s_u sin(gamma) d gamma
    t_std = math.hypot(math.cos(gamma) * s_std, s_u * math.sin(gamma) * gamma_std)
    return LaserAngles(gamma, beta, gamma_std, t_std / (1 + t ** 2), len(distance))


def _check_distance(distance: float, where: str) -> None:
    """A fixture distance is positive, and no fixture holds the SLM over MAX_DISTANCE
    (as a sensor's target distance) from the screen: such a value is in millimetres."""
    if distance <= 0:
        raise InputError(where, f"must be positive, got {distance}")
    if distance > MAX_DISTANCE:
        raise InputError(where, f"{distance:g} m is not a plausible fixture distance: distances are in metres "
                                f"(this looks like {length_units(distance, MAX_DISTANCE)})")


def load_measurements(path: str | Path) -> Measurements:
    """CSV with header laser,distance,u,v (laser 1 or 2; metres)."""
    path = Path(path)
    rows = csv_rows(read_text(path), str(path))
    if not rows or tuple(c.strip() for c in rows[0]) != COLUMNS:
        raise InputError(f"{path}: header", f"expected {','.join(COLUMNS)}")
    data: dict[int, list[tuple[float, ...]]] = {1: [], 2: []}
    for line, row in enumerate(rows[1:], start=2):
        if not any(cell.strip() for cell in row):
            continue
        if len(row) != 4:
            raise InputError(f"{path}: line {line}", f"{len(row)} fields, expected 4")
        laser = parse_int(row[0], f"{path}: line {line}, field laser")
        if laser not in data:
            raise InputError(f"{path}: line {line}, field laser", f"expected 1 or 2, got {laser}")
        values = [parse_number(cell, f"{path}: line {line}, field {name}") for name, cell in zip(COLUMNS[1:], row[1:])]
        _check_distance(values[0], f"{path}: line {line}, field distance")
        for name, value in zip(COLUMNS[2:], values[1:]):  # u = 1e11 gave beta 0 +- 0.009 deg, exit 0
            plausible_length(f"{path}: line {line}, field {name}", value, MAX_DISTANCE, "spot coordinate on the fixture")
        data[laser].append((line, *values))
    lasers = {}
    for laser, entries in data.items():
        if len({e[1] for e in entries}) < 2:
            raise InputError(str(path), f"laser {laser} needs spots at two or more different distances")
        arr = np.array(entries)
        lasers[laser] = Spots(arr[:, 0].astype(int), arr[:, 1], arr[:, 2:])
    return Measurements(str(path), lasers)


def _testable(spots: Spots, out: np.ndarray) -> bool:
    """Whether the spots not ``out`` both fit a line and leave a value to check it: three or more, at two or
    more distances."""
    kept = ~out
    return int(kept.sum()) >= 3 and len(np.unique(spots.distance[kept])) >= 2


def _judge_whole(measurements: Measurements, laser: int, out: dict[int, np.ndarray], sigma: float | None) -> None:
    """A laser whose candidates would leave too few spots to check the others (three): its spots are judged as a
    whole, against the --spot-sigma (chi^2) or the other laser's residual (F; its candidates left out when
    it can spare them). On one line as far as that
    tells (or nothing tells), its candidates were the robust scale's doing (a repeated-median line through
    two of three spots leaves those no residual); off it, a wrong spot is there and cannot be told."""
    spots = measurements.lasers[laser]
    _, _, own, own_dof = deletion(spots, np.zeros(len(spots.distance), bool))
    if sigma is not None:
        p, against = float(chdtrc(own_dof, own / sigma ** 2)), f"the --spot-sigma {sigma * 1e3:.3g} mm"
    else:
        others = [deletion(s, out[j] if _testable(s, out[j]) else np.zeros_like(out[j]))
                  for j, s in measurements.lasers.items() if j != laser]
        dof = sum(o[3] for o in others)
        if dof < 1:
            return
        variance = sum(o[2] for o in others) / dof
        p = float(fdtrc(own_dof, dof, (own / own_dof) / max(variance, SCALE_FLOOR ** 2)))
        against = f"the other laser's residual {math.sqrt(variance) * 1e3:.3g} mm"
    if p >= FAMILY_FALSE_REJECTION:
        return
    raise InputError(f"{measurements.path}: laser {laser}",
                     f"its spots (lines {', '.join(str(n) for n in spots.line)}) lie "
                     f"{math.sqrt(own / own_dof) * 1e3:.3g} mm RMS off one line, beyond what {against} allows "
                     f"(p = {p:.2g}), and with {len(spots.distance)} spots the wrong one cannot be told (the others "
                     "would fit a line exactly and nothing would check them): correct the spot or measure at more "
                     "distances")


def _compare_lasers(measurements: Measurements, out: dict[int, np.ndarray]) -> None:
    """Each laser's residual, its rejected spots left out, against the other's (F; one camera sees both, so one
    sigma): far above it (LASER_MISMATCH_LEVEL), the laser is refused, its wrong spots too many for the spot
    rule to tell (module docstring)."""
    fits = {j: deletion(spots, out[j]) for j, spots in measurements.lasers.items()}
    for j, (_, _, own, own_dof) in fits.items():
        others = [fit for k, fit in fits.items() if k != j]
        dof = sum(fit[3] for fit in others)
        if own_dof < 1 or dof < 1:  # spots at two distances: nothing to compare
            continue
        variance = max(sum(fit[2] for fit in others) / dof, SCALE_FLOOR ** 2)
        p = float(fdtrc(own_dof, dof, (own / own_dof) / variance))
        if p >= LASER_MISMATCH_LEVEL:
            continue
        spots, rms = measurements.lasers[j], math.sqrt(own / own_dof)
        rejected = spots.line[out[j]]
        raise InputError(
            f"{measurements.path}: laser {j}",
            f"its spots (lines {', '.join(str(n) for n in spots.line)}"
            + (f"; line{'s' * (len(rejected) > 1)} {', '.join(str(n) for n in rejected)} rejected"
               if len(rejected) else "")
            + f") lie {rms * 1e3:.3g} mm RMS off one line, {rms / math.sqrt(variance):.3g} times the other laser's "
            f"{math.sqrt(variance) * 1e3:.3g} mm (F = {own / own_dof / variance:.3g} on {own_dof}, {dof} degrees of "
            f"freedom, p = {p:.2g}; one camera sees both): more of its spots are wrong than the line through the "
            "others can single out, and which cannot be told; correct them or measure again")


def _outliers(measurements: Measurements, sigma: float | None) -> tuple[dict[int, np.ndarray], str]:
    """The spots rejected per laser (bool (K,)) and the rule said with them (module docstring)."""
    lasers = measurements.lasers
    n_spots = sum(len(s.distance) for s in lasers.values())
    known_limit = float(chdtri(SPOT_VALUES, FAMILY_FALSE_REJECTION / n_spots))
    robust, distances = robust_scale(list(lasers.values()), known_limit)
    start = dict(zip(lasers, distances))
    if sigma is not None and sigma >= robust:
        scale, said = sigma, f"the --spot-sigma {sigma * 1e3:.3g} mm"
    else:  # a given sigma the spots exceed would reject good spots: the chi^2 test says it is too small
        scale = robust
        said = (f"the spot sigma {robust * 1e3:.3g} mm estimated robustly (the median distance of a spot off the "
                "line through two others of its laser, spots off repeated-median lines left out; "
                + ("no --spot-sigma)" if sigma is None else f"above the --spot-sigma {sigma * 1e3:.3g} mm)"))
    out = {j: d2 / scale ** 2 > known_limit for j, d2 in start.items()}
    for j, spots in lasers.items():
        if not out[j].any():
            continue
        # at most the farthest K - 3 stay candidates: the least deviant are readmitted for the others' check
        farthest = np.zeros_like(out[j])
        farthest[np.argsort(-start[j])[:max(len(farthest) - 3, 0)]] = True
        out[j] &= farthest
        if not (out[j].any() and _testable(spots, out[j])):
            _judge_whole(measurements, j, out, sigma)
            out[j] = np.zeros_like(out[j])
    limit, judged = known_limit, ""
    while any(o.any() for o in out.values()):  # each laser with candidates keeps three spots or more
        deleted = {j: deletion(s, out[j]) for j, s in lasers.items()}
        dof = sum(d[3] for d in deleted.values())
        residual = sum(d[2] for d in deleted.values()) / dof
        if sigma is not None and residual <= sigma ** 2:
            variance, limit = sigma ** 2, known_limit
            judged = f"chi^2_2(1 - {FAMILY_FALSE_REJECTION:g} / {n_spots}) at the --spot-sigma {sigma * 1e3:.3g} mm"
        else:
            variance, limit = max(residual, SCALE_FLOOR ** 2), outlier_limit(SPOT_VALUES, dof, n_spots)
            judged = (f"2 F_2,{dof}(1 - {FAMILY_FALSE_REJECTION:g} / {n_spots}) at the others' residual "
                      f"{math.sqrt(variance) * 1e3:.3g} mm ({dof} degrees of freedom)")
        within = {j: out[j] & ((resid ** 2).sum(axis=1) / (variance * factor) <= limit)
                  for j, (resid, factor, _, _) in deleted.items()}
        if not any(w.any() for w in within.values()):  # the rejections only shrink: this ends
            break
        out = {j: out[j] & ~within[j] for j in out}
    for j, spots in lasers.items():
        if out[j].sum() > MAX_REJECTED * len(out[j]):
            raise InputError(f"{measurements.path}: laser {j}",
                             f"{int(out[j].sum())} of its {len(out[j])} spots lie off the line through the others "
                             f"(beyond {math.sqrt(limit):.3g} times the noise, {judged}): the spots do not follow "
                             "one line (the fixture moved, spots of the other laser?)")
    _compare_lasers(measurements, out)
    rule = (f"a spot off its laser's lines fitted without it by more than {math.sqrt(limit):.3g} times the noise "
            f"(plus the lines' uncertainty there) is rejected: the limit {judged}; candidates at {said}")
    return out, rule


def _level_warning(laser: int, spots: Spots, sigma: float) -> list[str]:
    """The chi^2 test of a laser's residual against the given spot sigma."""
    _, resid, _ = line_fit(spots.distance, spots.uv)
    dof = SPOT_VALUES * (len(spots.distance) - 2)
    if dof < 1:
        return [f"laser {laser}: spots at only two distances: the lines fit them exactly and nothing checks them "
                "(a wrong spot goes unseen); measure at three or more distances"]
    chi2 = float((resid ** 2).sum()) / sigma ** 2
    p = float(chdtrc(dof, chi2))
    if p >= FAMILY_FALSE_REJECTION / 2:  # both lasers: a clean file warns with probability 1 %
        return []
    rms = sigma * math.sqrt(chi2 / dof)
    return [f"laser {laser}: the spots lie {rms * 1e3:.3g} mm RMS off their lines, {rms / sigma:.2g} times the "
            f"--spot-sigma {sigma * 1e3:.3g} mm (chi^2 = {chi2:.3g} on {dof} degrees of freedom, p = {p:.2g}): "
            "the sigma is too small, or the spots or the fixture moved; the angles' standard deviations, from "
            "the sigma, are too small"]


def _likely_causes(robot: Robot, laser: int, angles: LaserAngles) -> str:
    """What misreading of the file turns the robot file's angles into the fitted ones, if one does."""
    s_u, s_v = math.tan(angles.beta) / math.cos(angles.gamma), -math.tan(angles.gamma)
    bound = math.radians(MOUNTING_BOUND_DEG)
    own, other = robot.lasers[laser - 1], robot.lasers[2 - laser]
    readings = {"the u and v columns swapped": ((s_v, s_u), own),
                "u of the opposite sign": ((-s_u, s_v), own),
                "v of the opposite sign (v = v0 - D tan gamma)": ((s_u, -s_v), own),
                "lasers 1 and 2 numbered the other way round": ((s_u, s_v), other)}
    causes = [cause for cause, (slopes, nominal) in readings.items()
              if max(abs(a - b) for a, b in zip(_angles(*slopes), (nominal.gamma, nominal.beta))) < bound]
    return (f"likely {' or '.join(causes)}" if causes else
            "check the u and v columns, their signs and the lasers' numbering")


def _nominal_check(robot: Robot, angles: list[LaserAngles], path: str, accept: bool) -> list[str]:
    """A fitted angle implausibly far from the robot file's: refused, or a warning when accepted."""
    warnings = []
    for laser, fitted in enumerate(angles, start=1):
        nominal = robot.lasers[laser - 1]
        for name, value, std, was in (("gamma", fitted.gamma, fitted.gamma_std, nominal.gamma),
                                      ("beta", fitted.beta, fitted.beta_std, nominal.beta)):
            change = abs(value - was)
            if change <= math.radians(MOUNTING_BOUND_DEG) or change <= CHANGE_SIGMAS * std:
                continue
            sigmas = f"{change / std:.0f} standard deviations" if std > 0 else "fitted exactly"
            problem = (f"{name} = {math.degrees(value):+.2f} deg is {math.degrees(change):.1f} deg from the robot "
                       f"file's {math.degrees(was):+.2f} deg ({sigmas}), more than a laser's mounting error "
                       f"({MOUNTING_BOUND_DEG:g} deg): {_likely_causes(robot, laser, fitted)}")
            if not accept:
                raise InputError(f"{path}: laser {laser}, {name}",
                                 problem + "; if the laser was remounted, give --accept-large-change")
            warnings.append(f"laser {laser}: {problem} (accepted: --accept-large-change)")
    return warnings


def _estimated_sigma(kept: dict[int, Spots]) -> tuple[float, list[str]]:
    """The spot sigma (m) from the lasers' line residuals pooled, and what its degrees of freedom allow."""
    if any(len(spots.distance) < 3 for spots in kept.values()):
        raise ValueError("with spots at only two distances the slope's error is unknown: give --spot-sigma "
                         "or measure at three or more distances")
    # Pooled, not per laser and coordinate: each line through K spots leaves K - 2, 1 at three distances, and a
    # std from 1 degree of freedom means nothing (the error over it is Student's t with 1, without a variance).
    # Pooled: 2 sum(K - 2) >= 4, so of estimate's rule only the uncertainty warning (below 8) can apply, not
    # NOT A CALIBRATION (2 or fewer).
    fits = [deletion(spots, np.zeros(len(spots.distance), bool)) for spots in kept.values()]
    dof = sum(fit[3] for fit in fits)
    sigma = math.sqrt(sum(fit[2] for fit in fits) / dof)
    return sigma, sigma_warnings(sigma, dof, "measure at more distances or give --spot-sigma")


def calibrate(robot: Robot, measurements: Measurements, sigma: float | None = None,
              accept_large_change: bool = False) -> SlmCalibration:
    """The robot with its laser angles replaced by those fitted to the spots not rejected."""
    out, rule = _outliers(measurements, sigma)
    kept = {laser: Spots(spots.line[~out[laser]], spots.distance[~out[laser]], spots.uv[~out[laser]])
            for laser, spots in measurements.lasers.items()}
    estimated, warnings = _estimated_sigma(kept) if sigma is None else (sigma, [])
    angles, rejected = [], []
    for laser, spots in sorted(measurements.lasers.items()):
        angles.append(fit_laser(kept[laser].distance, kept[laser].uv, estimated))
        resid = deletion(spots, out[laser])[0]
        rejected.extend(Rejected(int(spots.line[k]), laser, float(spots.distance[k]), resid[k])
                        for k in np.flatnonzero(out[laser]))
        if sigma is not None:
            warnings.extend(_level_warning(laser, kept[laser], sigma))
    warnings.extend(_nominal_check(robot, angles, measurements.path, accept_large_change))
    lasers = tuple(Laser(a.gamma, a.beta) for a in angles)
    return SlmCalibration(replace(robot, lasers=lasers), angles, rejected, rule, warnings)
