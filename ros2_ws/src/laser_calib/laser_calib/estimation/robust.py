"""Robust estimation: a single wrong detection, whatever its size, cannot move the fit.

Iteratively reweighted least squares on the normal equations of a Problem:
each measured unit (a spot, a point, a pose: one channel of one pose, D
values) gets a weight w, applied as sqrt(w) on its columns of the whitener
(its covariance inflated by 1/w, cross-terms included), so every model
(spots, sensors, effects) runs unchanged on the reweighted residuals and
Jacobian; the final least-squares fit is any solver's (LM, the EKF).

The rule (ROBUST_RULE, stated in result.json):
- d_u^2 = r_u^T C_u^-1 r_u per unit u (C_u its block of the noise covariance,
  so it is chi^2_D under the noise model);
- scale s^2 = median(d_u^2) / median(chi^2_D) over the kept units: for D = 1
  the MAD about zero (1.4826 median |z|; a fit's residual is centred on
  zero), for D > 1 the same on the unit's distance, so a unit whose
  components differ in size (position, rotation) is not judged per value;
- Cauchy weight w_u = 1 / (1 + t_u^2 / (D c^2)) with t_u^2 = d_u^2 / s^2 and
  c = 2.385 (95 % efficiency at the normal distribution). Its influence
  redescends to zero, so a 1e6 m spot weighs nothing;
- the first weights are those of the start (the nominal model: its residual
  is centimetres, a gross outlier metres), then one damped Gauss-Newton step
  and a reweighting per round until no weight changes by more than 1e-3 (at
  most MAX_ROUNDS rounds); near the minimum (no weight changed by more than
  NEWTON_BELOW) a round's step is a damped Newton step on the Cauchy
  objective instead, without joint noise (independent units). Beyond 2
  WARM_POSES poses the rounds start where those on an evenly spread subset
  of WARM_POSES settled (itself started on one a tenth its size, down to
  SMALLEST_RUNG poses), and are Newton's from the first;
- at the end the units with t_u^2 > chi^2_D(1 - 0.01 / N) (N units) are
  candidates. The others, n units of D values fitted with p free parameters,
  leave nu = n D - p residual degrees of freedom: the scale becomes the larger
  of s and sqrt(sum of their d^2 / nu) (a fit absorbs p of the values'
  scatter; real residuals have heavier tails than the MAD assumes), and a
  unit beyond D F_{D,nu}(1 - 0.01 / N) at that scale is rejected (listed;
  redundancy.outlier_limit: F, the scale being estimated; chi^2_D's limit
  with thousands of values). A clean set loses any unit with probability
  1 %, a gross outlier is hundreds of sigma out. With nu < 1 (the rest would
  be fitted exactly, as the reweighting does by down-weighting just enough
  units) nothing tells an outlier from a unit the others cannot predict:
  none is rejected (RobustFit.untestable). If more than MAX_REJECTED of the
  units lie beyond the limit, the model, not the data, is wrong: nothing is
  rejected and RobustFit.overflow says so;
- the final fit is least squares on the others (its covariance and chi^2
  keep their meaning), and each rejection is confirmed there
  (redundancy.deletion_distances): a unit stays out only if its residual,
  against its noise plus the fit's uncertainty where it lies, is beyond the
  same limit at that fit's nu. The reweighted d^2 leaves that uncertainty
  out: negligible with thousands of values, as large as the noise or larger
  with a few to spare (8 clean poses of the 4-DOF arm: 3 of 30 sets lost a
  spot for it; confirmed, none, while a 20 cm error is found in 27 of 30).
  Units within are fitted again and the rest confirmed anew (the rejections
  only shrink).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
# chi^2 quantiles as scipy.stats.chi2 computes them (ppf, isf), without importing scipy.stats (seconds)
from scipy.special import chdtri, gammaincinv

from laser_calib.estimation.lm import LmOptions
from laser_calib.estimation.problem import Fit, Normal, Problem, n_poses, pose_blocks
from laser_calib.estimation.redundancy import (FAMILY_FALSE_REJECTION, deletion_distances, outlier_limit,
                                               unit_covariances)
from laser_calib.measurement.base import MeasurementModel, NoiseModel, Residuals

CAUCHY_C = 2.385
MAX_ROUNDS = 30
WEIGHT_TOL = 1e-3
# A residual below a thousandth of the noise model's sigma (noise-free data)
# has no outliers: the scale is not taken below this, in whitened units.
MIN_SCALE = 1e-3
MAX_REJECTED = 1 / 3  # beyond this fraction of outliers the residual is a model error
WARM_POSES = 20000  # above twice this many poses, the reweighting starts on an evenly spread subset of this size
SMALLEST_RUNG = 2000  # ... and that subset starts on one a tenth its size, down to this many poses
NEWTON_BELOW = 0.05  # after a round that changed no weight by more than this, Newton steps (near the minimum)
ROBUST_RULE = ("IRLS with the Cauchy loss (c = 2.385) on each spot's (point's, pose's) whitened residual, "
               "scale s^2 = median(d^2) / median(chi^2_D) (the MAD about zero for D = 1), weights from the "
               "nominal model first; at convergence the spots beyond chi^2_D(1 - 0.01 / N) of N spots at s are "
               "candidates, and a spot with d^2 / s'^2 > D F_{D,nu}(1 - 0.01 / N) is rejected (s'^2 the larger of "
               "s^2 and the others' sum of d^2 / nu, nu = their values less the free parameters; none when nu < 1), "
               "the final fit is least squares on the rest, and a rejected spot whose residual there, against its "
               "noise plus the fit's uncertainty at it, is within D F_{D,nu'}(1 - 0.01 / N) (nu' that fit's residual "
               "degrees of freedom) is fitted again")

# Said with the rejections when the noise model has no joint-reading noise: joints that have some scatter a
# measurement in proportion to its lever (a spot's beam, a marker's arm), and the longest levers' then lie
# beyond the limit (10,000 clean poses, joint noise 0.06 deg not given: 31 of 20,000 spots; given: none).
NO_JOINT_NOISE = ("; the noise model has no joint-reading noise: if the joints have some, measurements on long "
                  "levers scatter more and can be rejected for it (give their sigma)")

# (problem, start x, its normal equations there or None) -> fit: LM, the EKF, ...
Solver = Callable[[Problem, np.ndarray, Normal | None], Fit]


@dataclass(frozen=True)
class WeightedNoise(NoiseModel):
    """A noise model with a weight per unit (P,C) in [0, 1]: unit u's own
    covariance block is inflated by 1/w_u (its cross-covariances with the
    pose's other units kept), so w_u = 0 is exactly leaving it out. Without
    joint noise this is sqrt(w_u) on its whitener columns. dataclasses.replace
    keeps the weights (the EKF replaces sigma)."""

    weights: np.ndarray | None = None

    def for_poses(self, index: slice) -> "WeightedNoise":
        return self if self.weights is None else replace(self, weights=self.weights[index])

    def whitener(self, residuals: Residuals) -> np.ndarray:
        if self.weights is None:
            return super().whitener(residuals)
        kept = self.weights > 0
        dims = residuals.r.shape[2]
        weight = np.repeat(np.where(kept, self.weights, 1.0), dims, axis=1)        # (P, CD)
        left_out = np.repeat(kept, dims, axis=1)[:, None, :]                        # zero columns: no residual
        base = super().whitener(replace(residuals, valid=residuals.valid & kept))
        if not (self.joint_noise and residuals.jac_q is not None):  # the base whitener is diagonal
            np.einsum("pii->pi", base)[...] *= np.sqrt(weight) * left_out[:, 0]
            return base
        factor = np.linalg.inv(base)
        covariance = factor @ factor.transpose(0, 2, 1)                             # (P, CD, CD)
        own = np.kron(np.eye(residuals.r.shape[1]), np.ones((dims, dims)))          # the units' blocks
        covariance = covariance + covariance * own * (1.0 / weight - 1.0)[:, :, None]
        return np.linalg.inv(np.linalg.cholesky(covariance)) * left_out


@dataclass(frozen=True)
class RobustFit:
    """fit: the final least-squares fit without the rejected units (None when
    none is rejected: the caller's own fit is that least squares); rejected
    (P,C) bool; weights (P,C) of the last round; scale s (whitened units);
    rounds of reweighting; converged: the weights settled; overflow: the
    number of units beyond the limit when it exceeded MAX_REJECTED (none
    rejected), else 0; untestable: likewise the units beyond it at the MAD
    scale when the others leave no residual value to test them with."""

    fit: Fit | None
    rejected: np.ndarray
    weights: np.ndarray
    scale: float
    rounds: int
    converged: bool
    overflow: int = 0
    untestable: int = 0


def unit_distances(res: Residuals, noise: NoiseModel) -> np.ndarray:
    """Squared Mahalanobis distance d^2 (P,C) of each unit against its own block of the noise covariance (so one
    outlier does not colour its pose's other unit). Invalid units: 0."""
    if not noise.joint_noise and type(noise) is NoiseModel:  # C_u = sigma^2 I: no factor to form
        return np.where(res.valid, (res.r ** 2).sum(axis=2) / noise.sigma ** 2, 0.0)
    chol = np.linalg.cholesky(unit_covariances(res, noise))
    z = np.linalg.solve(chol, res.r[..., None])[..., 0]
    return np.where(res.valid, (z ** 2).sum(axis=2), 0.0)


def distances_at(model: MeasurementModel, noise: NoiseModel, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """unit_distances (P,C) at x, the valid units (P,C) and the values per unit D, block by block of poses
    (problem.pose_blocks): memory does not grow with the poses beyond these (P,C) arrays. Only joint noise
    needs the Jacobian (its whitener); without it the model runs without."""
    joint = noise.joint_noise
    d2, valid = [], []
    for index, block in pose_blocks(model):
        res = block.residuals(x, joint)
        d2.append(unit_distances(res, noise.for_poses(index)))
        valid.append(res.valid)
    return np.concatenate(d2), np.concatenate(valid), res.r.shape[2]


def _cauchy_a(scale: float, dims: int) -> float:
    """a = s^2 D c^2: the Cauchy weight is 1 / (1 + d^2 / a)."""
    return scale ** 2 * dims * CAUCHY_C ** 2


def cauchy_weights(d2: np.ndarray, scale: float, dims: int) -> np.ndarray:
    return 1.0 / (1.0 + d2 / _cauchy_a(scale, dims))


def cauchy_cost(d2: np.ndarray, use: np.ndarray, scale: float, dims: int) -> float:
    """The Cauchy objective sum_u (a/2) log(1 + d_u^2 / a) over the units in use (P,C)."""
    a = _cauchy_a(scale, dims)
    return float(0.5 * a * np.log1p(d2[use] / a).sum())


def mad_scale(d2: np.ndarray, use: np.ndarray, dims: int) -> float:
    """sqrt(median d^2 / median chi^2_D) over the units in ``use`` (P,C), at least MIN_SCALE."""
    values = d2[use]
    scale = float(np.sqrt(np.median(values) / (2 * gammaincinv(dims / 2, 0.5)))) if values.size else 1.0
    return max(scale, MIN_SCALE)


def robust_fit(model: MeasurementModel, noise: NoiseModel, free: np.ndarray, prior_sigma: np.ndarray | None,
               x0: np.ndarray, solve: Solver, excluded: np.ndarray | None = None, start: Residuals | None = None,
               options: LmOptions = LmOptions()) -> RobustFit:
    """IRLS (module docstring), then the final least-squares fit by any solver
    solve(problem, x_start, normal equations there or None) -> Fit. excluded (P,C): units already refused
    (impossible measurements); start: the model's residuals at x0, when the
    caller has them; options: the damping, step tolerance and progress of the
    IRLS steps."""
    x = np.asarray(x0, float)
    if start is not None and not noise.joint_noise:
        d2, valid, dims = unit_distances(start, noise), start.valid, start.r.shape[2]
    else:
        d2, valid, dims = distances_at(model, noise, x)
    excluded = np.zeros(valid.shape, bool) if excluded is None else excluded
    total = n_poses(model)
    near = False  # x is a minimum of the rounds on a subset: Newton's from the first
    if total is not None and total > 2 * WARM_POSES:
        # From nominal the weights settle in a dozen rounds; on an evenly spread
        # subset they settle where all poses would put them, within its noise, so
        # the rounds on all poses start there and need only the last few. The
        # subset itself starts where one a tenth its size settled.
        for size in _rungs():
            every = slice(None, None, -(-total // size))
            rung = model.subset(every)
            x = _irls(rung, noise, free, prior_sigma, excluded[every], x,
                      distances_at(rung, noise, x)[0] if near else d2[every], valid[every], dims, options,
                      f"robust on 1 in {every.step} poses", near, final=False).x
            near = True
        d2 = distances_at(model, noise, x)[0]
    state = _irls(model, noise, free, prior_sigma, excluded, x, d2, valid, dims, options, "robust", near)
    use, d2, scale = valid & ~excluded, state.d2, state.scale
    units = max(int(use.sum()), 1)
    candidates = use & (d2 / scale ** 2 > chdtri(dims, FAMILY_FALSE_REJECTION / units))
    inliers = use & ~candidates
    # the residual degrees of freedom of the units that scale the test: their values less the
    # parameters fitted to them (counted in full with a prior too: fewer rejections, never more)
    dof = dims * int(inliers.sum()) - int(np.count_nonzero(free))
    untestable = int(candidates.sum()) if dof < 1 else 0
    if untestable:  # the rest would be fitted exactly: no scale to judge the candidates by
        rejected = np.zeros_like(use)
    else:  # judged by the inliers' own residual variance (heavier tails than the MAD assumes)
        scale = max(scale, float(np.sqrt(d2[inliers].sum() / dof)))
        rejected = use & (d2 / scale ** 2 > outlier_limit(dims, dof, units))
    overflow = int(rejected.sum()) if rejected.sum() > MAX_REJECTED * use.sum() else 0
    if overflow:
        rejected[:] = False
    # with nothing rejected the caller fits the same units from its own start (robust or not, one result)
    final = None
    if rejected.any():
        problem = Problem(model, noise, free, prior_sigma, excluded | rejected)
        start_x, start = state.x, None
        if state.least_squares is not None and total is not None:
            # the last Newton round's pass also summed the least squares: it starts there
            start_x, d2_there, normal = state.least_squares
            start = _without(problem, normal, start_x, d2_there, rejected)
        final = solve(problem, start_x, start)
        # confirmed at the fit without them (module docstring); those within are fitted again
        while True:
            t2, left = deletion_distances(problem, final, rejected)
            confirmed = rejected & (t2 > outlier_limit(dims, left, units)) if left >= 1 else np.zeros_like(rejected)
            if np.array_equal(confirmed, rejected):
                break
            rejected = confirmed
            if not rejected.any():
                final = None
                break
            problem = Problem(model, noise, free, prior_sigma, excluded | rejected)
            final = solve(problem, final.x, None)
    return RobustFit(final, rejected, state.weights, scale, state.rounds, state.converged, overflow, untestable)


def _without(problem: Problem, normal: Normal, x: np.ndarray, d2: np.ndarray, rejected: np.ndarray) -> Normal:
    """problem's normal equations at x from ``normal``, those of the same least
    squares with the units ``rejected`` (P,C) still in: their rows leave the sums
    (the model evaluated on their poses only), and the cost is summed anew from
    the unit distances d2 (P,C) at x (a gross outlier's square would swamp the
    difference). Independent units only (no joint noise)."""
    poses = np.flatnonzero(rejected.any(axis=1))
    theirs = Problem(problem.model.subset(poses), problem.noise, problem.free,
                     excluded=~rejected[poses]).normal_equations(x)
    whitener = normal.whitener.copy()
    dims = whitener.shape[1] // rejected.shape[1]
    np.einsum("pii->pi", whitener)[np.repeat(rejected, dims, axis=1)] = 1.0   # left out: unit variance
    return replace(normal, information=normal.information - theirs.information,
                   gradient=normal.gradient - theirs.gradient,
                   cost=problem.prior_cost(x) + 0.5 * float(d2[~problem.excluded].sum()), whitener=whitener,
                   n_values=normal.n_values - theirs.n_values, also=None)


def _rungs() -> list[int]:
    """The subsets' sizes, smallest first: WARM_POSES and a tenth of each down to SMALLEST_RUNG."""
    sizes = [WARM_POSES]
    while sizes[0] // 10 >= SMALLEST_RUNG:
        sizes.insert(0, sizes[0] // 10)
    return sizes


@dataclass(frozen=True)
class _Irls:
    """Where the reweighting stopped: x (n,), d2 (P,C) there, its MAD scale and
    weights (P,C), the rounds taken and whether the weights settled;
    least_squares: (x, d2 there, the least-squares normal equations there) of
    the last Newton round's pass, None without one."""

    x: np.ndarray
    d2: np.ndarray
    scale: float
    weights: np.ndarray
    rounds: int
    converged: bool
    least_squares: tuple[np.ndarray, np.ndarray, Normal] | None = None


def _irls(model: MeasurementModel, noise: NoiseModel, free: np.ndarray, prior_sigma: np.ndarray | None,
          excluded: np.ndarray, x: np.ndarray, d2: np.ndarray, valid: np.ndarray, dims: int,
          options: LmOptions, label: str, near: bool = False, final: bool = True) -> _Irls:
    """Reweight from x, where the unit distances are d2 (P,C), until no weight
    changes by more than WEIGHT_TOL (at most MAX_ROUNDS rounds). Without joint
    noise (independent units) the rounds are Newton steps once near the minimum:
    ``near`` from the start, else once a round changed no weight by more than
    NEWTON_BELOW. final: the least squares follow (not a subset's rounds)."""
    independent = not noise.joint_noise
    newton = near and independent
    use = valid & ~excluded
    scale = mad_scale(d2, use, dims)
    weights = np.where(use, cauchy_weights(d2, scale, dims), 0.0)

    def weighted(w: np.ndarray) -> Problem:
        return Problem(model, WeightedNoise(noise.sigma, noise.joint_sigma, w), free, prior_sigma, excluded)

    plain = Problem(model, noise, free, prior_sigma, excluded)
    least_squares = None

    def normal_at(x: np.ndarray, d2: np.ndarray) -> Normal:
        """The weighted normal equations at x; a Newton round's pass sums the least squares too."""
        nonlocal least_squares
        if not (newton and final):
            return problem.normal_equations(x, unit_outer=newton)
        normal = problem.normal_equations(x, unit_outer=True, also=plain)
        least_squares = (x, d2, normal.also)
        return normal

    # One damped Gauss-Newton step per reweighting, each from the last (the
    # classic IRLS iteration, Holland & Welsch 1977), not a full solve per
    # round: a step is kept when it lowers the cost under the current weights,
    # which for the Cauchy loss (concave in d^2) also lowers the robust cost.
    # Its convergence is linear (the weights' change shrinks ~3x a round); near
    # the minimum a Newton step converges quadratically: it adds the loss's
    # curvature to the weighted J^T J. With rho(d2) = (a/2) log(1 + d2/a),
    # a = s^2 D c^2, the Hessian (Gauss-Newton in the residuals) is
    # sum_u w_u J_u^T J_u - (2/a) w_u^2 g_u g_u^T, g_u = J_u^T r_u, and the step
    # is kept when it lowers the Cauchy objective at this scale.
    problem = weighted(weights)
    normal = normal_at(x, d2)
    eye = np.eye(len(normal.gradient))
    damping = options.damping
    converged = False
    rounds = 0
    while rounds < MAX_ROUNDS and not converged:
        curvature = normal.information
        if newton:
            curvature = curvature - 2.0 / _cauchy_a(scale, dims) * normal.unit_outer   # w^2 g g^T: weighted rows
        step = np.linalg.solve(curvature + damping * eye, normal.gradient)
        if np.sqrt(max(step @ normal.information @ step, 0.0)) < options.step_tol:
            converged = True  # x stays, so do its weights
            break
        trial = x.copy()
        trial[problem.free] += step * problem.scales
        cost, trial_d2 = _trial_pass(problem, noise, trial, normal.whitener)
        rise = (not cost <= normal.cost if not newton else
                not (cauchy_cost(trial_d2, use, scale, dims) + problem.prior_cost(trial)
                     <= cauchy_cost(d2, use, scale, dims) + problem.prior_cost(x)))
        if rise:  # a rise, or not finite (a step where the model overflows)
            damping *= 10.0
            continue
        rounds += 1
        x, d2 = trial, trial_d2
        damping = max(damping / 10.0, 1e-12)
        scale = mad_scale(d2, use, dims)
        new = np.where(use, cauchy_weights(d2, scale, dims), 0.0)
        change = float(np.abs(new - weights).max(initial=0.0))
        converged = change < WEIGHT_TOL
        newton = newton or (independent and change < NEWTON_BELOW)
        weights = new
        if options.progress is not None:
            options.progress(rounds, None, f"{label}: weights change {change:.2g} (settled below {WEIGHT_TOL:g})")
        if not converged:
            problem = weighted(weights)
            normal = normal_at(x, d2)
    return _Irls(x, d2, scale, weights, rounds, converged, least_squares)


def _trial_pass(problem: Problem, noise: NoiseModel, x: np.ndarray, whitener: np.ndarray) -> tuple[float, np.ndarray]:
    """At a trial x, in one pass of the model: its cost under the current
    point's (weighted) whitener (P,CD,CD), prior included, and the unit
    distances d^2 (P,C) under its own noise (without the weights). Only joint
    noise needs the Jacobian."""
    joint = noise.joint_noise
    cost = problem.prior_cost(x)
    d2 = []
    for index, block in pose_blocks(problem.model, problem.chunk):
        res = block.residuals(x, joint)
        r, _ = problem.whitened(index, problem.excluding(res, index), whitener[index], jacobian=False)
        cost += 0.5 * float(r @ r)
        d2.append(unit_distances(res, noise.for_poses(index)))
    return cost, np.concatenate(d2)
