"""What the measurements can and cannot separate.

The stacked, whitened measurement Jacobian J (M,n) is scaled column-wise by
each parameter's characteristic size (10 mm, 1 deg) so that singular values
compare like with like. Directions with a singular value below ``rel_tol`` of
the largest are invisible to the data; the estimators fix one parameter per
such direction at its nominal value and say which parameters carry the
combination instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

REL_TOL = 1e-7


@dataclass(frozen=True)
class Identifiability:
    """singular_values (min(M,n),) of the scaled Jacobian; rank; condition number
    (largest / smallest kept singular value); free (n,) parameters kept;
    null_combinations: one text per invisible direction; merged: fixed parameter
    name -> the parameters that carry its combination."""

    names: tuple[str, ...]
    singular_values: np.ndarray
    rank: int
    condition: float
    free: np.ndarray
    null_combinations: tuple[str, ...]
    merged: dict[str, str]

    def table(self) -> str:
        lines = [f"parameters: {len(self.names)}   numerical rank: {self.rank}   "
                 f"condition number (scaled): {self.condition:.3g}", "",
                 " k  singular value (scaled)"]
        lines += [f"{k + 1:2d}  {s:.4g}" for k, s in enumerate(self.singular_values)]
        if self.null_combinations:
            lines += ["", "directions that move no spot (coefficients in units of 10 mm / 1 deg; "
                      "+1 d1 -1 d2 means only the sum d1 + d2 is seen):"]
            lines += [f"  {text}" for text in self.null_combinations]
            lines += ["", "fixed at nominal (merged):"]
            lines += [f"  {name}: {how}" for name, how in self.merged.items()]
        else:
            lines += ["", "all parameters identifiable"]
        return "\n".join(lines)


def describe(vector: np.ndarray, names: tuple[str, ...], threshold: float = 0.05) -> str:
    v = vector / np.abs(vector).max()
    v = v * np.sign(v[np.flatnonzero(np.abs(v) > threshold)[0]])  # first term positive: one canonical text
    terms = [f"{c:+.2f} {names[i]}" for i, c in enumerate(v) if abs(c) > threshold]
    return " ".join(terms)


def analyse(jacobian: np.ndarray, scales: np.ndarray, names: tuple[str, ...],
            fixed: np.ndarray | None = None, rel_tol: float = REL_TOL) -> Identifiability:
    """Identifiability of the parameters from a whitened Jacobian (M,n).

    Parameters are kept greedily in their natural order (base to tip), so of a
    pair that only acts as a sum the one nearer the base is kept and carries it.
    ``fixed`` (n,) marks parameters the user holds; they are never kept.
    """
    n = jacobian.shape[1]
    fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, bool)
    scaled = jacobian * scales
    candidates = np.flatnonzero(~fixed)
    _, singular, vt = np.linalg.svd(scaled[:, candidates], full_matrices=False)
    top = singular[0] if singular.size and singular[0] > 0 else 1.0
    rank = int((singular > rel_tol * top).sum())

    kept: list[int] = list(candidates)
    if rank < len(candidates):
        kept = []
        for j in candidates:
            trial = scaled[:, kept + [j]]
            if np.linalg.svd(trial, compute_uv=False)[-1] > rel_tol * top:
                kept.append(j)
    free = np.zeros(n, bool)
    free[kept] = True

    if vt.shape[0] < len(candidates):  # fewer values than parameters: complete the basis
        vt = np.linalg.svd(scaled[:, candidates])[2]
    null = vt[rank:].T  # (len(candidates), n - rank) in scaled coordinates
    null_full = np.zeros((n, null.shape[1]))
    null_full[candidates] = null
    combinations = tuple(describe(null_full[:, k], names) for k in range(null_full.shape[1]))
    merged = {}
    projector = null_full @ null_full.T
    for j in np.flatnonzero(~free & ~fixed):
        partners = [names[i] for i in np.flatnonzero(np.abs(projector[j]) > 0.05) if i != j and free[i]]
        merged[names[j]] = ("not separable from " + ", ".join(partners) + "; fixed at nominal, "
                            "those parameters carry the combination") if partners else "not seen by the data; fixed at nominal"
    kept_singular = singular[:rank]
    condition = float(kept_singular[0] / kept_singular[-1]) if rank else float("inf")
    return Identifiability(tuple(names), singular, rank, condition, free, combinations, merged)
