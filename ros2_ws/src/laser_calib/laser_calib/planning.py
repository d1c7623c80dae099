"""Pose planning: which N poses to measure so the calibration learns the most.

Criterion: D-optimality on the whitened Fisher information of the identifiable
errors, with the manufacturing tolerance as prior information (Bayesian
D-optimality):

    maximise  log det( I + sum_p G_p^T G_p ),   G_p = W_p J_p S       (4 x k per pose)

J_p (4,n) the spot Jacobian of pose p at the nominal model (both lasers, y
and z), S the parameters' tolerances (10 mm, 1 deg: the identity is the prior
information of errors of that size), and W_p the inverse Cholesky factor of
the pose's full noise covariance

    C_p = spot_sigma^2 I_4 + J_q,p diag(joint_sigma^2) J_q,p^T        (J_q,p = d spots / d q, 4 x N)

so a pose whose long beams amplify the joint disturbance into spot motion is
worth only what it really tells: without this term the design prefers exactly
those poses. Parameters no pose set can separate (the identifiability analysis
on all candidates) are left out of the determinant. The prior keeps the
criterion finite from the first pose and stops the design from spending poses
on directions already known to well within the tolerance; the estimator itself
runs without it.

Search: candidates uniform in the joint limits with both beams on the screen
at least ``margin`` inside its edge on the nominal model (the true spots may
lie ~0.15 m away before calibration); a greedy start by the matrix
determinant lemma, det(M + G^T G) = det(M) det(I + G M^-1 G^T), then Fedorov
exchange passes (swap a chosen pose for a candidate while log det rises).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from laser_calib.estimation.identifiability import STD_FACTOR, analyse
from laser_calib.estimation.lm import ProgressCallback
from laser_calib.estimation.problem import pose_blocks
from laser_calib.model.kinematics import predict, usable
from laser_calib.measurement.base import NoiseModel, robot_scales, whiten
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.io.samples import Samples
from laser_calib.sim.simulation import NoiseSpec

PRIOR = 1.0         # prior information per scaled error: one tolerance (10 mm, 1 deg) standard deviation
IMPROVEMENT = 1e-9  # least rise of log det that counts as an exchange
DRAW_BLOCK = 20000  # candidate readings drawn and checked at a time


@dataclass(frozen=True)
class PlanOptions:
    """n poses; spot_sigma (m) per spot coordinate and joint_sigma (rad) per
    joint reading (defaults: the paper's uniform noise, +-2 mm and +-0.1 deg);
    candidates drawn; margin (m) inside the screen edge; exchange passes; seed."""

    n: int
    spot_sigma: float = NoiseSpec().spot_sigma
    joint_sigma: float = NoiseSpec().joint_sigma
    candidates: int = 3000
    margin: float = 0.10
    passes: int = 4
    seed: int = 0

    def __post_init__(self):
        if self.n < 1:
            raise ValueError(f"the number of poses must be at least 1, got {self.n}")
        if not self.spot_sigma > 0:
            raise ValueError(f"the spot sigma must be a positive number of metres, got {self.spot_sigma}")
        if not (self.joint_sigma >= 0 and self.margin >= 0):
            raise ValueError(f"joint sigma and margin must not be negative, got {self.joint_sigma} and {self.margin}")
        if self.candidates < self.n:
            raise ValueError(f"{self.candidates} candidates cannot give {self.n} distinct poses")


@dataclass(frozen=True)
class Plan:
    """q (n,N) the chosen joint readings, rad; log_det of their information
    (identifiable errors, scaled); free (n_params,) the errors in the criterion;
    determined: how many of those the chosen poses alone determine at the plan's noise, by
    estimate's rule (a std beyond STD_FACTOR tolerance scales is held; the criterion's small
    prior makes log_det finite with fewer poses than errors)."""

    q: np.ndarray
    log_det: float
    free: np.ndarray
    determined: int


def candidate_poses(robot: Robot, count: int, rng: np.random.Generator, margin: float,
                    max_tries: int = 200) -> np.ndarray:
    """(count,N) readings uniform in the joint limits that the arm can take with both beams on
    the screen (kinematics.usable), drawn at most DRAW_BLOCK at a time (bounded memory for
    large pools)."""
    chosen: list[np.ndarray] = []
    found = drawn = 0
    for _ in range(max_tries):
        q = rng.uniform(*robot.pose_range(), (min(max(2 * count, 256), DRAW_BLOCK), robot.n_joints))
        drawn += len(q)
        chosen.append(q[usable(robot, predict(robot, q), margin)])
        found += len(chosen[-1])
        if found >= count:
            return np.concatenate(chosen)[:count]
    raise ValueError(f"found only {found} of {count} poses with both beams {margin} m inside the screen (the arm "
                     f"on its side of it), in "
                     f"{drawn} drawn within the joint limits ({100 * found / drawn:.2g} % hit): ask for fewer "
                     "candidates, lower the margin, or check the joint limits and the screen")


def whitened_jacobians(robot: Robot, q: np.ndarray, spot_sigma: float, joint_sigma: float) -> np.ndarray:
    """(P,4,n) G_p = W_p J_p per pose, in scaled parameters (module docstring)."""
    samples = Samples(np.arange(len(q)), np.arange(len(q), dtype=float), q, np.zeros((len(q), 2, 2)))
    noise = NoiseModel(spot_sigma, joint_sigma)
    g = np.empty((len(q), 4, robot.n_params))
    for index, block in pose_blocks(SpotModel(robot, samples)):
        res = block.residuals(np.zeros(robot.n_params), True)
        g[index] = whiten(res, noise.whitener(res))[1].reshape(-1, 4, robot.n_params)
    return g * robot_scales(robot)


def values_and_determined(robot: Robot, q: np.ndarray) -> tuple[int, int]:
    """(values, errors) of the poses q (P,N) at the nominal model: the spot values whose beams
    meet the screen, and how many errors those values determine (identifiability.analyse, by
    rank as estimate_model's start). An estimate needs more values than errors: as many fit
    exactly, and nothing checks the fit (identifiability.TooFewValues)."""
    g = whitened_jacobians(robot, q, 1e-3, 0.0)
    return int(np.any(g != 0, axis=-1).sum()), int(_identifiable(robot, g).free.sum())


def _identifiable(robot: Robot, g: np.ndarray):
    """identifiability.analyse of the poses' whitened Jacobians g (P,4,n), by rank, from the R factor
    of their stack (its singular values, without the (4P,n) SVD)."""
    return analyse(np.linalg.qr(g.reshape(-1, robot.n_params), mode="r"), np.ones(robot.n_params),
                   robot.param_names)


def _log_det_plus_identity(q: np.ndarray) -> np.ndarray:
    """log det(I + Q) for symmetric positive semi-definite Q (M,4,4), by Cholesky."""
    factor = np.linalg.cholesky(np.eye(q.shape[-1]) + q)
    return 2.0 * np.log(np.diagonal(factor, axis1=-2, axis2=-1)).sum(axis=-1)


def _projections(g: np.ndarray, inverse: np.ndarray) -> np.ndarray:
    """Q_c = G_c M^-1 G_c^T (M,4,4) of every candidate, g (M,4,k): O(M k^2)."""
    h = (g.reshape(-1, g.shape[2]) @ np.linalg.cholesky(inverse)).reshape(g.shape)
    return h @ h.transpose(0, 2, 1)


class _Design:
    """The chosen set's information M (k,k), its inverse, and for the exchange
    Q_c of every candidate kept current by rank-4 updates (Woodbury): adding or
    removing pose b changes Q_c by -/+ U_c S^-1 U_c^T, U_c = G_c M^-1 G_b^T,
    S = I +/- Q_b, at O(M k) per change instead of O(M k^2)."""

    def __init__(self, g: np.ndarray):
        self.g = g
        self.info = PRIOR * np.eye(g.shape[2])
        self.inverse = np.eye(g.shape[2]) / PRIOR
        self.q: np.ndarray | None = None

    def refresh(self) -> None:
        """Q of every candidate from scratch (no drift from the updates)."""
        self.q = _projections(self.g, self.inverse)
        self.gain = _log_det_plus_identity(self.q)
        self.trace = np.trace(self.q, axis1=1, axis2=2)

    def change(self, b: int, sign: float) -> None:
        """Add (sign +1) or remove (-1) candidate b."""
        gb = self.g[b]
        if self.q is not None:
            cross = (self.g.reshape(-1, gb.shape[1]) @ (self.inverse @ gb.T)).reshape(-1, 4, 4)  # U_c
            s = np.eye(4) + sign * self.q[b]
            self.q -= sign * (cross @ np.linalg.inv(s)) @ cross.transpose(0, 2, 1)
            self.gain = _log_det_plus_identity(self.q)
            self.trace = np.trace(self.q, axis1=1, axis2=2)
        self.info = self.info + sign * gb.T @ gb
        self.inverse = np.linalg.inv(self.info)

    def gains(self, index: np.ndarray) -> np.ndarray:
        """log det(I + G_c M^-1 G_c^T) of candidates ``index``, exactly."""
        return _log_det_plus_identity(_projections(self.g[index], self.inverse))


def _lazy_best(design: _Design, bound: np.ndarray, batch: int = 32) -> int:
    """The candidate of largest gain given upper bounds of every gain (-inf for
    those not eligible; updated in place with the exact gains it computes):
    exact gains of the best-bounded few, twice as many each round, until one
    beats every bound left (log det is submodular, so a gain computed earlier,
    at less information, bounds it from above: lazy greedy, Minoux)."""
    eligible = np.isfinite(bound)
    while True:
        count = min(batch, int(eligible.sum()))
        top = np.argpartition(-bound, count - 1)[:count]
        bound[top] = design.gains(top)
        best = int(top[np.argmax(bound[top])])
        rest = np.where(eligible, bound, -np.inf)
        rest[top] = -np.inf
        if bound[best] >= rest.max():
            return best
        eligible[top] = False
        batch *= 2


def d_optimal(g: np.ndarray, n: int, passes: int,
              progress: ProgressCallback | None = None) -> tuple[np.ndarray, float]:
    """Indices (n,) of the candidates g (M,4,k) maximising log det(PRIOR I + sum G^T G).

    Greedy by lazy evaluation (_lazy_best), then Fedorov exchange passes: per
    slot b, the gain of candidate c against the set without b is bounded by
    gain_c + tr(Q_c) l / (1 - l), l = the largest eigenvalue of Q_b (Woodbury,
    log det(A + E) <= log det A + tr E), so only candidates whose bound beats
    b's own gain are evaluated exactly. Cost: O(M k^2) per pass and O(M k) per
    swap, beside the few exact evaluations.
    """
    design = _Design(g)
    total = n * (1 + passes)
    bound = _log_det_plus_identity(g @ g.transpose(0, 2, 1) / PRIOR)
    chosen: list[int] = []
    for step in range(n):
        bound[chosen] = -np.inf
        best = _lazy_best(design, bound)
        chosen.append(best)
        design.change(best, +1.0)
        if progress is not None:
            progress(step + 1, total, "greedy")
    for done_passes in range(passes):
        design.refresh()
        swapped = 0
        for slot in range(n):
            current = chosen[slot]
            own_q = design.q[current]
            largest = np.linalg.eigvalsh(own_q)[-1]
            own = -np.linalg.slogdet(np.eye(4) - own_q)[1]
            bound = design.gain + design.trace * largest / (1.0 - largest)
            bound[chosen] = -np.inf
            candidates = np.flatnonzero(bound > own + IMPROVEMENT)
            if len(candidates):
                best, value = _best_without(design, current, candidates)
                if value > own + IMPROVEMENT:
                    design.change(current, -1.0)
                    design.change(best, +1.0)
                    chosen[slot] = best
                    swapped += 1
            if progress is not None:
                progress(n * (1 + done_passes) + slot + 1, total, f"exchange pass {done_passes + 1}: {swapped} swaps")
        if not swapped:
            break
    if progress is not None:
        progress(total, total, "done")
    return np.array(chosen), float(np.linalg.slogdet(design.info)[1])


def _best_without(design: _Design, current: int, candidates: np.ndarray) -> tuple[int, float]:
    """The best of ``candidates`` against the set without ``current``, exactly, and its gain."""
    reduced = np.linalg.inv(design.info - design.g[current].T @ design.g[current])
    gain = _log_det_plus_identity(_projections(design.g[candidates], reduced))
    k = int(np.argmax(gain))
    return int(candidates[k]), float(gain[k])


class NotPlannable(ValueError):
    """A robot without joints or the two-laser module: the planner knows why, a command the file."""


def plan(robot: Robot, options: PlanOptions, progress: ProgressCallback | None = None) -> Plan:
    """N poses maximising the D-criterion of the whitened information (module docstring)."""
    if robot.n_joints == 0 or len(robot.lasers) != 2:
        raise NotPlannable("pose planning needs a robot with joints and the two-laser module ('slm:' and 'lasers:')")
    rng = np.random.default_rng(options.seed)
    q = candidate_poses(robot, options.candidates, rng, options.margin)
    g = whitened_jacobians(robot, q, options.spot_sigma, options.joint_sigma)
    ident = _identifiable(robot, g)
    index, log_det = d_optimal(np.ascontiguousarray(g[:, :, ident.free]), options.n, options.passes, progress)
    # estimate's rule at the plan's noise: by rank alone a joint of +-0.002 rad 'determined' 33 errors,
    # of which estimate and identify then held 4 for that noise
    chosen = analyse(g[index].reshape(-1, robot.n_params), np.ones(robot.n_params), robot.param_names, ~ident.free,
                     std_factor=STD_FACTOR)   # g is in scaled parameters already
    return Plan(q[index], log_det, ident.free, int(chosen.free.sum()))
