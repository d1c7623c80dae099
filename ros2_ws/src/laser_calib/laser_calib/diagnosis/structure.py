"""Residual analysis: does what the model leaves follow anything the data holds?

Covariates (conventions.md: everything a samples file carries, plus what the
robot model derives from it):

    pose level: q_i, move_i (sign of the last move of joint i, from the row
                order, base.move_directions), torque_i (gravity torque,
                joint.gravity_torques), stamp, every extra column, every
                text column (labels: an operator, a fixture) as categories
    spot level: spot_y, spot_z (where the model puts the spot: the measured
                position holds the residual's own noise, and one pose measured
                40 times "followed spot_z" at p = 1e-26), incidence (angle
                between beam and screen normal, deg), laser

The pose level serves every measurement model (it needs only the readings and
the Jacobians); the spot level is the laser data's measurement level, other
measurement models supply their own (diagnosis.sensor_data: the residual
components against the measured position in the sensor frame).

The raw spot residual of a joint or length error changes sign from pose to
pose with the kinematics, so a binned mean of raw residuals hides it.
Responses therefore project each pose's residual onto the direction a given
error would move it, in whitened units (the noise model's metric):

    apparent error of x_j at pose p:  e_jp = (W g)^T (W r) / |W g|^2,  weight |W g|^2

with g = d spots / d x_j (4,) and W the pose's whitener; under the noise model
e_jp has variance 1 / weight. Responses: the apparent error of each joint
(against the pose covariates), of each length (against stamp and the extra
columns), and at spot level the residual y, z and the apparent screen height
h = t.r / |t|^2, t = (z_y, z_z)/z_x (against the spot covariates).

Test: weighted one-way analysis of variance of the response over bins of the
covariate (quantile bins; the values themselves when they are few, e.g. the
move signs; a text column's categories, when 2 to MAX_BINS):
F = [sum_b W_b (m_b - m)^2 / (B-1)] / [sum w (e - m_b)^2 / (n-B)],
F(B-1, n-B) under "no dependence"; the within-bin scatter estimates the noise,
so the test does not need the noise level. p-values are Bonferroni-adjusted
over every test made; eta^2 = between / total sum of squares says how much of
the residual the covariate's bin means explain.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Mapping, Protocol

import numpy as np
from scipy import stats

from laser_calib.measurement.base import NoiseModel, Residuals
from laser_calib.model.robot import Robot
from laser_calib.io.samples import Samples
from laser_calib.effects.base import move_directions
from laser_calib.effects.joint import gravity_torques

POSE, SPOT_LEVEL = "pose", "spot"
MAX_BINS = 8
POSES_PER_BIN = 10


class Readings(Protocol):
    """What the pose-level covariates need of a samples set (spot or sensor)."""

    q: np.ndarray                    # (P,N) rad
    stamp: np.ndarray                # (P,) s
    extra: Mapping[str, np.ndarray]  # name -> (P,)
    labels: Mapping[str, np.ndarray]  # name -> (P,) str


@dataclass(frozen=True)
class Series:
    """A covariate or response: values (P,) at pose level or (P,L) at spot level;
    weights (same shape, 0 where missing) for responses; unit and display factor;
    joint (0-based) for what belongs to one joint; length marks the responses of
    a length; own_joint_only a covariate tested only against its joint's response;
    categorical a text column's codes 0..K-1, each value its own bin."""

    name: str
    values: np.ndarray
    level: str
    unit: str
    factor: float = 1.0
    weights: np.ndarray | None = None
    joint: int | None = None
    length: bool = False
    own_joint_only: bool = False
    categorical: bool = False


def joined(parts: list[list[Series]]) -> list[Series]:
    """The series of all poses from those of consecutive blocks of poses (the same series in each)."""
    if len(parts) == 1:
        return parts[0]
    return [replace(first, values=np.concatenate([p[i].values for p in parts]),
                    weights=None if first.weights is None else np.concatenate([p[i].weights for p in parts]))
            for i, first in enumerate(parts[0])]


@dataclass(frozen=True)
class Test:
    """One response against one covariate: the F test and the binned means
    (centres, means, standard errors in display units) for plots."""

    response: str
    covariate: str
    f: float
    dof: tuple[int, int]
    p: float
    p_adjusted: float
    eta2: float
    centres: np.ndarray
    means: np.ndarray
    errors: np.ndarray
    response_unit: str
    covariate_unit: str

    def sentence(self) -> str:
        spread = float(np.ptp(self.means)) if self.means.size else 0.0
        return (f"{self.response} follows {self.covariate}: bin means span {spread:.3g} {self.response_unit} "
                f"(F = {self.f:.3g} on {self.dof[0]}, {self.dof[1]} dof, p = {self.p_adjusted:.2g} "
                f"Bonferroni-adjusted, eta^2 = {self.eta2:.2f})")


def pose_covariates(robot: Robot, samples: Readings) -> list[Series]:
    """The pose-level covariates of any samples with readings q (P,N), stamp (P,)
    and extra columns: q_i, move_i, torque_i, stamp, every extra column."""
    out = []
    q = samples.q
    moves = move_directions(q)
    torques = gravity_torques(robot, q)
    for i in range(robot.n_joints):
        out.append(Series(f"q{i + 1}", q[:, i], POSE, "deg", np.degrees(1.0), joint=i))
        out.append(Series(f"move{i + 1}", moves[:, i], POSE, "sign", joint=i))
        out.append(Series(f"torque{i + 1}", torques[:, i], POSE, "m (per unit weight)", joint=i,
                          own_joint_only=True))
    out.append(Series("stamp", samples.stamp, POSE, "s"))
    out += [Series(name, values, POSE, "") for name, values in samples.extra.items()]
    for name, text in samples.labels.items():
        categories, codes = np.unique(text, return_inverse=True)
        if 2 <= len(categories) <= MAX_BINS:  # one label per pose (a time stamp as text) tells nothing
            out.append(Series(name, codes.astype(float), POSE, "category", categorical=True))
    return out


def spot_covariates(samples: Samples, predicted: np.ndarray, beams: np.ndarray) -> list[Series]:
    """The spot-level covariates; predicted (P,L,2) spots and beams (P,L,3) of the model."""
    spots = np.where(samples.seen[..., None], predicted, np.nan)
    out = [Series("spot_y", spots[..., 0], SPOT_LEVEL, "mm", 1e3),
           Series("spot_z", spots[..., 1], SPOT_LEVEL, "mm", 1e3)]
    with np.errstate(invalid="ignore"):
        incidence = np.degrees(np.arccos(np.clip(np.abs(beams[..., 0]), 0.0, 1.0)))
    out.append(Series("incidence", incidence, SPOT_LEVEL, "deg"))
    out.append(Series("laser", np.broadcast_to(np.arange(1, spots.shape[1] + 1), spots.shape[:2]).astype(float),
                      SPOT_LEVEL, ""))
    return out


def _apparent(res: Residuals, whitener: np.ndarray, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Apparent errors (P,m) and weights (P,m) of m Jacobian directions (P,C,D,m)."""
    n_poses = res.r.shape[0]
    white_r = np.einsum("pij,pj->pi", whitener, res.r.reshape(n_poses, -1))
    white_g = np.einsum("pij,pjm->pim", whitener, columns.reshape(n_poses, -1, columns.shape[-1]))
    weight = (white_g ** 2).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        value = np.einsum("pim,pi->pm", white_g, white_r) / weight
    return np.nan_to_num(value), weight


def pose_responses(robot: Robot, res: Residuals, noise: NoiseModel) -> list[Series]:
    """The pose-level responses of a fit's residuals (res with jac and jac_q at
    the fit, the D-H errors first in jac): the apparent error of each joint and
    of each length, for any measurement model."""
    whitener = noise.whitener(res)
    out = []
    joint_e, joint_w = _apparent(res, whitener, res.jac_q)
    for i in range(robot.n_joints):
        out.append(Series(f"apparent error of joint {i + 1}", joint_e[:, i], POSE, "deg", np.degrees(1.0),
                          joint_w[:, i], joint=i))
    lengths = np.flatnonzero(robot.param_kinds() == "length")
    length_e, length_w = _apparent(res, whitener, res.jac[..., lengths])
    for k, j in enumerate(lengths):
        if length_w[:, k].max() > 0:
            out.append(Series(f"apparent error of {robot.param_names[j]}", length_e[:, k], POSE, "mm", 1e3,
                              length_w[:, k], length=True))
    return out


def value_variance(res: Residuals, noise: NoiseModel) -> np.ndarray:
    """(P,C,D) variance of each measured value: the diagonal of the pose
    covariance sigma^2 I + joint^2 G G^T (G = jac_q)."""
    joint_sigma = np.broadcast_to(np.asarray(noise.joint_sigma, float), (res.jac_q.shape[-1],))
    return noise.sigma ** 2 + np.einsum("pcdn,n->pcd", res.jac_q ** 2, joint_sigma ** 2)


def spot_responses(res: Residuals, noise: NoiseModel, beams: np.ndarray) -> list[Series]:
    """The spot-level responses: residual y, z (each weighted by its own
    variance) and the apparent screen height."""
    variance = value_variance(res, noise)
    valid = res.valid
    out = [Series(f"residual {axis}", res.r[..., d], SPOT_LEVEL, "mm", 1e3,
                  np.where(valid, 1.0 / variance[..., d], 0.0)) for d, axis in enumerate("yz")]
    with np.errstate(invalid="ignore", divide="ignore"):
        t = beams[..., 1:] / beams[..., :1]
        t2 = (t ** 2).sum(axis=-1)
        height = np.nan_to_num((t * res.r).sum(axis=-1) / t2)
        weight = np.where(valid & (t2 > 0), np.nan_to_num(t2 / variance.mean(axis=-1)), 0.0)
    out.append(Series("apparent screen height", height, SPOT_LEVEL, "mm", 1e3, weight))
    return out


def _pairs(responses_: list[Series], covariates_: list[Series]) -> list[tuple[Series, Series]]:
    """Which response is tested against which covariate (module docstring)."""
    pose_covariates = [c for c in covariates_ if c.level == POSE]
    time_like = [c for c in pose_covariates if c.joint is None]
    spot_covariates = [c for c in covariates_ if c.level == SPOT_LEVEL]
    pairs = []
    for r in responses_:
        if r.joint is not None:
            # A joint's gravity torque only against that joint (it is a mixture of the angles).
            pairs += [(r, c) for c in pose_covariates if not c.own_joint_only or c.joint == r.joint]
        elif r.length:
            pairs += [(r, c) for c in time_like]
        else:
            pairs += [(r, c) for c in spot_covariates]
    return pairs


def _bins(values: np.ndarray) -> np.ndarray:
    """Bin index per value: the distinct values when few, else quantile bins."""
    unique = np.unique(values)
    if len(unique) <= 3:
        return np.searchsorted(unique, values)
    n_bins = int(np.clip(len(values) // POSES_PER_BIN, 2, MAX_BINS))
    edges = np.quantile(values, np.linspace(0, 1, n_bins + 1)[1:-1])
    return np.searchsorted(np.unique(edges), values, side="right")


def binned_test(response: Series, covariate: Series) -> Test | None:
    """The weighted analysis of variance of one response over bins of one covariate."""
    shape = response.values.shape
    x = np.broadcast_to(covariate.values if covariate.values.ndim == len(shape) else covariate.values[:, None],
                        shape).ravel()
    e = response.values.ravel()
    w = response.weights.ravel()
    keep = (w > 0) & np.isfinite(x) & np.isfinite(e)
    x, e, w = x[keep], e[keep], w[keep]
    if len(e) < 6:
        return None
    bins = x.astype(int) if covariate.categorical else _bins(x)
    labels = np.unique(bins)
    if len(labels) < 2 or len(labels) >= len(e):
        return None
    index = np.searchsorted(labels, bins)
    wsum = np.bincount(index, w)
    means = np.bincount(index, w * e) / wsum
    grand = (w * e).sum() / w.sum()
    between = float((wsum * (means - grand) ** 2).sum())
    within = float((w * (e - means[index]) ** 2).sum())
    dof = (len(labels) - 1, len(e) - len(labels))
    f = (between / dof[0]) / max(within / dof[1], 1e-300)
    centres = np.bincount(index, x) / np.bincount(index)
    scale = np.sqrt(within / dof[1])  # noise of one unit weight, from the scatter within bins
    return Test(response.name, covariate.name, float(f), dof, float(stats.f.sf(f, *dof)), 1.0,
                between / max(between + within, 1e-300), centres * covariate.factor, means * response.factor,
                scale / np.sqrt(wsum) * response.factor, response.unit, covariate.unit)


def structure_tests(responses_: list[Series], covariates_: list[Series]) -> list[Test]:
    """Every test, Bonferroni-adjusted, strongest first."""
    tests = [t for r, c in _pairs(responses_, covariates_) if (t := binned_test(r, c)) is not None]
    n = len(tests)
    tests = [replace(t, p_adjusted=min(1.0, t.p * n)) for t in tests]
    return sorted(tests, key=lambda t: (t.p_adjusted, -t.f))
