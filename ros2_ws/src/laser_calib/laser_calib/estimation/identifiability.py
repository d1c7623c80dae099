"""What the measurements can and cannot separate.

The stacked, whitened measurement Jacobian J (M,n) is scaled column-wise by
each parameter's characteristic size (10 mm, 1 deg: the tolerance scales) so
that singular values compare like with like. A singular value s of the scaled
J is the inverse of the standard deviation, in tolerance units, of the
estimate along its direction. A direction is not identifiable when

- s < rel_tol * s_max: numerically invisible (exact rank deficiency), or
- s < SLIVER * s_r, s_r the weakest of the r directions the whole Jacobian
  determines: a sliver, a near-duplicate of columns that rounding in the
  robot's description leaves (a URDF's right angle written 1.5708, 3.7e-6 rad
  off pi/2, makes one joint's y a hair off the previous joint's z), or
- s < 1 / std_factor (only when the whitening used the real noise): the data
  determines it worse than std_factor times its tolerance, so a fitted value
  would be the noise's, not the robot's (a joint that never moves, a pose set
  that barely spans a direction).

Parameters are kept in their natural order, but a column that adds to the span
of those kept so far only a near-duplicate's share of itself (the sine of its
angle to that span below NEAR_DUPLICATE) is deferred to the end: written 3.14
for pi, a URDF's flipped prismatic joint (SCARA) moves 1.6e-3 rad off the
first joint's z, so its offset is that z plus 1.6e-3 of a sideways shift that
the joint's own y carries in full. Kept first, the offset stood for that
shift at 1 / 1.6e-3 = 620 times its size and the joint's y was held: the
errors along y were fitted as offsets of 500-1000 tolerances, far outside
the linear model, and the offset's weak direction spent the noise threshold
that the laser module's real ones need (3 of 5 seeds NOT A CALIBRATION at
0.1 mm spot noise, 7-10 mm test error, where the same arm with pi reaches
0.09 mm). Deferred, the offset is held as pi holds it (its sum with the first
joint's z) and y absorbs the rounding like any geometric error. A deferred
column that no later one replaces is tested by the same thresholds after the
others, so deferring chooses among near-duplicates and nothing else.

In order, the held parameter of a combination may be the one its carriers
weigh least: a random arm's laser module at 79 deg, not 90, made slm_rz a
first-order combination of theta6 and slm_ry at 5.4 times its weight, so its
true -0.68 deg was fitted as 3.7 deg of each, where the kinematics is not
linear: the fit missed second-order structure a correct model does not leave
(chi^2 4 below its value at the true errors, where 27 free parameters take
about 27 off), and the diagnosis said "structure remains" on effect-free data.
The estimators (estimate_model, the online filter, `identify`) therefore swap
a held parameter for its largest carrier while that carrier's coefficient
exceeds AMPLIFY (maxvol's exchange: each swap multiplies the kept columns'
volume by at least that coefficient, so the swaps end), and no carrier then moves by
much more than the error it carries. Sums (coefficient 1) are left in order;
the paper's arms and the UR5e file hold what they held. The sensor fit
(calibrate-poses) decides what the frames carry by its own order, and keeps it.

The estimators then hold one parameter per such direction at nominal and say
which parameters carry the combination. The combinations are canonical: for
each held parameter f, the direction e_f - c with c the least-squares
compensation of f's column by the kept columns. It is unique (the kept columns
are independent), so every machine and BLAS prints the same text, and each
combination names only f and the kept parameters that carry it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

REL_TOL = 1e-7
# Parameters are kept in order while the kept set's weakest direction stays
# above the threshold, so a sliver kept early spends a slot the real
# directions need: every later column that brings the sliver's combination
# back to exact dependence is refused (a Kinova Gen3 kept 22 parameters, its
# kept set's weakest direction at 4e-5, where the whole Jacobian determines 34
# directions, the weakest at 0.9). A kept set's weakest direction 1000 times
# below the weakest the data determine is no direction of the robot.
SLIVER = 1e-3
# A direction whose standard deviation exceeds STD_FACTOR times its tolerance
# scale (10 mm / 1 deg) is not identifiable: its fitted value would be mostly
# noise: at 10 tolerances (100 mm, 10 deg) it is no measurement of the robot.
# It keeps every direction of the paper's arms at their noise (the weakest,
# 7-DOF theta7 - slm_rz, has 2-4 tolerances) and holds what a joint that never
# moves leaves (hundreds of tolerances).
STD_FACTOR = 10.0
# Kept, but with a standard deviation beyond WEAK_FACTOR tolerance scales, a value is said to be
# mostly noise (two axes 0.05 rad from parallel wrote d3 and d4 93 and 96 mm off, std 52 mm, without
# a word); the paper's arms' largest stds are 1.2-1.8 scales at their noise.
WEAK_FACTOR = 3.0
# A column within 0.01 rad (0.6 deg) of the kept columns' span is a near-duplicate
# (module docstring). A description's rounding leaves 1.6e-3 (3.14 for pi) and less;
# the smallest a real direction of the paper's arms shows is 0.006 (slm_rz, their
# last column, so deferring it changes nothing), and a deferred column that no later
# one replaces is kept all the same.
NEAR_DUPLICATE = 0.01
# A held parameter whose carrier moves by more than AMPLIFY times its error (module docstring).
AMPLIFY = 2.0
TIE = 1e-6  # carriers' coefficients this close (relative) are equal
TERM_THRESHOLD = 0.05  # terms below 5 % of the largest are not printed, except the held parameter's own (describe)


# What to check when the nominal model reaches none or few of the measured spots
CHECK_UNITS = ("check the joint readings' units (radians; metres for a prismatic joint) and the robot file "
               "(lengths in metres, joint zeros, the laser module, the screen)")


class TooFewValues(ValueError):
    """As many measured values as free parameters, or fewer: they fit exactly, and nothing
    tests the fit or estimates the noise. The estimator knows the counts, a command the file.
    n_params: the model's parameter count, said when the values reach fewer;
    rejected: the measurements the robust rule left out, when they made the values too few;
    refused: (measurements, their values) refused before the fit as physically impossible
    (estimation.impossible: the nominal beam misses the screen by far). When those values are
    at least as many as the values left, the refusals, not the poses, made them too few, and
    the data are not the nominal model's: readings in other units (a continuous joint's in
    degrees, which no joint range catches) or another arm's file, so the line says that.
    copies: the rows left uncounted as exact copies of another (io.revisits.copied)."""

    def __init__(self, n_values: int, n_free: int, rejected: int = 0, refused: tuple[int, int] = (0, 0),
                 n_params: int | None = None, copies: int = 0):
        left = f" left after {rejected} rejected as outliers" if rejected else ""
        if copies:  # a copied row adds values that neither determine nor check anything
            left += f" (not counting {copies} rows that copy another row exactly)"
        if refused[0]:
            left += (f"{' and' if rejected else ' left after'} {refused[0]} refused as physically impossible (the "
                     "nominal model's beam misses the screen or lands far from the spot)")
        advice = CHECK_UNITS if refused[1] >= n_values else "measure more poses or use the prior"
        # n_free counts what these values reach: one pose of a 33-parameter arm reaches 4
        what = (f"reach only {n_free} of the model's {n_params} parameters and cannot determine and check even those"
                if n_params and n_params > n_free else f"cannot determine and check {n_free} parameters")
        super().__init__(f"{n_values} measured values{left} {what}; {advice}")
        self.n_values, self.n_free, self.rejected = n_values, n_free, rejected


class UnknownFixed(ValueError):
    """A name to hold (EstimateOptions.fixed) that is no parameter of the model: the estimator knows the
    parameters, the command where the name was given (estimate's --fix)."""

    def __init__(self, name: str, names: tuple[str, ...]):
        super().__init__(f"cannot fix unknown parameter {name!r}; parameters are {', '.join(names)}")
        self.name, self.names = name, names


def check_fixed(fixed, names) -> None:
    """UnknownFixed for the first of the names to hold ``fixed`` that is none of the model's ``names``."""
    unknown = [name for name in fixed if name not in names]
    if unknown:
        raise UnknownFixed(unknown[0], tuple(names))


@dataclass(frozen=True)
class Identifiability:
    """singular_values (min(M,n),) of the scaled Jacobian; rank (directions kept);
    condition number (largest / smallest kept singular value); free (n,)
    parameters kept; null_combinations: one text per held direction; merged:
    held parameter name -> the parameters that carry its combination, as text;
    min_singular: the threshold that was applied; carriers: held parameter
    name -> the names of the kept parameters that carry its combination."""

    names: tuple[str, ...]
    singular_values: np.ndarray
    rank: int
    condition: float
    free: np.ndarray
    null_combinations: tuple[str, ...]
    merged: dict[str, str]
    min_singular: float = 0.0
    carriers: dict[str, tuple[str, ...]] = field(default_factory=dict)
    by_noise: int = 0  # directions held only by the std_factor threshold: the noise level decides them
    # (n,) per kept parameter, the sum over the held ones it carries of |its coefficient| in their
    # combination, in tolerance scales per tolerance scale (0 where it carries none)
    carry: np.ndarray | None = None
    # held (or carried --fix) name -> {kept name: how far that kept value moves per unit of the held one's error,
    # in its own unit per the held one's}: each kept value is its own error plus these shares of the held ones'
    shares: dict[str, dict[str, float]] = field(default_factory=dict)

    @property
    def carried(self) -> dict[str, tuple[str, ...]]:
        """Kept parameter name -> the held ones whose combination it carries (carried_by_kept)."""
        return carried_by_kept(self.carriers)

    def table(self) -> str:
        lines = [f"parameters: {len(self.names)}   numerical rank: {self.rank}   "
                 f"condition number (scaled): {self.condition:.3g}", "",
                 " k  singular value (scaled)"]
        lines += [f"{k + 1:2d}  {s:.4g}" for k, s in enumerate(self.singular_values)]
        if self.null_combinations:
            lines += ["", "directions the data cannot determine (coefficients in units of 10 mm / 1 deg; "
                      "+1 d1 -1 d2 means only the sum d1 + d2 is seen):"]
            lines += [f"  {text}" for text in self.null_combinations]
            lines += ["", "fixed at nominal (merged):"]
            lines += [f"  {name}: {how}" for name, how in self.merged.items()]
        else:
            lines += ["", "all parameters identifiable"]
        return "\n".join(lines)


def carried_by_kept(carriers: dict[str, tuple[str, ...]]) -> dict[str, tuple[str, ...]]:
    """Kept parameter name -> the held ones whose combination it carries, from held
    name -> its carriers: its value is that combination's, not its own error alone
    (d1 carrying d2 holds d1 + d2)."""
    out: dict[str, tuple[str, ...]] = {}
    for held, partners in carriers.items():
        for name in partners:
            out[name] = out.get(name, ()) + (held,)
    return out


# result.json's note on a parameter the user held (EstimateOptions.fixed: --fix), not identifiable
# for that reason, not for the data's: as the merged and carried ones say why
FIXED_NOTE = "held at nominal: --fix"


def carried_note(name: str, held: tuple[str, ...]) -> str:
    """What a kept parameter's value is when it carries held ones' combination (Identifiability.carried)."""
    return (f"carries its combination with {', '.join(held)} (held at nominal): the value is that combination's, "
            f"not {name}'s own error alone")


def describe(vector: np.ndarray, names: tuple[str, ...], threshold: float = TERM_THRESHOLD,
             held: int | None = None) -> str:
    """The terms above threshold of the largest, and always the held parameter's own:
    where its carriers weigh hundreds of times more (a near-duplicate kept), its term
    falls below the threshold, and held parameters carried by the same pair would
    read as one text that names none of them."""
    v = vector / np.abs(vector).max()
    v = v * np.sign(v[np.flatnonzero(np.abs(v) > threshold)[0]])  # first term positive: one canonical text
    shown = np.abs(v) > threshold
    if held is not None:
        shown[held] = True
    terms = [f"{c:+.2f} {names[i]}" if abs(c) >= 0.005 else f"{c:+.1e} {names[i]}"
             for i, c in enumerate(v) if shown[i]]
    return " ".join(terms)


def _outside(basis: np.ndarray, column: np.ndarray) -> np.ndarray:
    """The part of column outside the span of the orthonormal basis (projected out
    twice: once loses the digits of a near-duplicate)."""
    for _ in range(2):
        column = column - basis @ (basis.T @ column)
    return column


def _least_amplified(r_factor: np.ndarray, kept: list[int], held: list[int], threshold: float,
                     amplify: float) -> list[int]:
    """The kept columns with each held one swapped for its largest carrier while that carrier's
    coefficient exceeds ``amplify`` (tolerance scales per tolerance scale; module docstring). Each
    swap multiplies the kept columns' volume by at least that coefficient, so the swaps end; one that
    would take the kept set's weakest direction below ``threshold`` is not made."""
    refused: set[tuple[int, int]] = set()
    while kept:
        worst = (amplify, -1, -1)
        for j in held:
            coefficients = np.abs(np.linalg.lstsq(r_factor[:, kept], r_factor[:, j], rcond=None)[0])
            # of carriers equal to rounding (a symmetric arm), the first in order: the same on every machine
            k = int(np.flatnonzero(coefficients >= (1.0 - TIE) * coefficients.max())[0])
            if coefficients[k] > worst[0] and (j, kept[k]) not in refused:
                worst = (float(coefficients[k]), j, kept[k])
        _, j, carrier = worst
        if j < 0:
            return kept
        swapped = sorted([i for i in kept if i != carrier] + [j])
        if np.linalg.svd(r_factor[:, swapped], compute_uv=False)[-1] > threshold:
            kept, held = swapped, [i for i in held if i != j] + [carrier]
        else:
            refused.add((j, carrier))
    return kept


def analyse(jacobian: np.ndarray, scales: np.ndarray, names: tuple[str, ...],
            fixed: np.ndarray | None = None, rel_tol: float = REL_TOL,
            std_factor: float | None = None, amplify: float | None = None) -> Identifiability:
    """Identifiability of the parameters from a whitened Jacobian (M,n).

    Parameters are kept greedily in their natural order (base to tip), so of a
    pair that only acts as a sum the one nearer the base is kept and carries it.
    ``fixed`` (n,) marks parameters the user holds; they are never kept.
    std_factor: apply the noise threshold (module docstring); only meaningful
    when the Jacobian was whitened with the real measurement noise. amplify
    (AMPLIFY, None for the order alone): hold a combination's largest carrier
    where in order it would carry the held one at more than this (module docstring).
    """
    n = jacobian.shape[1]
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    # R (n,n) of J's QR has J's column geometry (J[:,S] = Q R[:,S]): every test
    # below runs on it, so a long measurement stack is factored once.
    r_factor = np.linalg.qr(jacobian * scales, mode="r")
    if r_factor.shape[0] < n:  # fewer values than parameters
        r_factor = np.vstack([r_factor, np.zeros((n - r_factor.shape[0], n))])
    candidates = np.flatnonzero(~fixed)
    singular = np.linalg.svd(r_factor[:, candidates], compute_uv=False)
    top = singular[0] if singular.size and singular[0] > 0 else 1.0
    threshold = rel_tol * top
    rank = int(np.count_nonzero(singular > threshold))
    if rank:   # slivers (module docstring)
        threshold = max(threshold, SLIVER * singular[rank - 1])
    numerical = threshold
    if std_factor is not None:
        threshold = max(threshold, 1.0 / std_factor)

    kept: list[int] = []
    deferred: list[int] = []  # near-duplicates (module docstring): a later column may carry their direction
    basis = np.zeros((len(r_factor), 0))  # orthonormal, spans the kept columns
    for j in candidates:
        new = _outside(basis, r_factor[:, j])
        if np.linalg.norm(new) < NEAR_DUPLICATE * np.linalg.norm(r_factor[:, j]):
            deferred.append(j)
        elif np.linalg.svd(r_factor[:, kept + [j]], compute_uv=False)[-1] > threshold:
            kept.append(j)
            basis = np.column_stack([basis, new / np.linalg.norm(new)])
    for j in deferred:
        if np.linalg.svd(r_factor[:, kept + [j]], compute_uv=False)[-1] > threshold:
            kept.append(j)
    kept.sort()
    if amplify is not None:
        kept = _least_amplified(r_factor, kept, [j for j in candidates if j not in kept], threshold, amplify)
    free = np.zeros(n, bool)
    free[kept] = True

    # A parameter the user holds that the kept ones could not be told from is carried by them too: with
    # wrist_3_joint.offset held by --fix, wrist_3_joint.rz was written with no note, and its value was the sum.
    carried_fixed = [j for j in np.flatnonzero(fixed)
                     if kept and np.linalg.svd(r_factor[:, kept + [j]], compute_uv=False)[-1] <= threshold]
    kept_singular = np.linalg.svd(r_factor[:, kept], compute_uv=False) if kept else np.zeros(0)
    condition = float(kept_singular[0] / kept_singular[-1]) if kept else float("inf")
    return Identifiability(tuple(names), singular, len(kept), condition, free, min_singular=float(threshold),
                           by_noise=int(np.count_nonzero((singular > numerical) & (singular <= threshold))),
                           **_combinations(r_factor, names, scales, kept, np.flatnonzero(~free & ~fixed),
                                           carried_fixed))


def _combinations(r_factor: np.ndarray, names, scales: np.ndarray, kept: list[int], held, carried_fixed) -> dict:
    """Identifiability's fields that say what the kept columns ``kept`` of r_factor (scaled) carry of the
    ``held`` ones and of the user's ``carried_fixed`` (indices): null_combinations, merged, carriers, carry
    and shares."""
    n = len(names)
    combinations, merged, carriers, carry, shares = [], {}, {}, np.zeros(n), {}
    for j in [*held, *carried_fixed]:
        direction = np.zeros(n)
        direction[kept] = -np.linalg.lstsq(r_factor[:, kept], r_factor[:, j], rcond=None)[0] if kept else 0.0
        carry[kept] += np.abs(direction[kept])
        # a kept value moves by -direction (scaled) when j is off by one scale; below REL_TOL it is rounding
        shares[names[j]] = {names[i]: float(-direction[i] * scales[i] / scales[j]) for i in kept
                            if abs(direction[i]) > REL_TOL}
        if j in carried_fixed:  # its own 0 weighs nothing: a carrier is one that carries more than 5 % of it
            weight = np.abs(direction) / max(np.abs(direction).max(), 1.0)
            carriers[names[j]] = tuple(names[i] for i in kept if weight[i] > TERM_THRESHOLD)
            continue
        direction[j] = 1.0
        combinations.append(describe(direction, names, held=j))
        weight = np.abs(direction) / np.abs(direction).max()
        partners = [names[i] for i in kept if weight[i] > TERM_THRESHOLD]
        carriers[names[j]] = tuple(partners)
        merged[names[j]] = ("not separable from " + ", ".join(partners) + "; fixed at nominal, "
                            "those parameters carry the combination") if partners else \
            "not determined by the data; fixed at nominal"
    return {"null_combinations": tuple(combinations), "merged": merged, "carriers": carriers, "carry": carry,
            "shares": shares}


def at_values(ident: Identifiability, factor: np.ndarray, scales: np.ndarray) -> Identifiability:
    """ident, the same parameters held and kept, with what the kept ones carry of the held ones taken from
    ``factor`` (whitened_factor's R (m,n)) at other values, the calibrated ones: the values were fitted
    there. The 4-DOF arm's d1 carries d2 alone at nominal, alpha1 = 0; at a true alpha1 of 1 deg a 10 mm
    d2 also moves the arm 0.17 mm sideways, which theta4 and slm_ry carry in part (and slm_z's, theta3
    and theta4 at 0.09 deg per 10 mm, 0.6 of theta3's std at 0.3 mm spot noise): those values are
    combinations as much as d1's is."""
    index = {name: i for i, name in enumerate(ident.names)}
    held = [index[name] for name in ident.merged]
    carried_fixed = [index[name] for name in ident.carriers if name not in ident.merged]
    return replace(ident, **_combinations(np.asarray(factor) * scales, ident.names, scales,
                                          list(np.flatnonzero(ident.free)), held, carried_fixed))


def weak_warnings(names: tuple[str, ...], std: np.ndarray, scales: np.ndarray, own: np.ndarray,
                  values: np.ndarray) -> list[str]:
    """One line naming the kept values among ``own`` (n,) whose std (n,) exceeds WEAK_FACTOR times
    their tolerance scale (n,), largest first; and one (WEAK_AND_LARGE) when such a value is itself
    beyond WEAK_FACTOR scales from nominal: noise written as a large correction (poses within half a
    degree of one: theta2 +27 deg, std 11 deg, the model 733 mm RMS off elsewhere where nominal was 142)."""
    ratio = np.where(own & np.isfinite(std), std / scales, 0.0)
    weak = [int(i) for i in np.argsort(-ratio) if ratio[i] > WEAK_FACTOR]
    if not weak:
        return []
    listed = ", ".join(f"{names[i]} (std {ratio[i]:.2g} tolerance scales)" for i in weak[:5])
    more = f" and {len(weak) - 5} more" if len(weak) > 5 else ""
    said = [f"weakly determined: {listed}{more}: each value is mostly noise (a tolerance scale is 10 mm or 1 deg); "
            "more poses, wider joint motion or less noise determine them better"]
    large = [i for i in weak if abs(values[i]) > WEAK_FACTOR * scales[i]]
    if large:
        said.append(f"{WEAK_AND_LARGE} " + ", ".join(f"{names[i]} at {abs(values[i]) / scales[i]:.2g} tolerance scales "
                                                     f"from nominal, std {ratio[i]:.2g}" for i in large[:5])
                    + ": the data barely determine them, and the model may miss poses away from the calibration's "
                      "by more than the nominal one; --prior bounds them by their tolerances")
    return said


# The start of the warning weak_warnings gives when a value the data barely determine is written large:
# the calibrated files say it (CAUTION), as they say a calibration worse than nominal on its test poses.
WEAK_AND_LARGE = "large corrections the data barely determine:"


def weak_and_large(warnings) -> str | None:
    """An estimate's warning that it writes large values the data barely determine, None without."""
    return next((w for w in warnings if w.startswith(WEAK_AND_LARGE)), None)
