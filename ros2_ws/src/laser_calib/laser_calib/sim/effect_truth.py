"""Truth forms of the effects for the simulator, and seeded effect sessions.

A true effect is an Effect with values. hooks() turns a list of them into the
param_offsets / spot_transform hooks of simulation.measure: joint effects as
offsets of the theta errors, parameter effects as offsets of their parameter,
spot effects as maps of the true spots (evaluated with the true robot and the
true beams, so the truth is physical: compliance uses the true geometry, the
screen intersection is solved exactly). The joint-reading disturbance of the
simulator is left out of the beams of the spot maps (0.02 deg moves a beam's
t = z_yz / z_x by ~1e-4 of a mm-sized effect).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, ClassVar, Sequence

import numpy as np

from laser_calib.model.kinematics import forward, predict
from laser_calib.measurement.base import NoiseModel, whiten
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.io.samples import Samples
from laser_calib.sim.simulation import NoiseSpec, ParamOffsets, SpotTransform, bundled_robot, measure, sample_poses, true_errors
from laser_calib.effects.base import JOINT, PARAM, SPOT, Effect, sign_choice
from laser_calib.effects.effect_model import EffectModel, Fixed
from laser_calib.estimation.estimate import EstimateOptions, estimate_model
from laser_calib.effects.screen import Surface

TEMPERATURE = "temperature_c"


@dataclass(frozen=True)
class TrueEffect:
    effect: Effect
    values: np.ndarray


@dataclass(frozen=True)
class ForeignError:
    """An error outside the library, for tests of what the library cannot
    explain: offsets (P,n) of the geometric parameters (theta_j columns are
    joint offsets) = offsets(robot, samples), robot the true one."""

    name: str
    offsets: Callable[[Robot, Samples], np.ndarray]

    def param_offsets(self, robot: Robot, samples: Samples) -> np.ndarray:
        return self.offsets(robot, samples)

    def scaled(self, factor: float) -> "ForeignError":
        return ForeignError(self.name, lambda robot, samples: factor * self.offsets(robot, samples))


@dataclass(frozen=True)
class ForeignJointError:
    """A joint error outside the library: dq of joint ``joint`` (0-based) =
    offset(samples) rad, (P,)."""

    name: str
    joint: int
    offset: Callable[[Samples], np.ndarray]

    def param_offsets(self, robot: Robot, samples: Samples) -> np.ndarray:
        out = np.zeros((len(samples), robot.n_params))
        out[:, 4 * self.joint + 3] = self.offset(samples)
        return out

    def scaled(self, factor: float) -> "ForeignJointError":
        return ForeignJointError(self.name, self.joint, lambda samples: factor * self.offset(samples))


@dataclass(frozen=True)
class CurvedScreen(Surface, register=False):
    """A true screen surface outside the library's polynomials, x = amplitude ·
    g(u, v) (u = y / half_y, v = z / half_z, g of size 1 on the screen), the
    beam intersection solved exactly as for every Surface. One parameter, the
    amplitude (m), so the "true model" (the shape known, its size fitted) is an
    ordinary effect model. Shapes (``shape``, with ``width`` and the direction
    or centre (a, b) drawn per seed):

    - cylinder: a section of a cylinder of radius ``width`` (in half sizes,
      > 1) whose axis lies in the screen at angle a, the sag of the arc;
    - cubic: a cubic sag along direction a, (w u')^3 + b (w u')^2 v', u' the
      coordinate along a, v' across;
    - bump: a gaussian bump of standard deviation ``width`` at (a, b);
    - wave: a ripple along direction a, sin(pi u' / w + b), crests ``width``
      half sizes apart (the screen bench's held-out family: neither a
      polynomial nor a single bump).
    """

    kind: ClassVar[str] = "curved_screen"
    title: ClassVar[str] = "curved screen (truth)"
    params: ClassVar[tuple[str, ...]] = ("amplitude",)
    units: ClassVar[tuple[str, ...]] = ("m",)

    half_y: float
    half_z: float
    shape: str
    width: float
    a: float
    b: float

    @property
    def label(self) -> str:
        return f"{self.shape} screen (width {self.width:.2f})"

    @property
    def scales(self) -> np.ndarray:
        return np.full(1, 1e-3)

    @property
    def typical(self) -> np.ndarray:
        return np.full(1, 2e-3)

    @classmethod
    def from_yaml(cls, robot, entry, where):
        raise NotImplementedError("a simulator truth, not a robot file's effect")

    def terms(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v = s[..., 0] / self.half_y, s[..., 1] / self.half_z
        if self.shape == "bump":
            du, dv = u - self.a, v - self.b
            g = np.exp(-(du ** 2 + dv ** 2) / (2 * self.width ** 2))
            gu, gv = -du / self.width ** 2 * g, -dv / self.width ** 2 * g
        else:
            c, s_ = np.cos(self.a), np.sin(self.a)
            along, across = c * u + s_ * v, -s_ * u + c * v
            if self.shape == "cylinder":
                root = np.sqrt(np.maximum(self.width ** 2 - along ** 2, 1e-12))
                g, g_along, g_across = self.width - root, along / root, 0.0 * along
            elif self.shape == "cubic":
                w = self.width
                g = (w * along) ** 3 + self.b * (w * along) ** 2 * across
                g_along = 3 * w ** 3 * along ** 2 + 2 * self.b * w ** 2 * along * across
                g_across = self.b * (w * along) ** 2
            elif self.shape == "wave":
                phase = np.pi * along / self.width + self.b
                g, g_along, g_across = np.sin(phase), np.pi / self.width * np.cos(phase), 0.0 * along
            else:
                raise ValueError(f"unknown screen shape {self.shape!r}")
            gu, gv = c * g_along - s_ * g_across, s_ * g_along + c * g_across
        gradient = np.stack([gu / self.half_y, gv / self.half_z], axis=-1)
        return g[..., None], gradient[..., None, :]


SCREEN_SHAPES = ("cylinder", "cubic", "bump")
HELD_OUT_SHAPES = ("wave",)  # never looked at while the screen surface was built


def curved_screen(robot: Robot, shape: str, rng: np.random.Generator) -> CurvedScreen:
    """A curved screen of ``shape`` on the robot's screen (seen by its camera), its
    width, direction or centre drawn: cylinders of radius 1.5 to 3 half sizes
    (the screen corners, at 1.41, inside) (a strongly to a mildly curved
    section), cubics over 0.8 to 1.2 of the screen, bumps of width 0.25 to 0.6
    anywhere within the middle half, waves of crests 0.6 to 1.2 half sizes apart."""
    half_y, half_z, camera = robot.screen.half_y, robot.screen.half_z, robot.screen.camera
    if shape == "wave":
        return CurvedScreen(half_y, half_z, shape, float(rng.uniform(0.6, 1.2)), float(rng.uniform(0, np.pi)),
                            float(rng.uniform(0, 2 * np.pi)), camera=camera)
    if shape == "cylinder":
        return CurvedScreen(half_y, half_z, shape, float(rng.uniform(1.5, 3.0)), float(rng.uniform(0, np.pi)), 0.0,
                            camera=camera)
    if shape == "cubic":
        return CurvedScreen(half_y, half_z, shape, float(rng.uniform(0.8, 1.2)), float(rng.uniform(0, 2 * np.pi)),
                            float(rng.uniform(-1, 1)), camera=camera)
    return CurvedScreen(half_y, half_z, shape, float(rng.uniform(0.25, 0.6)), float(rng.uniform(-0.5, 0.5)),
                        float(rng.uniform(-0.5, 0.5)), camera=camera)


Foreign = ForeignError | ForeignJointError
Truth = TrueEffect | ForeignError | ForeignJointError


def draw_truth(effect: Effect, rng: np.random.Generator, size: float = 1.0) -> TrueEffect:
    """Values of random sign with magnitudes in [0.5, 1] x size x the effect's typical size."""
    return TrueEffect(effect, size * effect.typical * sign_choice(rng, len(effect.params)))


def visibility(robot: Robot, errors: np.ndarray, context: Samples, truth: Truth, noise: NoiseSpec) -> float:
    """How visible a true effect is after a geometric fit: the noncentrality
    |P m|^2 of its whitened spot motion m (m = J_e v for an effect with values
    v; jac_q dq for a foreign joint error) once the directions the geometric
    errors can take up (P: the projector onto the complement of their whitened
    Jacobian) are removed; the expected excess of chi^2 it leaves in the
    geometric fit. ``robot`` nominal, ``errors`` the true geometric errors,
    ``context`` the calibration readings (spots not needed)."""
    spots = predict(robot.with_errors(errors), context.q).spots
    seen = Samples(context.pose, context.stamp, context.q, spots, context.extra)
    effects = [truth.effect] if isinstance(truth, TrueEffect) else []
    model = EffectModel(SpotModel(robot, seen), effects)
    values = truth.values if isinstance(truth, TrueEffect) else np.zeros(0)
    res = model.residuals(np.concatenate([errors, np.zeros(len(values))]), True)
    whitener = NoiseModel(noise.spot_sigma, noise.joint_sigma).whitener(res)
    _, jac = whiten(res, whitener)
    if isinstance(truth, TrueEffect):
        motion = jac[:, model.n_geometric:] @ values
    else:
        moved = np.einsum("pcdn,pn->pcd", res.jac[..., :robot.n_params],
                          truth.param_offsets(robot.with_errors(errors), context))
        motion = np.einsum("pij,pj->pi", whitener, moved.reshape(len(moved), -1)).ravel()
    u, s, _ = np.linalg.svd(jac[:, :model.n_geometric], full_matrices=False)
    u = u[:, s > 1e-9 * s[0]]
    return float(np.sum((motion - u @ (u.T @ motion)) ** 2))


def sized(robot: Robot, errors: np.ndarray, context: Samples, truth: Truth, noise: NoiseSpec,
          target: float) -> Truth:
    """The true effect scaled to the visibility ``target`` (same shape and signs)."""
    factor = float(np.sqrt(target / visibility(robot, errors, context, truth, noise)))
    if isinstance(truth, TrueEffect):
        return TrueEffect(truth.effect, truth.values * factor)
    return truth.scaled(factor)


def hooks(truth: Sequence[Truth]) -> tuple[ParamOffsets | None, SpotTransform | None]:
    """simulation.measure hooks producing the given true effects."""
    foreign = [t for t in truth if not isinstance(t, TrueEffect)]
    effects = [t for t in truth if isinstance(t, TrueEffect)]
    blocks = [t for t in effects if t.effect.family in (JOINT, PARAM)]
    spot = sorted((t for t in effects if t.effect.family == SPOT), key=lambda t: t.effect.order)

    def param_offsets(robot: Robot, context: Samples) -> np.ndarray:
        offsets = np.zeros((len(context), robot.n_params))
        for t in blocks:
            column = 4 * t.effect.joint + 3 if t.effect.family == JOINT else t.effect.param
            offsets[:, column] += t.effect.basis(robot, context) @ t.values
        for t in foreign:
            offsets += t.param_offsets(robot, context)
        return offsets

    def spot_transform(robot: Robot, context: Samples, spots: np.ndarray) -> np.ndarray:
        beams = forward(robot, context.q, param_offsets(robot, context)).beams
        for t in spot:
            spots = t.effect.apply(spots, beams, t.values)[0]
        return spots

    return (param_offsets if blocks or foreign else None), (spot_transform if spot else None)


@dataclass(frozen=True)
class EffectSession:
    """Calibration and test sets of one arm with true effects. Both sets span
    the same time (test rows interleaved between calibration rows), each file
    in its own measurement order starting from q = 0, with a temperature column."""

    nominal: Robot
    true: Robot
    errors: np.ndarray
    cal: Samples
    test: Samples
    cal_truth: Samples
    test_truth: Samples
    truth: tuple[Truth, ...]
    noise: NoiseSpec


def fitted_test_rms(session: EffectSession, model_of: Callable[[Samples], EffectModel],
                    options: EstimateOptions) -> float:
    """Test RMS (mm) of the spot error of model_of(samples) fitted on the calibration set."""
    est = estimate_model(model_of(session.cal), options)
    test = model_of(session.test).residuals(est.values, False)
    d = np.linalg.norm(test.r, axis=-1)[test.valid]
    return float(np.sqrt(np.mean(d ** 2)) * 1e3)


def true_offsets_rms(session: EffectSession, truth: ForeignError | ForeignJointError,
                     options: EstimateOptions) -> float:
    """fitted_test_rms of the geometric errors with the true foreign offsets known: the best a
    model of the foreign error can do on these poses."""
    def model(samples: Samples) -> EffectModel:
        errors = truth.param_offsets(session.true, samples)
        return EffectModel(SpotModel(session.nominal, samples), (), None, Fixed(np.zeros_like(samples.q), errors))
    return fitted_test_rms(session, model, options)


def warmup(stamps: np.ndarray, duration: float) -> np.ndarray:
    """A warm-up and cool-down (deg C): rises and falls over the session, so it is
    not a linear function of time."""
    phase = np.pi * stamps / duration
    return 22.0 + 4.0 * np.sin(phase) + 1.0 * np.sin(3.0 * phase + 0.5)


def temperature(stamps: np.ndarray, duration: float, rng: np.random.Generator) -> np.ndarray:
    """The warm-up read by a sensor with 0.05 deg C noise."""
    return warmup(stamps, duration) + rng.normal(0.0, 0.05, len(stamps))


def effect_session(case: str | Robot, seed: int,
                   make_truth: Callable[[Robot, np.ndarray, Samples, np.random.Generator], Sequence[Truth]],
                   n_cal: int = 80, n_test: int = 80, noise: NoiseSpec = NoiseSpec(),
                   period: float = 10.0, camera: tuple[float, float, float] | None = None) -> EffectSession:
    """A seeded session of ``case`` (simulation.CASES, or a nominal robot) over the whole workspace:
    random geometric errors (uniform within 10 mm / 1 deg), the true effects
    ``make_truth(nominal, true errors, calibration context, rng)`` (effects whose
    constants depend on the data, e.g. a drift's reference, see the calibration
    set's stamps and covariates; ``sized`` needs the errors), spot and joint
    noise as in simulation.measure. Rows are ``period`` s apart; ``camera``: the
    centre of the camera watching the screen (the robots' screen.camera)."""
    rng = np.random.default_rng(seed)
    nominal = case if isinstance(case, Robot) else bundled_robot(case)
    nominal = replace(nominal, screen=replace(nominal.screen, camera=camera))
    errors = true_errors(nominal, rng)
    true = nominal.with_errors(errors)
    q_cal = sample_poses([nominal, true], n_cal, rng, "whole")
    q_test = sample_poses([nominal, true], n_test, rng, "whole")
    duration = period * max(n_cal, n_test)
    stamps_cal = period * np.arange(n_cal)
    stamps_test = period * np.arange(n_test) + period / 2
    extra_cal = {TEMPERATURE: temperature(stamps_cal, duration, rng)}
    extra_test = {TEMPERATURE: temperature(stamps_test, duration, rng)}
    context = Samples(np.arange(n_cal), stamps_cal, q_cal, np.full((n_cal, 2, 2), np.nan), extra_cal)
    truth = tuple(make_truth(nominal, errors, context, rng))
    offsets, transform = hooks(truth)
    cal, cal_truth = measure(true, q_cal, rng, noise, stamps_cal, extra_cal, offsets, transform)
    test, test_truth = measure(true, q_test, rng, noise, stamps_test, extra_test, offsets, transform,
                               first_pose=n_cal)
    return EffectSession(nominal, true, errors, cal, test, cal_truth, test_truth, truth, noise)
