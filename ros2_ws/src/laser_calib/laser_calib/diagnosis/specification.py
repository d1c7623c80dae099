"""The specification test of the chosen model: does a parameter vary with a covariate?

A library effect that approximates a foreign one (compliance for a stiffness
that changes with another joint, periodic for a polynomial joint error, drift
for a step in time) can bring the residual to the noise level, so a test of
the level alone passes. What it leaves is a parameter of the model that is not
constant: its effect on the measurements is the model's own Jacobian column
modulated by a function of what the pose was measured with. The test (a
varying-coefficient, RESET-like F test) asks that of every column of the final
model (every identifiable geometric error and effect parameter) and every
covariate (each joint reading, the stamp, every extra column such as the
temperature; for the geometric columns also the gravity torque of each joint:
a link that bends or a bearing that tilts under the load makes a length or
twist follow a torque, which no joint reading alone carries, and the library's
compliance covers only a joint's own angle following its own torque; the
added effects' columns keep their own share of alpha undiluted by the loads):

    y = W r (whitened residual, M values),  J = W d predicted / d x (M, k free columns)
    Z = [J_j P1(u_c), J_j P2(u_c)]  (M, 2)  u_c the covariate mapped to [-1, 1] (per pose),
                                            P1, P2 the Legendre polynomials of degree 1, 2
    Z, y with the columns of J projected out;  F = (dSS / r) / ((SS - dSS) / (M - k - r))

dSS the sum of squares of y the r independent columns of Z explain. F(r, M-k-r)
under "the model is right" whatever the noise level (both sums scale alike), so
it holds when a noise component is estimated.

Every quantity is a sum over the values, so the poses are read block by block
and nothing of size M is kept: the QR factor R of J (stacked blocks, as
estimation.problem.whitened_factor) gives J's span, B = J V S^-1 (the right
singular vectors V and values S of R, columns of J at unit norm); per
covariate c and degree a the sums J^T diag(P_a) J (k,k), J^T diag(P_a) y and
the columns' sums of J_j^2 P_a P_b give, for every column j at once,
B^T Z = S^-1 V^T J^T Z, Z^T Z and Z^T y, hence the projected
Z'^T Z' = Z^T Z - (B^T Z)^T B^T Z and Z'^T y' = Z^T y - (B^T Z)^T B^T y, whose
eigen-decomposition (r,r) is the SVD of Z' the test needs.

One test per (column, covariate) pair rather than one per covariate with every
column at once: an error outside the library makes one parameter vary with one
covariate, and a test with 2 degrees of freedom sees it with a fraction of the
chi^2 excess that one with 2k needs. The p-values are Bonferroni-adjusted, weighted: the columns of the
effects the selection added (the chosen form, the prime suspect) get one share
of the family rate, shared by their pairs, the geometric errors another (all
of it when no effect was added).

The shape of a drift (effects.drift: a length linear in the stamp or an
extra column such as the temperature) is tested apart, as a third share: a
drift says the arm changes with that covariate, and the library's form is
the simplest one, one length changing linearly. Time and heat change an arm
in ways that are not smooth (a coupling slips, the arm is re-homed, a fan
starts) and at more than one place, so every column is also tested against a
free function of the drift's covariate: the column times cubic B-splines of
it (the detector's knots), whose span holds a step as well as a curve:

    Z = J_j B(c)   (M, N_KNOTS + 2)   B the cubic B-splines on N_KNOTS knots over the range of the
                                      covariate c; they sum to 1, so J_j itself (in the model)
                                      is one of their combinations: N_KNOTS + 1 dof

The shares are equal among the families that have pairs: the family rate of
a false "structure remains" is at most the engine's alpha (1 %) in every case.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Iterable, Mapping

import numpy as np
from scipy import stats
from sklearn.preprocessing import SplineTransformer

from laser_calib.diagnosis.detector import DEGREE, N_KNOTS
from laser_calib.effects.base import Effect
from laser_calib.effects.drift import Drift
from laser_calib.measurement.base import NoiseModel, Residuals, whiten

MIN_SPREAD = 1e-9       # a covariate that does not vary is not a covariate
SMOOTH, FREE = "smooth", "free"  # the shapes a parameter is tested to vary in
RANK_TOLERANCE = 1e-4   # a column whose part outside the model's span is below this fraction of its norm adds nothing


@dataclass(frozen=True)
class Varying:
    """One (column, covariate) test: F on dof, its p and Bonferroni-adjusted p,
    the fraction of the residual sum of squares the varying column explains and
    the shape tested: SMOOTH (Legendre degree 1, 2) or FREE (B-splines, a drift's shape)."""

    parameter: str
    covariate: str
    f: float
    dof: tuple[int, int]
    p: float
    p_adjusted: float
    share: float
    shape: str = SMOOTH

    def sentence(self) -> str:
        shape = " beyond a linear drift (a free shape)" if self.shape == FREE else ""
        return (f"{self.parameter} varies with {self.covariate}{shape} (varying-coefficient F = {self.f:.3g} on "
                f"{self.dof[0]}, {self.dof[1]} dof, p = {self.p_adjusted:.2g} Bonferroni-adjusted, "
                f"{100 * self.share:.1f} % of the residual sum of squares)")


def varying(out: list[tuple[str, np.ndarray]]) -> list[tuple[str, np.ndarray]]:
    return [(name, values) for name, values in out if np.all(np.isfinite(values)) and np.ptp(values) > MIN_SPREAD]


def covariate_table(q: np.ndarray, stamp: np.ndarray, extra: Mapping[str, np.ndarray]
                    ) -> list[tuple[str, np.ndarray]]:
    """The covariates (name, (P,) values) a parameter may vary with: q_i, stamp, every extra column."""
    out = [(f"q{i + 1}", q[:, i]) for i in range(q.shape[1])] + [("stamp", np.asarray(stamp, float))]
    return varying(out + [(name, np.asarray(values, float)) for name, values in extra.items()])


def load_table(torques: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """The loads a geometric error may vary with: the gravity torque of each joint, torque_i
    (torques (P,N), effects.joint.gravity_torques)."""
    return varying([(f"torque{i + 1}", torques[:, i]) for i in range(torques.shape[1])])


def legendre(values: np.ndarray) -> np.ndarray:
    """(P,2) Legendre polynomials of degree 1 and 2 of the values mapped to [-1, 1]."""
    u = 2.0 * (values - values.min()) / np.ptp(values) - 1.0
    return np.stack([u, 1.5 * u ** 2 - 0.5], axis=1)


def free_shape(values: np.ndarray) -> np.ndarray:
    """(P,N_KNOTS+2) cubic B-splines of the values on N_KNOTS evenly spaced knots over their range."""
    return SplineTransformer(n_knots=N_KNOTS, degree=DEGREE).fit_transform(np.asarray(values, float)[:, None])


def drift_covariates(effects: tuple[Effect, ...] | list[Effect]) -> tuple[str, ...]:
    """The covariates the added drifts follow (stamp, temperature, ...), each once."""
    return tuple(dict.fromkeys(e.covariate for e in effects if isinstance(e, Drift)))


def specification_tests(names: tuple[str, ...], identifiable: np.ndarray,
                        res: Residuals | Iterable[tuple[slice, Residuals]], noise: NoiseModel,
                        covariates: list[tuple[str, np.ndarray]], n_geometric: int | None = None,
                        loads: list[tuple[str, np.ndarray]] = (), drifts: tuple[str, ...] = ()) -> list[Varying]:
    """Every (column, covariate) test (module docstring) of a fit's residual
    (with jac at the fit): res, or its blocks of poses (index, Residuals) in
    order (estimation.problem.pose_blocks); the model's parameter names and
    identifiable mask (n,), under the noise model; the first n_geometric
    parameters are the geometric errors, the rest the added effects' (None: all
    geometric); loads (load_table) are tested against the geometric columns
    only; every column against a free shape of the covariates named in drifts
    (drift_covariates); strongest first."""
    # (covariate, modulation (P,r), shape, which columns): smooth against every covariate, loads
    # against the geometric columns, a free shape of each drift's covariate against every column.
    table = dict(covariates)
    plan = ([(c, legendre(v), SMOOTH, True) for c, v in covariates] + [(c, legendre(v), SMOOTH, False) for c, v in loads]
            + [(c, free_shape(table[c]), FREE, True) for c in drifts if c in table])
    sums = _Sums([modulation for _, modulation, _, _ in plan])
    for index, block in [(slice(None), res)] if isinstance(res, Residuals) else res:
        y, jac = whiten(block, noise.for_poses(index).whitener(block))
        rows = np.repeat(block.valid, block.r.shape[2], axis=1).ravel()
        sums.add(index, np.where(rows, y, 0.0), np.where(rows[:, None], jac[:, identifiable], 0.0), int(rows.sum()))
    norms = np.linalg.norm(sums.factor, axis=0)                        # J's column norms (R's)
    used = norms > 0
    if not used.any():  # no measured value moves with a parameter (a wrong robot file's fit lost them all)
        return []
    columns = [names[k] for k, u in zip(np.flatnonzero(identifiable), used) if u]
    # J at unit column norms, J' = J D: its span's orthonormal basis B = J' V S^-1 over the
    # singular values kept (R' = R D = U S V^T), so B^T = to_span J^T
    _, s, vt = np.linalg.svd(sums.factor[:, used] / norms[used], full_matrices=False)
    kept = s > RANK_TOLERANCE * s.max()
    to_span = vt[kept] / s[kept, None] / norms[used]                   # (k, used)
    span_y = to_span @ sums.jy[used]                                   # B^T y
    total = sums.yy - float(span_y @ span_y)                           # ||y'||^2, y' = y - B B^T y
    n_values, k = sums.n_values, int(kept.sum())
    found, family = [], []
    added = set(names[len(names) if n_geometric is None else n_geometric:])
    for (covariate, _, shape, with_added), weighted, zy, zz in zip(plan, sums.weighted, sums.zy, sums.zz):
        # per column j, Z_j = J'_j P(u): B^T Z_j (k,r), Z_j^T Z_j (r,r), Z_j^T y (r,)
        span_z = np.einsum("sk,akj->jsa", to_span, weighted[:, used][:, :, used]) / norms[used, None, None]
        z_z = zz[:, :, used] / norms[used] ** 2
        z_y = zy[:, used] / norms[used]
        for j, parameter in enumerate(columns):
            if not with_added and parameter in added:
                continue
            size = float(np.sqrt(np.diag(z_z[:, :, j]).max()))          # Z's largest column norm
            gram = z_z[:, :, j] - span_z[j].T @ span_z[j]              # Z'^T Z', Z' = Z - B B^T Z
            value, vector = np.linalg.eigh(gram)                       # Z' = U sqrt(value) vector^T
            independent = np.sqrt(np.maximum(value, 0.0)) > RANK_TOLERANCE * size
            r = int(independent.sum())
            dof = n_values - k - r
            if r == 0 or dof < 1:
                continue
            projected = vector[:, independent].T @ (z_y[:, j] - span_z[j].T @ span_y)   # sqrt(value) U^T y'
            explained = float(np.sum(projected ** 2 / value[independent]))
            f = (explained / r) / max((total - explained) / dof, 1e-300)
            found.append(Varying(parameter, covariate, f, (r, dof), float(stats.f.sf(f, r, dof)), 1.0,
                                 explained / max(total, 1e-300), shape))
            family.append(FREE if shape == FREE else "effect" if parameter in added else "geometric")
    # Weighted Bonferroni: an equal share of alpha per family that has pairs, shared by its pairs.
    sizes = {name: family.count(name) for name in set(family)}
    found = [replace(v, p_adjusted=min(1.0, v.p * len(sizes) * sizes[f])) for v, f in zip(found, family)]
    return sorted(found, key=lambda v: (v.p_adjusted, -v.f))


class _Sums:
    """The test's sums over the values, block by block of poses: the QR factor R
    of J (each block stacked under it), J^T y, y^T y and the values measured, and
    per modulation P (P poses, r functions) J^T diag(P_a) J (r,k,k),
    sum_m P_a y J (r,k) and sum_m P_a P_b J^2 (r,r,k) (m over the values)."""

    def __init__(self, modulations: list[np.ndarray]):
        self.modulations = modulations
        self.factor = None
        self.jy, self.yy, self.n_values = 0.0, 0.0, 0
        self.weighted, self.zy, self.zz = ([0.0] * len(modulations) for _ in range(3))

    def add(self, index: slice, y: np.ndarray, jac: np.ndarray, n_values: int) -> None:
        """The block of poses ``index``: whitened y (m,) and jac (m,k), zero where not measured."""
        self.factor = np.linalg.qr(jac if self.factor is None else np.vstack([self.factor, jac]), mode="r")
        self.jy = self.jy + jac.T @ y
        self.yy += float(y @ y)
        self.n_values += n_values
        m, k = jac.shape
        square = jac * jac
        for c, modulation in enumerate(self.modulations):
            p = np.repeat(modulation[index], m // len(modulation[index]), axis=0)        # (m,r) per value
            r = p.shape[1]
            modulated = (p[:, :, None] * jac[:, None, :]).reshape(m, r * k)              # [P_1 J, ..., P_r J]
            self.weighted[c] = self.weighted[c] + (modulated.T @ jac).reshape(r, k, k)
            self.zy[c] = self.zy[c] + (p * y[:, None]).T @ jac
            self.zz[c] = self.zz[c] + ((p[:, :, None] * p[:, None, :]).reshape(m, r * r).T @ square).reshape(r, r, k)
