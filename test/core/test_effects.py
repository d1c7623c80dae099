"""The effect library: Jacobians, truth forms, the robot-file key, the pieces
the diagnosis builds on (move directions, gravity torques, residual tests)."""

import numpy as np
import pytest

from laser_calib.effects import (Backlash, CameraDistortion, Compliance, Drift, EffectModel, JointScale, Periodic,
                                 ScreenShape, calibrated_model, candidates, effects_from_robot, effects_to_yaml,
                                 gravity_torques, move_directions)
from laser_calib.effects.catalog import camera_distortion, screen_shape
from laser_calib.diagnosis.structure import POSE, Series, binned_test
from laser_calib.sim.effect_truth import TEMPERATURE, draw_truth, effect_session, hooks, visibility
from laser_calib.io.errors import InputError
from laser_calib.estimation.estimate import EstimateOptions, estimate_model
from laser_calib.estimation.ekf import EkfOptions
from laser_calib.model.kinematics import forward
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot_file import dump_robot, robot_from_dict
from laser_calib.io.samples import Samples
from laser_calib.sim.simulation import NoiseSpec, bundled_robot, measure, sample_poses
from dataclasses import replace
import yaml

ARMS = ("paper-7dof", "paper-4dof")
NOISE = NoiseSpec(spot=0.5e-3, joint=float(np.deg2rad(0.02)))


def all_effects(robot, samples):
    """One effect of every kind (joint effects at joint 2, which carries a gravity load on both arms)."""
    return [JointScale(joint=1), Compliance.make(robot, samples, 1), Periodic(joint=1), Backlash(joint=1),
            Drift.make(robot, samples, "a2", TEMPERATURE), screen_shape(robot), camera_distortion(robot)]


def session(arm, make, n=16, noise=NoiseSpec(0.0, 0.0), seed=3):
    return effect_session(arm, seed, lambda r, e, c, rng: [draw_truth(x, rng) for x in make(r, c)], n, 4, noise)


def numeric_jacobian(model, x, columns, step=1e-6):
    """Central differences of the predicted spots, step in units of each parameter's scale."""
    out = np.zeros(model.residuals(x, False).predicted.shape + (len(columns),))
    for k, j in enumerate(columns):
        h = step * model.scales[j]
        plus, minus = x.copy(), x.copy()
        plus[j] += h
        minus[j] -= h
        out[..., k] = (model.residuals(plus, False).predicted - model.residuals(minus, False).predicted) / (2 * h)
    return out


@pytest.mark.parametrize("arm", ARMS)
def test_truth_forms_are_what_the_model_predicts(arm):
    """Noise-free data simulated with every effect's truth form equals the
    model's prediction at the true errors and effect values."""
    s = session(arm, all_effects)
    model = EffectModel(SpotModel(s.nominal, s.cal), [t.effect for t in s.truth])
    x = np.concatenate([s.errors] + [t.values for t in s.truth])
    predicted = model.residuals(x, False).predicted
    seen = s.cal.seen
    assert np.abs(predicted[seen] - s.cal.spots[seen]).max() < 1e-9


@pytest.mark.parametrize("arm", ARMS)
def test_jacobian_of_joint_and_parameter_effects_is_exact(arm):
    """With the spot maps at zero (they neglect a second-order term), every
    column matches central differences to the differencing error, once the one
    stated omission is added back: the compliance basis is recomputed at the
    geometric errors, and its change with them (jac_q_i x gain x d tau_i / d x_j)
    is left out of the Jacobian."""
    s = session(arm, all_effects)
    model = EffectModel(SpotModel(s.nominal, s.cal), [t.effect for t in s.truth])
    values = [t.values if t.effect.family != "spot" else 0 * t.values for t in s.truth]
    x = np.concatenate([s.errors] + values)
    res = model.residuals(x, True)
    columns = list(range(len(x)))
    numeric = numeric_jacobian(model, x, columns)
    compliance = next(t for t in s.truth if t.effect.kind == "compliance")
    i, gain = compliance.effect.joint, x[model.names.index(f"compliance{compliance.effect.joint + 1}")]
    omitted = np.zeros_like(numeric)
    for j in range(model.n_geometric):
        h = 1e-6 * model.scales[j]
        plus, minus = s.errors.copy(), s.errors.copy()
        plus[j] += h
        minus[j] -= h
        dtau = (gravity_torques(s.nominal.with_errors(plus), s.cal.q)[:, i]
                - gravity_torques(s.nominal.with_errors(minus), s.cal.q)[:, i]) / (2 * h)
        omitted[..., j] = res.jac_q[..., i] * (gain * dtau)[:, None, None]
    scale = np.abs(numeric * model.scales).max()
    assert np.abs((res.jac + omitted - numeric) * model.scales).max() < 1e-6 * scale


@pytest.mark.parametrize("arm", ARMS)
def test_jacobian_of_spot_effect_parameters_is_exact(arm):
    s = session(arm, lambda r, c: [screen_shape(r), camera_distortion(r)])
    model = EffectModel(SpotModel(s.nominal, s.cal), [t.effect for t in s.truth])
    x = np.concatenate([s.errors] + [t.values for t in s.truth])
    columns = list(range(model.n_geometric, len(x)))
    analytic = model.residuals(x, True).jac[..., columns]
    numeric = numeric_jacobian(model, x, columns)
    assert np.abs(analytic - numeric).max() < 1e-6 * np.abs(numeric).max()


def test_screen_shape_solves_the_intersection_with_the_surface():
    """The beam p + k z meets x = f(y, z) where the map puts the spot."""
    robot = bundled_robot("paper-4dof")
    q = sample_poses([robot], 10, np.random.default_rng(1))
    shape = screen_shape(robot)
    values = np.array([1.0, -1.5, 3.0, 2.0, -2.5]) * 1e-3
    state = forward(robot, q)
    p, z = state.origin[:, None, :], state.beams
    k = -p[..., 0] / z[..., 0]
    flat = (p + k[..., None] * z)[..., 1:]
    spots = shape.apply(flat, z, values)[0]
    # Where the beam reaches those (y, z), its x must be f(y, z).
    k_surface = (spots[..., 0] - p[..., 1]) / z[..., 1]
    x = p[..., 0] + k_surface * z[..., 0]
    u, v = spots[..., 0] / shape.half_y, spots[..., 1] / shape.half_z
    f = np.stack([u, v, u * u, u * v, v * v], axis=-1) @ values
    assert np.abs(x - f).max() < 1e-12


def test_move_directions_follow_the_row_order_from_home():
    q = np.array([[0.1, 0.0], [0.1, -0.2], [0.05, -0.2], [0.05, 0.3]])
    expected = np.array([[1, 0], [1, -1], [-1, -1], [-1, 1]])
    assert np.array_equal(move_directions(q), expected)


@pytest.mark.parametrize("arm", ARMS)
def test_gravity_torque_is_minus_the_gradient_of_the_potential(arm):
    """tau_i = -dV/dq_i with V = -sum_m g.p_m over the lumped unit masses."""
    robot = bundled_robot(arm)
    q = sample_poses([robot], 5, np.random.default_rng(2))
    g = np.array(robot.gravity)

    def potential(q):
        state = forward(robot, q)
        points = np.concatenate([state.joint_origin[:, 1:], state.origin[:, None]], axis=1)
        return [-(points[:, i:] @ g).sum(axis=1) for i in range(robot.n_joints)]

    h = 1e-6
    for i in range(robot.n_joints):
        plus, minus = q.copy(), q.copy()
        plus[:, i] += h
        minus[:, i] -= h
        numeric = -(potential(plus)[i] - potential(minus)[i]) / (2 * h)
        assert np.allclose(gravity_torques(robot, q)[:, i], numeric, atol=1e-7)


def test_candidates_cover_the_library_where_the_data_can_show_it():
    robot = bundled_robot("paper-4dof")
    s = session("paper-4dof", lambda r, c: [], n=20)
    kinds = {(c.kind, c.where) for c in candidates(robot, s.cal)}
    assert ("joint_scale", "joint 1") in kinds and ("backlash", "joint 4") in kinds
    # Joint 1 of the 4-DOF arm turns about the vertical: no gravity torque, no compliance candidate.
    assert ("compliance", "joint 1") not in kinds and ("compliance", "joint 2") in kinds
    assert ("screen_shape", "screen") in kinds and ("camera_distortion", "camera") in kinds
    drifts = [c for c in candidates(robot, s.cal) if c.kind == "drift"]
    assert {d.covariate for d in drifts} == {"stamp", TEMPERATURE}
    assert len(drifts) == 2 * (2 * robot.n_joints + 2)


@pytest.mark.parametrize("arm", ARMS)
def test_effects_key_round_trips_through_the_robot_file(arm):
    s = session(arm, all_effects)
    effects, values = [t.effect for t in s.truth], [t.values for t in s.truth]
    robot = replace(s.nominal, extra={"effects": effects_to_yaml(effects, values)})
    loaded = robot_from_dict(yaml.safe_load(dump_robot(robot)))
    effects2, values2 = effects_from_robot(loaded)
    assert effects2 == effects
    assert all(np.array_equal(a, b) for a, b in zip(values, values2))
    model, x = calibrated_model(loaded.with_errors(s.errors), s.cal)
    reference = EffectModel(SpotModel(s.nominal, s.cal), effects)
    x_reference = np.concatenate([s.errors, *values])
    assert np.allclose(model.residuals(x, False).predicted, reference.residuals(x_reference, False).predicted,
                       atol=1e-12, equal_nan=True)


@pytest.mark.parametrize("entry, where", [
    ({"type": "wobble", "joint": 1}, "type"),
    ({"type": "backlash", "joint": 9, "b": 0.001}, "joint"),
    ({"type": "backlash", "joint": 2}, "missing key 'b'"),
    ({"type": "drift", "parameter": "alpha1", "covariate": "stamp", "reference": 0, "spread": 1, "rate": 0},
     "parameter"),
    ({"type": "screen_shape", "u": "big", "v": 0, "uu": 0, "uv": 0, "vv": 0}, "u"),
])
def test_bad_effects_key_gives_one_line_naming_the_entry(entry, where):
    robot = replace(bundled_robot("paper-4dof"), extra={"effects": [entry]})
    with pytest.raises(InputError) as info:
        effects_from_robot(robot, "r.yaml")
    assert "r.yaml: effects[0]" in str(info.value) and where in str(info.value)
    assert "\n" not in str(info.value)


def test_visibility_is_the_chi2_excess_left_in_the_geometric_fit():
    """Sizing by visibility: the geometric fit's chi^2 exceeds its dof by about
    the target (noncentral chi^2: mean dof + lambda, std sqrt(2 dof + 4 lambda))."""
    target = 200.0
    arm = "paper-7dof"

    def make(robot, errors, context, rng):
        truth = draw_truth(Backlash(joint=2), rng)
        return [replace(truth, values=truth.values * np.sqrt(target / visibility(robot, errors, context, truth,
                                                                                 NOISE)))]

    s = effect_session(arm, 4, make, 80, 4, NOISE)
    est = estimate_model(SpotModel(s.nominal, s.cal), EstimateOptions(spot_sigma=NOISE.spot_sigma,
                                                                      joint_sigma=NOISE.joint_sigma, restarts=0))
    dof = est.fit.dof
    assert abs(est.fit.chi2 - dof - target) < 4 * np.sqrt(2 * dof + 4 * target)


def test_ekf_and_lm_reach_the_same_estimate_with_an_effect():
    """The effect model plugs into the paper's EKF as into LM: same weighted
    least-squares point (well within the estimate's std)."""
    s = session("paper-4dof", lambda r, c: [Backlash(joint=1)], n=30, noise=NOISE)
    model = EffectModel(SpotModel(s.nominal, s.cal), [t.effect for t in s.truth])
    base = EstimateOptions(spot_sigma=NOISE.spot_sigma, joint_sigma=NOISE.joint_sigma, restarts=0)
    lm = estimate_model(model, base)
    ekf = estimate_model(model, replace(base, method="ekf", ekf=EkfOptions(r=None, q=1e-8, max_iter=3000,
                                                                             tol=1e-10)))
    free = lm.identifiable
    assert np.all(np.abs(ekf.values - lm.values)[free] < 0.05 * lm.std[free])


def test_binned_test_is_calibrated_and_sees_a_step():
    """Under no dependence the F test's p is uniform; a step of 3 noise sigmas
    over half the poses is found."""
    rng = np.random.default_rng(5)
    x = rng.uniform(0, 1, 80)
    p_values = []
    for _ in range(400):
        e = rng.normal(0, 1, 80)
        p_values.append(binned_test(Series("e", e, POSE, "", weights=np.ones(80)), Series("x", x, POSE, "")).p)
    assert abs(np.mean(np.array(p_values) < 0.05) - 0.05) < 3 * np.sqrt(0.05 * 0.95 / 400)
    e = rng.normal(0, 1, 80) + 3.0 * (x > 0.5)
    assert binned_test(Series("e", e, POSE, "", weights=np.ones(80)), Series("x", x, POSE, "")).p < 1e-10


def test_hooks_apply_joint_effects_as_theta_offsets():
    robot = bundled_robot("paper-4dof")
    q = sample_poses([robot], 6, np.random.default_rng(0))
    truth = [draw_truth(Backlash(joint=2), np.random.default_rng(1))]
    offsets, transform = hooks(truth)
    assert transform is None
    measured, _ = measure(robot, q, np.random.default_rng(2), NoiseSpec(0.0, 0.0), param_offsets=offsets)
    context = Samples(np.arange(6), np.arange(6.0), q, np.full((6, 2, 2), np.nan))
    shifted = q.copy()
    shifted[:, 2] += Backlash(joint=2).basis(robot, context)[:, 0] * truth[0].values[0]
    expected, _ = measure(robot, shifted, np.random.default_rng(2), NoiseSpec(0.0, 0.0))
    assert np.allclose(measured.spots, expected.spots, atol=1e-12, equal_nan=True)


def test_screen_and_distortion_units_and_scales():
    """Every coefficient of the spot effects is a length at the screen edge:
    a unit coefficient moves an edge spot by about that length."""
    robot = bundled_robot("paper-7dof")
    spots = np.array([[[1.0, 0.0], [0.0, 1.0]]])
    beams = np.tile(np.array([1.0, 0.0, 0.0]), (1, 2, 1))
    camera = CameraDistortion(radius=1.0)
    moved = camera.apply(spots, beams, np.array([1e-3, 0, 0, 0]))[0]
    assert np.allclose(moved - spots, [[[1e-3, 0.0], [0.0, 1e-3]]])
    assert np.all(ScreenShape(1.0, 1.0).scales == 1e-3) and np.all(camera.scales == 1e-3)
    assert screen_shape(robot).half_y == robot.screen.half_y


def test_joint_effects_work_on_any_sensor_model_with_jac_q():
    """A backlash on a point sensor's model (no laser, no screen): the Jacobian
    is jac_q @ basis there too, and subsets slice the approach directions."""
    from laser_calib.io.sensor_samples import SensorSamples
    from laser_calib.measurement.frames import Pose, robot_frames, with_frames
    from laser_calib.measurement.sensor import PointModel
    from laser_calib.measurement.chain import chain_names, target_in_sensor

    robot = with_frames(bundled_robot("paper-4dof"), {
        "sensor": Pose(np.eye(3), np.array([1.5, 0.2, 0.4])), "base": Pose(np.eye(3), np.zeros(3)),
        "target": Pose(np.eye(3), np.array([0.02, -0.01, 0.05]))})
    rng = np.random.default_rng(4)
    q = rng.uniform(robot.q_min, robot.q_max, (20, robot.n_joints))
    position = target_in_sensor(robot, robot_frames(robot), q, np.zeros(len(chain_names(robot)))).position
    samples = SensorSamples(np.arange(20), np.arange(20.0), q, position=position)
    model = EffectModel(PointModel(robot, samples), [Backlash(joint=1)])
    x = np.zeros(len(model.names))
    x[-1] = 2e-3
    res = model.residuals(x, True)
    numeric = numeric_jacobian(model, x, [len(x) - 1])
    assert np.allclose(res.jac[..., -1:], numeric, rtol=0, atol=1e-5 * np.abs(numeric).max())
    assert np.array_equal(model.subset(np.arange(5, 20)).bases.joint, model.bases.joint[5:])
    with pytest.raises(ValueError):
        EffectModel(PointModel(robot, samples), [camera_distortion(robot)])
