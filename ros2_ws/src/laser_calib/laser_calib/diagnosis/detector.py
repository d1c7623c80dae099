"""The flexible structure detector: does the residual follow anything smooth?

What a residual can follow is not known in advance, so the detector regresses
the whitened residual of every measured value (spot coordinate, point or pose
axis) on all the inputs of a pose jointly: every joint reading, the sign and
the size of each joint's last move, the stamp and every extra column
(temperature). The size is there for what a joint does after a move other
than a dead band (the sign: backlash), such as a servo that stops short by a
share of the move (test_diagnosis.py: p 0.25-0.42 on the sign alone, and
"explained" on another joint and seed; 0.001-0.004 with the size). It enters that joint's angle error
only (submodels: own): with every direction, the size of joint 1's last move
"found" a Dahl loop of joint 3 at p = 0.01, by chance (bench/effects_probe3.py,
which the size of joint 3's own move does not see: p 0.91), and cost 16 %
more CPU on bench/effects_bench.py, 10 % as it is. The
regression goes through the kinematics: a pose's residual is modelled as

    W r  =  sum_j (W g_j) f_j(z)         g_j = d predicted / d theta_j, d alpha_j, d d_j, d a_j

a smooth joint-angle error f_j and smooth errors of each link's twist (link
bending, a tilted bearing), offset and length (a hose that pulls, a link that
grows with heat other than linearly), as functions of the inputs z. Each f_j is a
penalised regression on a basis of z (scikit-learn SplineTransformer: cubic
B-splines of every input, additive; plus the products of pairs of joint
readings, for errors that depend on two joints; scikit-learn Ridge), the
penalty the one of the best held-out gain over a grid (leave-one-value-out
GCV would leak between the values of one pose and choose too little). Why this family and not trees or a
GP on z alone: the residual's dependence on z is the product of the
Jacobian, which changes with every joint, and a smooth error; on 80 poses of
the 7-DOF arm a gradient-boosted regression and a GP with ARD of the raw
residual on z predicted held-out residuals worse than zero (held-out gain
-0.2 to -0.4 and -0.05 to -0.1 where this finds structure), while f_j(z) of a
joint coupling or a step in time is a simple function.

The regression is fitted on sub-models (submodels: one direction with one
input, or with a pair of joint readings); the one of
the best held-out gain counts, the choice inside the permutation test.

Test: the held-out gain 1 - SSE / SS0 over the engine's folds (each pose's
residual predicted by the fit on the other folds, SS0 that of predicting 0),
against its distribution under "the residual is noise": the same statistic
with the poses' residual vectors permuted (each permutation with its own best
sub-model and penalty, so the choice is inside the test; a batch of them fitted
as columns of one multi-target ridge per fold and penalty). The permutations
are drawn sequentially (Besag and Clifford 1991, "Sequential Monte Carlo
p-values"): batches of BATCH until EXCEEDANCES permuted gains reach the data's
(p = EXCEEDANCES / l, l the permutations drawn when the last of them came) or
MAX_PERMUTATIONS are drawn (p = (g + 1) / (MAX_PERMUTATIONS + 1), g of them
reaching it). A fixed 99 could not resolve p below 0.01: a test at alpha 0.01
then needed every permutation below the data, and lost structure whose p lies
near alpha; residuals with nothing in them stop after one batch. The test is
scale-free: a misstated noise level does not change it. What it found is named by
sklearn.inspection.permutation_importance of the inputs. Its regression,
refitted on all poses, is the learned compensator (compensator.py).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Mapping

import numpy as np
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.inspection import permutation_importance
from sklearn.linear_model import Ridge
from sklearn.preprocessing import SplineTransformer

from laser_calib.effects.base import last_moves, move_directions
from laser_calib.measurement.base import NoiseModel, Residuals

BATCH = 99               # permutations per pass (the first pass also fits the data)
MAX_PERMUTATIONS = 999   # p resolved to 0.001
EXCEEDANCES = 10         # permuted gains at least the data's that decide p early (Besag and Clifford's h)
ALPHAS = np.logspace(-2, 5, 8)
N_KNOTS, DEGREE = 4, 3
MIN_SPREAD = 1e-9  # an input that does not vary is left out
LINK_DIRECTIONS = ("alpha", "d", "a")  # the D-H link parameters a smooth error may follow, beside theta
STEP = re.compile(r"step[1-9][0-9]*")  # input_table's name of a joint's last move size


def input_table(q: np.ndarray, stamp: np.ndarray, extra: dict[str, np.ndarray]) -> tuple[list[str], np.ndarray]:
    """The detector's inputs of a pose sequence: names and values (P,d): q_i
    (rad), move_i (sign of the last move, in row order), step_i (the last move,
    q_i minus the row before's, from q = 0 before the first: rad), stamp (s), every extra column."""
    n = q.shape[1]
    names = ([f"q{i + 1}" for i in range(n)] + [f"move{i + 1}" for i in range(n)] + [f"step{i + 1}" for i in range(n)]
             + ["stamp"])
    columns = [q, move_directions(q), last_moves(q), np.asarray(stamp, float)[:, None]]
    for name, values in extra.items():
        names.append(name)
        columns.append(np.asarray(values, float)[:, None])
    return names, np.hstack(columns)


@dataclass(frozen=True)
class Basis:
    """The basis of the inputs: standardisation (mean, std (d,)), spline knots
    (K,d) in standardised units, pairs (i, j) of joint-reading columns, and
    size: the RMS of the whitened directions (1/rad), which divides the
    features so that one penalty grid fits every arm and noise level. A pair
    enters as the product of its two readings, or with ``tensor`` as the
    products of their splines (K + DEGREE - 1 squared functions: any smooth
    function of the two, such as sin q1 sin q7, which the product and the
    additive splines cannot hold; the compensator's refinement, compensation.py)."""

    mean: np.ndarray
    std: np.ndarray
    knots: np.ndarray
    pairs: np.ndarray  # (np, 2) int
    size: float = 1.0
    tensor: bool = False

    @classmethod
    def of(cls, z: np.ndarray, n_joints: int, size: float = 1.0) -> "Basis":
        mean, std = z.mean(axis=0), z.std(axis=0)
        std = np.where(std > MIN_SPREAD, std, 1.0)
        zs = (z - mean) / std
        knots = np.linspace(zs.min(axis=0), zs.max(axis=0), N_KNOTS)
        moving = [i for i in range(n_joints) if np.ptp(z[:, i]) > MIN_SPREAD]
        pairs = np.array([(i, j) for a, i in enumerate(moving) for j in moving[a + 1:]], int).reshape(-1, 2)
        return cls(mean, std, knots, pairs, size)

    def __call__(self, z: np.ndarray) -> np.ndarray:
        """(P,b) basis values at inputs z (P,d)."""
        zs = (z - self.mean) / self.std
        splines = SplineTransformer(knots=self.knots, degree=DEGREE, extrapolation="constant").fit(
            self.knots).transform(zs)                                              # (P, d n)
        if not self.tensor:
            return np.hstack([splines, zs[:, self.pairs[:, 0]] * zs[:, self.pairs[:, 1]]])
        n = self.splines_per_input
        per_input = splines.reshape(len(zs), -1, n)
        products = [(per_input[:, i, :, None] * per_input[:, j, None, :]).reshape(len(zs), n * n)
                    for i, j in self.pairs]
        return np.hstack([splines, *products])

    def part(self, z: np.ndarray, local: np.ndarray) -> np.ndarray:
        """(P, len(local)) the basis functions ``local`` (indices into __call__'s b columns) at
        inputs z (P,d), evaluating only the inputs and pairs they belong to: a sub-model holds one
        input or one pair, and permutation importance predicts with it many times."""
        n, d = self.splines_per_input, len(self.mean)
        per_pair = n * n if self.tensor else 1
        pair = np.where(local >= d * n, (local - d * n) // per_pair, -1)
        inputs = np.unique(np.concatenate([local[pair < 0] // n, self.pairs[pair[pair >= 0]].ravel()])).astype(int)
        zs = (z[:, inputs] - self.mean[inputs]) / self.std[inputs]
        knots = self.knots[:, inputs]
        splines = SplineTransformer(knots=knots, degree=DEGREE, extrapolation="constant").fit(knots).transform(zs)
        of = {k: splines[:, a * n:(a + 1) * n] for a, k in enumerate(inputs)}      # input -> its (P,n) splines
        out = np.empty((len(z), len(local)))
        for c, (column, p) in enumerate(zip(local, pair)):
            if p < 0:
                out[:, c] = of[column // n][:, column % n]
                continue
            i, j = self.pairs[p]
            if not self.tensor:
                out[:, c] = zs[:, np.searchsorted(inputs, i)] * zs[:, np.searchsorted(inputs, j)]
            else:
                k = column - d * n - p * per_pair
                out[:, c] = of[i][:, k // n] * of[j][:, k % n]
        return out

    @property
    def splines_per_input(self) -> int:
        return len(self.knots) + DEGREE - 1

    @property
    def width(self) -> int:
        """b, the number of basis functions: every input's splines, then per pair its
        product or, with tensor, the products of its two inputs' splines."""
        n = self.splines_per_input
        return len(self.mean) * n + len(self.pairs) * (n * n if self.tensor else 1)


class OffsetRegression(BaseEstimator, RegressorMixin):
    """y = sum_j g_j f_j(z), f_j = basis(z) @ c_j, ridge-penalised (sklearn Ridge).

    X rows (one per measured value): the inputs z (d) of its pose, then the
    whitened directions g (m) of the value; y the whitened residual. The basis
    is fixed from the calibration poses, so every fold shares it."""

    def __init__(self, basis: Basis | None = None, n_inputs: int = 0, alpha: float = 1.0,
                 columns: np.ndarray | None = None):
        self.basis = basis
        self.n_inputs = n_inputs
        self.alpha = alpha
        self.columns = columns

    def all_features(self, X: np.ndarray) -> np.ndarray:
        """(rows, m b): every direction times every basis function (direction-major)."""
        z, g = X[:, :self.n_inputs], X[:, self.n_inputs:]
        return (g[:, :, None] * self.basis(z)[:, None, :]).reshape(len(X), -1) / self.basis.size

    def features(self, X: np.ndarray) -> np.ndarray:
        """The ``columns`` of all_features (all when None), only those formed, from only the basis
        functions they use (permutation importance predicts 146 times; all of them are ~20x the
        chosen sub-model's)."""
        if self.columns is None:
            return self.all_features(X)
        local = np.unique(self.columns % self.basis.width)
        values = np.zeros((len(X), self.basis.width))
        values[:, local] = self.basis.part(X[:, :self.n_inputs], local)
        return self.formed(X, values, self.columns)

    def formed(self, X: np.ndarray, basis_values: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """(rows, len(columns)) the ``columns`` of all_features from the basis at the rows' inputs (rows, b)."""
        width = basis_values.shape[1]
        return X[:, self.n_inputs + columns // width] * basis_values[:, columns % width] / self.basis.size

    def fit(self, X: np.ndarray, y: np.ndarray) -> "OffsetRegression":
        self.ridge_ = Ridge(alpha=self.alpha, fit_intercept=False).fit(self.features(X), y)
        return self

    def predict(self, X: np.ndarray) -> np.ndarray:
        return self.ridge_.predict(self.features(X))

    def coefficients(self, n_directions: int) -> np.ndarray:
        """(m, b) coefficients per direction and basis function (rad; 0 where not used)."""
        width = self.basis.width
        out = np.zeros(n_directions * width)
        out[slice(None) if self.columns is None else self.columns] = self.ridge_.coef_ / self.basis.size
        return out.reshape(n_directions, width)


@dataclass(frozen=True)
class Detection:
    """The detector's finding: held-out gain (1 - SSE/SS0 over the folds), its
    permutation p, the null gains' 99th percentile, the inputs by permutation
    importance (name, mean increase of the MSE in whitened units^2, its std),
    the best regression refitted on all poses (the compensator's), the
    direction names, the inputs and the permutations drawn."""

    gain: float
    p: float
    null_99: float
    importance: tuple[tuple[str, float, float], ...]
    regression: OffsetRegression
    targets: tuple[str, ...]
    inputs: tuple[str, ...]
    permutations: int

    def sentence(self) -> str:
        named = ", ".join(f"{n} ({v:.2g})" for n, v, _ in self.importance[:4] if v > 0) or "no input singly"
        return (f"a flexible regression on all inputs predicts the held-out residual {100 * self.gain:.1f} % better "
                f"than zero (permutation p = {self.p:.2g}, {self.permutations} permutations; 99 % of permuted gains "
                f"below {100 * self.null_99:.1f} %); inputs by importance: {named}")


def directions(names: tuple[str, ...], res: Residuals, whitener: np.ndarray, n_joints: int
               ) -> tuple[tuple[str, ...], np.ndarray]:
    """The whitened directions (P,V,m) of each pose's V values: every joint
    angle (jac_q) and every link parameter of LINK_DIRECTIONS the model has (jac)."""
    n_poses = res.r.shape[0]
    flat_q = res.jac_q.reshape(n_poses, -1, n_joints)
    link = [names.index(f"{kind}{j + 1}") for kind in LINK_DIRECTIONS for j in range(n_joints)
            if f"{kind}{j + 1}" in names]
    columns = np.concatenate([flat_q, res.jac.reshape(n_poses, -1, res.jac.shape[-1])[..., link]], axis=-1)
    targets = tuple(f"theta{j + 1}" for j in range(n_joints)) + tuple(names[k] for k in link)
    return targets, np.einsum("pij,pjm->pim", whitener, columns)


def submodels(basis: Basis, n_inputs: int, n_directions: int, own: Mapping[int, int] | None = None
              ) -> list[np.ndarray]:
    """Column sets of all_features: each direction with each input's splines,
    each direction with a pair of joint readings (both splines and their
    product). A smooth error of one joint or link following
    one or two inputs is found with few terms; all inputs at once on 80 poses
    overfit so much that they miss it (held-out gain -0.07 where one input gave 0.24).
    own: input -> the one direction it is tried with (a joint's last move size:
    its angle error only), each a sub-model less to choose from than with every direction."""
    own = dict(own or {})
    n_splines = N_KNOTS + DEGREE - 1
    width = n_inputs * n_splines + len(basis.pairs)
    spline = [np.arange(k * n_splines, (k + 1) * n_splines) for k in range(n_inputs)]
    local = [spline[k] for k in range(n_inputs) if k not in own] + [
        np.concatenate([spline[i], spline[k], [n_inputs * n_splines + p]]) for p, (i, k) in enumerate(basis.pairs)]
    return ([j * width + cols for j in range(n_directions) for cols in local]
            + [j * width + spline[k] for k, j in own.items()])


@dataclass(frozen=True)
class FoldRidge:
    """What the held-out errors of a sub-model's ridge fits on one fold need
    besides the targets: the eigenvalues (k,) and eigenvectors (k,k) of the
    training rows' Gram matrix F_t^T F_t and the held rows' Gram matrix in
    that basis, V^T F_h^T F_h V (k,k). Kept per sub-model and fold, so that
    every batch of permutations pays only for its products with the targets."""

    values: np.ndarray
    vectors: np.ndarray
    held_gram: np.ndarray

    @classmethod
    def of(cls, gram_train: np.ndarray, gram_held: np.ndarray) -> "FoldRidge":
        values, vectors = np.linalg.eigh(gram_train)
        return cls(np.maximum(values, 0.0), vectors, vectors.T @ gram_held @ vectors)

    def sse(self, cross_train: np.ndarray, cross_held: np.ndarray, y_held_squared: np.ndarray) -> np.ndarray:
        """(len(ALPHAS), T) held-out sums of squares of the ridge fits (no intercept) of T
        targets at every penalty, from F_t^T Y_t and F_h^T Y_h (k,T) and the held targets'
        sums of squares (T,): with w = V (D + alpha)^-1 V^T F_t^T Y_t,
        ||Y_h - F_h w||^2 = ||Y_h||^2 - 2 w^T F_h^T Y_h + w^T F_h^T F_h w, all in the
        eigenbasis, so no held row is predicted (one eigendecomposition serves every
        penalty; sklearn's Ridge would refactor per penalty and sub-model)."""
        rotated, held = self.vectors.T @ cross_train, self.vectors.T @ cross_held     # (k,T) each
        out = np.empty((len(ALPHAS), rotated.shape[1]))
        for a, alpha in enumerate(ALPHAS):
            w = rotated / (self.values + alpha)[:, None]
            out[a] = y_held_squared - 2.0 * (w * held).sum(axis=0) + (w * (self.held_gram @ w)).sum(axis=0)
        return out


def design(names: tuple[str, ...], res: Residuals, noise: NoiseModel, z: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, tuple[str, ...], np.ndarray]:
    """The regression's rows X (P*V, d+m) and whitened residuals y (P,V) of a
    fit's residual res at inputs z (P,d); the direction names and directions (P,V,m)."""
    n_poses = len(z)
    whitener = noise.whitener(res)
    y = np.einsum("pij,pj->pi", whitener, res.r.reshape(n_poses, -1))
    targets, g = directions(names, res, whitener, res.jac_q.shape[-1])
    X = np.concatenate([np.repeat(z, y.shape[1], axis=0), g.reshape(-1, g.shape[-1])], axis=1)
    return X, y, targets, g


def detect(names: tuple[str, ...], res: Residuals, noise: NoiseModel, q: np.ndarray, stamp: np.ndarray,
           extra: dict[str, np.ndarray], fold: np.ndarray, seed: int) -> Detection:
    """The detector (module docstring) on a fit's residual res (with jac, jac_q),
    the model's parameter names, the poses' readings, stamps and extra columns,
    the engine's fold of each pose (P,) and a seed for the permutations."""
    n_poses, n_joints = q.shape
    input_names, z = input_table(q, stamp, extra)
    varying = np.ptp(z, axis=0) > MIN_SPREAD
    input_names, z = [n for n, v in zip(input_names, varying) if v], z[:, varying]
    X, y, targets, g = design(names, res, noise, z)
    size = float(np.sqrt(np.mean(g[np.any(g != 0, axis=-1)] ** 2)))
    basis = Basis.of(z, int(varying[:n_joints].sum()), size)
    n_values = y.shape[1]
    rng = np.random.default_rng(seed)
    own = {k: int(name[4:]) - 1 for k, name in enumerate(input_names) if STEP.fullmatch(name)}  # step_j -> theta_j
    subsets = submodels(basis, z.shape[1], g.shape[-1], own)
    held = [np.repeat(fold, n_values) == k for k in np.unique(fold)]
    former = OffsetRegression(basis, z.shape[1])
    basis_values = np.repeat(basis(z), n_values, axis=0)   # X's rows: each pose's inputs once per value

    ridges: list[list[FoldRidge]] = []   # per sub-model and fold, from the first batch on

    def gains_of(orders: list[np.ndarray]) -> np.ndarray:
        """(subsets, ALPHAS, T) held-out gains of the residual in each pose order."""
        Y = np.stack([y[order].ravel() for order in orders], axis=1)              # (P*V, T)
        held_y = [Y[rows] for rows in held]
        squared = [(part ** 2).sum(axis=0) for part in held_y]
        sse = np.zeros((len(subsets), len(ALPHAS), Y.shape[1]))
        # Each sub-model's columns of all_features formed on their own (all of them at once, m b
        # columns, were the detector's largest array), and a fold's training sums as all rows'
        # less its held rows' (no copy of the training rows).
        for m, columns in enumerate(subsets):
            features = former.formed(X, basis_values, columns)
            cross_all = features.T @ Y
            parts = [features[rows] for rows in held]
            if len(ridges) == m:
                gram_all = features.T @ features
                ridges.append([FoldRidge.of(gram_all - part.T @ part, part.T @ part) for part in parts])
            for ridge, part, y_held, y_squared in zip(ridges[m], parts, held_y, squared):
                cross_held = part.T @ y_held
                sse[m] += ridge.sse(cross_all - cross_held, cross_held, y_squared)
        return 1.0 - sse / np.maximum((Y ** 2).sum(axis=0), 1e-300)

    # The model and penalty of the best held-out gain, for the data and for every permutation alike.
    def best(gains: np.ndarray) -> np.ndarray:
        """(T,) each order's best gain over the sub-models and penalties of gains (subsets, ALPHAS, T)."""
        return gains.reshape(-1, gains.shape[-1]).max(axis=0)

    all_gains = gains_of([np.arange(n_poses)] + [rng.permutation(n_poses) for _ in range(BATCH)])
    gain = float(all_gains[..., 0].max())
    null = best(all_gains[..., 1:])
    while np.sum(null >= gain) < EXCEEDANCES and len(null) < MAX_PERMUTATIONS:
        more = min(BATCH, MAX_PERMUTATIONS - len(null))
        null = np.concatenate([null, best(gains_of([rng.permutation(n_poses) for _ in range(more)]))])
    reached = np.flatnonzero(null >= gain)
    p = (EXCEEDANCES / (reached[EXCEEDANCES - 1] + 1) if len(reached) >= EXCEEDANCES
         else (len(reached) + 1) / (len(null) + 1))
    m, a = np.unravel_index(int(np.argmax(all_gains[..., 0])), all_gains.shape[:2])
    regression = OffsetRegression(basis, z.shape[1], float(ALPHAS[a]), subsets[m]).fit(X, y.ravel())
    importance: tuple[tuple[str, float, float], ...] = ()
    if gain > 0:
        found = permutation_importance(regression, X, y.ravel(), scoring="neg_mean_squared_error", n_repeats=5,
                                       random_state=seed)
        ranked = sorted(range(z.shape[1]), key=lambda c: -found.importances_mean[c])
        importance = tuple((input_names[c], float(found.importances_mean[c]), float(found.importances_std[c]))
                           for c in ranked)
    return Detection(gain, float(p), float(np.quantile(null, 0.99)), importance, regression, targets,
                     tuple(input_names), len(null))
