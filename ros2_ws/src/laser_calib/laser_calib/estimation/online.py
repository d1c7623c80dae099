"""The EKF run online, one synchronized pose at a time (the ROS estimator node).

Each pose is one EKF step (paper eq. 13-15) with that pose's two spots as the
measurement: x_{k+1|k} = x_k, P_{k+1|k} = P_k + Q, then the update, with
R = the pose's spot noise plus its joint disturbance through the joint Jacobian.
The errors are constants, so Q defaults to 0; P0 is the manufacturing
tolerance (10 mm, 1 deg by default), which makes the filter's estimate after
all poses approximate the offline estimate with the same prior (``--prior``):
the same posterior, but linearised once per pose instead of iterated.
"""

from __future__ import annotations

import bisect

import numpy as np

from laser_calib.estimation.ekf import information_update
from laser_calib.estimation.estimate import EstimateOptions, prior_sigmas
from laser_calib.estimation.identifiability import AMPLIFY, analyse
from laser_calib.estimation.problem import whitened_factor
from laser_calib.measurement.base import NoiseModel, whiten
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.io.samples import Samples

DEFAULT_SPOT_SIGMA = 0.001


class OnlineEkf:
    """Sequential EKF over the geometric errors.

    update(q (N,), spots (2,2) with NaN for an unseen laser); errors, std (n,);
    identifiable (n,) from the poses seen so far; samples() the accumulated poses.
    """

    def __init__(self, robot: Robot, options: EstimateOptions = EstimateOptions(), q_noise: float = 0.0):
        self.robot = robot
        # a running filter has no residual to estimate either sigma from: what is not given is the default
        self.noise = NoiseModel(options.spot_sigma or DEFAULT_SPOT_SIGMA, options.joint_sigma or 0.0)
        model = SpotModel(robot, Samples(np.zeros(0, int), np.zeros(0), np.zeros((0, robot.n_joints)),
                                         np.zeros((0, 2, 2))))
        prior = prior_sigmas(model, robot.n_params, EstimateOptions(prior=True, prior_length=options.prior_length,
                                                                     prior_angle=options.prior_angle))
        self.p0 = np.diag(prior ** 2)
        self.q_noise = q_noise
        self.reset()

    def reset(self) -> None:
        n = self.robot.n_params
        self.x = np.zeros(n)
        self.covariance = self.p0.copy()
        self.q = np.eye(n) * self.q_noise
        self._q: list[np.ndarray] = []
        self._spots: list[np.ndarray] = []
        self._stamps: list[float] = []  # of the poses given to take(), in order

    @property
    def errors(self) -> np.ndarray:
        return self.x.copy()

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))

    @property
    def n_samples(self) -> int:
        return len(self._q)

    def samples(self) -> Samples:
        n = len(self._q)
        return Samples(np.arange(n), np.arange(n, dtype=float), np.array(self._q).reshape(n, self.robot.n_joints),
                       np.array(self._spots).reshape(n, 2, 2))

    @property
    def identifiable(self) -> np.ndarray:
        """Which errors the poses so far determine (all False before enough poses)."""
        n = self.robot.n_params
        if 4 * self.n_samples < n:
            return np.zeros(n, bool)
        model = SpotModel(self.robot, self.samples())
        factor, _ = whitened_factor(model, self.noise, self.errors)
        return analyse(factor, model.scales, model.names, amplify=AMPLIFY).free

    def take(self, stamp: float, q: np.ndarray, spots: np.ndarray) -> None:
        """update() with the pose measured at ``stamp`` (s), in stamp order: the filter's
        result depends on the order, and a pose can be delivered after a later one (a
        subscriber matched late gets a latched history while the live samples flow), so
        such a pose is put in its place and the poses are filtered again from the prior."""
        at = bisect.bisect_right(self._stamps, stamp)
        if at == len(self._stamps):
            self._stamps.append(stamp)
            self.update(q, spots)
            return
        poses = list(zip(self._stamps, self._q, self._spots))
        poses.insert(at, (stamp, np.asarray(q, dtype=float).ravel(), np.asarray(spots, dtype=float).reshape(2, 2)))
        self.reset()
        for stamp_k, q_k, spots_k in poses:
            self._stamps.append(stamp_k)
            self.update(q_k, spots_k)

    def update(self, q: np.ndarray, spots: np.ndarray) -> None:
        q = np.asarray(q, dtype=float).reshape(1, self.robot.n_joints)
        spots = np.asarray(spots, dtype=float).reshape(1, 2, 2)
        if not np.isfinite(q).all():
            raise ValueError("joint positions must be finite")
        self._q.append(q[0])
        self._spots.append(spots[0])
        pose = Samples(np.zeros(1, int), np.zeros(1), q, spots)
        res = SpotModel(self.robot, pose).residuals(self.x)
        if not res.valid.any():
            return  # nothing measured (or the beam misses the screen): the pose only joins the record
        # Whitened measurement: z = 0, h(x) = -r(x), R = I; an unseen spot's rows are zero.
        r_white, jac_white = whiten(res, self.noise.whitener(res))
        self.covariance = self.covariance + self.q                     # eq. 13
        self.x, self.covariance = information_update(self.x, self.covariance, jac_white.T @ jac_white,
                                                     jac_white.T @ r_white)   # eq. 14-15
