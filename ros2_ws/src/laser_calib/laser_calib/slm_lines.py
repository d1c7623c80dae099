"""The lines of slm-calibrate's spots (slm.py): least squares with or without some spots, and the robust
start of its outlier rule, which needs a spot sigma before any spot is trusted.

Each laser's lines of u and v against the distance are fitted by repeated medians (scipy.stats.siegelslopes:
half the spots may be wrong), and the spots far off them stand out. The spots' distances off those lines do
not measure the noise: the lines pass through or near the spots they are fitted to, so with few distances
the distances are small (their median said 0.57 sigma at four distances and 0.83 at eight over 2000 clean
simulated files, 0.72 and 0.89 with one spot 50 mm off), and a sigma too small makes good spots stand out.
The sigma comes from lines no fit has chosen instead: for three spots a, b, c of one laser
(d_a <= d_b <= d_c, d_a < d_c),

    e = p_b - w_a p_a - w_c p_c,    w_a = (d_c - d_b) / (d_c - d_a),    w_c = (d_b - d_a) / (d_c - d_a),

is b's distance off the line through a and c. It is zero for spots on any line, so for clean spots
e / sqrt(1 + w_a^2 + w_c^2) is distributed exactly as one spot's (u, v) noise, at any number of distances,
and its squared length as sigma^2 chi^2_2 (the pseudo-residuals of Gasser, Sroka and Jennen-Steinmetz,
Biometrika 1986, here over every triple). So s^2 = median(those) / median(chi^2_2) over the triples of
both lasers (one screen measures both) without a spot that stands out. A spot stands out first off the
repeated-median lines at their (low) scale, then stays out only while its residual at the least-squares
lines of the other spots, over its std there, is beyond the limit at the triples' s: the spots out only
shrink, so this ends. Over the same files s says 0.92 sigma at four distances (a clean spot that stays
out takes three of its laser's four triples along), 1.00 at eight; with one spot 50 mm off, 0.97 and 1.00
(standard errors 0.01; the estimate's own spread 0.4 and 0.2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import combinations

import numpy as np

SPOT_VALUES = 2  # u and v: a wrong spot is wrong as a whole, whichever coordinate shows it
# A robust scale below a nanometre is rounding of exact (hand-made, simulated) spots, not noise: without
# this floor their last digits would look like outliers.
SCALE_FLOOR = 1e-9
MEDIAN_CHI2_2 = 2.0 * math.log(2.0)  # median of chi^2 with 2 degrees of freedom


@dataclass(frozen=True)
class Spots:
    """One laser's spots: the measurements file's line of each, the fixture distance (m), u and v (m)."""

    line: np.ndarray
    distance: np.ndarray
    uv: np.ndarray


def line_fit(distance: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares lines of u and v against the distance: coefficients (2,2) (slope, offset per column),
    the residual (K,2) and (A^T A)^-1 (2,2) of the design A = [D, 1]."""
    design = np.column_stack([distance, np.ones_like(distance)])
    coef, *_ = np.linalg.lstsq(design, uv, rcond=None)
    return coef, uv - design @ coef, np.linalg.inv(design.T @ design)


def deletion(spots: Spots, out: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Least squares on the spots not ``out``: the residual (K,2) of every spot there, the variance factor
    1 + a (A^T A)^-1 a^T of each left-out spot's residual (1 elsewhere), the fitted spots' sum of squares
    and residual degrees of freedom."""
    kept = ~out
    coef, resid, cov_unit = line_fit(spots.distance[kept], spots.uv[kept])
    design = np.column_stack([spots.distance, np.ones_like(spots.distance)])
    factor = np.where(out, 1.0 + np.einsum("ki,ij,kj->k", design, cov_unit, design), 1.0)
    return spots.uv - design @ coef, factor, float((resid ** 2).sum()), SPOT_VALUES * (int(kept.sum()) - 2)


def robust_distances(spots: Spots) -> np.ndarray:
    """Squared distances (K,) of the spots off repeated-median lines of u and v."""
    from scipy.stats import siegelslopes  # here: scipy.stats takes seconds to import, and only this needs it

    fits = [siegelslopes(spots.uv[:, c], spots.distance) for c in range(SPOT_VALUES)]
    resid = spots.uv - np.column_stack([f.intercept + f.slope * spots.distance for f in fits])
    return (resid ** 2).sum(axis=1)


def _contrasts(spots: Spots) -> tuple[np.ndarray, np.ndarray]:
    """The triples (T,3) of spots (indices, by distance) whose outer two lie at two distances, and the squared
    length (T,) of each middle spot's distance off the line through the outer two, over its std factor."""
    triples = np.array(list(combinations(np.argsort(spots.distance, kind="stable"), 3)), dtype=int).reshape(-1, 3)
    triples = triples[spots.distance[triples[:, 2]] > spots.distance[triples[:, 0]]]
    d_a, d_b, d_c = spots.distance[triples].T
    w_a, w_c = (d_c - d_b) / (d_c - d_a), (d_b - d_a) / (d_c - d_a)
    e = spots.uv[triples[:, 1]] - w_a[:, None] * spots.uv[triples[:, 0]] - w_c[:, None] * spots.uv[triples[:, 2]]
    return triples, (e ** 2).sum(axis=1) / (1.0 + w_a ** 2 + w_c ** 2)


def robust_scale(lasers: list[Spots], limit: float) -> tuple[float, list[np.ndarray]]:
    """The spot sigma (m) estimated robustly (module docstring) and each laser's squared distances (K,) off its
    repeated-median lines; ``limit``: of d^2 / s^2 for a spot that stands out."""
    distances = [robust_distances(spots) for spots in lasers]
    scale = max(math.sqrt(float(np.median(np.concatenate(distances))) / MEDIAN_CHI2_2), SCALE_FLOOR)
    out = [d2 / scale ** 2 > limit for d2 in distances]
    contrasts = [_contrasts(spots) for spots in lasers]
    while True:
        clean = np.concatenate([z2[~o[triples].any(axis=1)] for (triples, z2), o in zip(contrasts, out)])
        if not len(clean):  # every triple holds a spot that stands out: the repeated-median lines' scale
            return scale, distances
        scale = max(math.sqrt(float(np.median(clean)) / MEDIAN_CHI2_2), SCALE_FLOOR)
        back = []
        for spots, o in zip(lasers, out):
            if len(np.unique(spots.distance[~o])) < 2:  # the others fit no line to judge them by
                back.append(np.zeros_like(o))
                continue
            resid, factor, _, _ = deletion(spots, o)
            back.append(o & ((resid ** 2).sum(axis=1) / factor <= limit * scale ** 2))
        if not any(b.any() for b in back):
            return scale, distances
        out = [o & ~b for o, b in zip(out, back)]
