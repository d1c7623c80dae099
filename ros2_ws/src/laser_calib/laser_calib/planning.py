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

from laser_calib.estimation.identifiability import analyse
from laser_calib.model.kinematics import predict
from laser_calib.measurement.base import NoiseModel, geometric_scales, whiten
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.io.samples import Samples
from laser_calib.sim.simulation import NoiseSpec

PRIOR = 1.0         # prior information per scaled error: one tolerance (10 mm, 1 deg) standard deviation
IMPROVEMENT = 1e-9  # least rise of log det that counts as an exchange


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
    (identifiable errors, scaled); free (4N+5,) the errors in the criterion."""

    q: np.ndarray
    log_det: float
    free: np.ndarray


def candidate_poses(robot: Robot, count: int, rng: np.random.Generator, margin: float,
                    max_tries: int = 200) -> np.ndarray:
    """(count,N) readings uniform in the joint limits with both beams on the screen."""
    chosen: list[np.ndarray] = []
    for _ in range(max_tries):
        q = rng.uniform(robot.q_min, robot.q_max, (max(2 * count, 256), robot.n_joints))
        p = predict(robot, q)
        inside = ((np.abs(p.spots[..., 0]) <= robot.screen.half_y - margin)
                  & (np.abs(p.spots[..., 1]) <= robot.screen.half_z - margin))
        chosen.extend(q[(p.hit & inside).all(axis=1)])
        if len(chosen) >= count:
            return np.array(chosen[:count])
    raise ValueError(f"found only {len(chosen)} of {count} poses with both beams {margin} m inside the screen; "
                     "lower the margin or check the joint limits")


def whitened_jacobians(robot: Robot, q: np.ndarray, spot_sigma: float, joint_sigma: float) -> np.ndarray:
    """(P,4,n) G_p = W_p J_p per pose, in scaled parameters (module docstring)."""
    samples = Samples(np.arange(len(q)), np.arange(len(q), dtype=float), q, np.zeros((len(q), 2, 2)))
    res = SpotModel(robot, samples).residuals(np.zeros(robot.n_params), True)
    _, jac = whiten(res, NoiseModel(spot_sigma, joint_sigma).whitener(res))
    return jac.reshape(len(q), -1, robot.n_params) * geometric_scales(robot.n_joints)


def _gains(g: np.ndarray, inverse: np.ndarray) -> np.ndarray:
    """log det(I + G M^-1 G^T) for every candidate, g (M,4,k): the rise of log det M."""
    inner = np.eye(g.shape[1]) + (g @ inverse) @ g.transpose(0, 2, 1)
    return np.linalg.slogdet(inner)[1]


def d_optimal(g: np.ndarray, n: int, passes: int) -> tuple[np.ndarray, float]:
    """Indices (n,) of the candidates g (M,4,k) maximising log det(PRIOR I + sum G^T G)."""
    k = g.shape[2]
    info = PRIOR * np.eye(k)
    chosen: list[int] = []
    for _ in range(n):
        gain = _gains(g, np.linalg.inv(info))
        gain[chosen] = -np.inf
        best = int(np.argmax(gain))
        chosen.append(best)
        info += g[best].T @ g[best]
    for _ in range(passes):
        swapped = False
        for slot in range(n):
            current = chosen[slot]
            reduced = info - g[current].T @ g[current]
            gain = _gains(g, np.linalg.inv(reduced))
            own = gain[current]
            gain[chosen] = -np.inf
            best = int(np.argmax(gain))
            if gain[best] > own + IMPROVEMENT:
                chosen[slot] = best
                info = reduced + g[best].T @ g[best]
                swapped = True
        if not swapped:
            break
    return np.array(chosen), float(np.linalg.slogdet(info)[1])


def plan(robot: Robot, options: PlanOptions) -> Plan:
    """N poses maximising the D-criterion of the whitened information (module docstring)."""
    if robot.n_joints == 0 or len(robot.lasers) != 2:
        raise ValueError("pose planning needs a robot with joints and the two-laser module")
    rng = np.random.default_rng(options.seed)
    q = candidate_poses(robot, options.candidates, rng, options.margin)
    g = whitened_jacobians(robot, q, options.spot_sigma, options.joint_sigma)
    ident = analyse(g.reshape(-1, robot.n_params), np.ones(robot.n_params), robot.param_names)
    index, log_det = d_optimal(g[:, :, ident.free], options.n, options.passes)
    return Plan(q[index], log_det, ident.free)
