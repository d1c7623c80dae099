"""Point and pose measurement models, unknown frames, standard D-H, sensor sample files."""

import json
from dataclasses import replace

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from laser_calib.cli.main import main
from laser_calib.diagnosis.engine import DiagnoseOptions, supports
from laser_calib.effects import CameraDistortion, EffectModel, JointScale, Periodic, ScreenShape
from laser_calib.io.errors import InputError
from laser_calib.estimation.estimate import EstimateOptions, estimate_model
from laser_calib.estimation.ekf import EkfOptions
from laser_calib.model.kinematics import forward
from laser_calib.measurement.base import NoiseModel, robot_scales
from laser_calib.model.robot_file import dump_robot, robot_from_dict
from laser_calib.io.sensor_samples import SensorSamples
from laser_calib.measurement.frames import Pose, robot_frames, with_frames
from laser_calib.measurement.sensor import PointModel, PoseModel
from laser_calib.diagnosis.sensor_data import diagnose, heldout_effects, sensor_data
from laser_calib.estimation.sensor_fit import SensorFitOptions, calibrate, frames_first, pose_errors
from laser_calib.measurement.chain import chain_names, target_in_sensor
from laser_calib.measurement.rotations import matrix_to_quaternion, quaternion_to_matrix
from laser_calib.io.sensor_samples import format_sensor_samples, parse_sensor_samples, save_sensor_samples
from laser_calib.sim.simulation import bundled_robot

STEP = 1e-6
SIGMA_T = 2e-4        # m, simulated position noise
SIGMA_R = 2e-4        # rad, simulated rotation noise (rotation_length = SIGMA_T / SIGMA_R = 1 m/rad)


def rig(convention: str = "paper"):
    """The paper's 4-DOF arm seen by a sensor 1.5 m away, a target 5 cm off the tool."""
    robot = replace(bundled_robot("paper-4dof"), convention=convention)
    frames = {"sensor": Pose(quaternion_to_matrix(np.array([0.2, 0.9, -0.3, 0.2])), np.array([1.5, 0.2, 0.4])),
              "base": Pose(quaternion_to_matrix(np.array([1.0, 0.05, -0.02, 0.1])), np.array([0.1, -0.2, 0.05])),
              "target": Pose(quaternion_to_matrix(np.array([0.7, 0.1, 0.7, 0.0])), np.array([0.02, -0.01, 0.05]))}
    return with_frames(robot, frames)


def simulate(robot, truth: np.ndarray, n: int, seed: int, kind: str, still: int | None = None) -> SensorSamples:
    """Measured samples of the true parameters ``truth`` (chain vector) with Gaussian noise;
    still: a joint read at the middle of its range in every pose."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(robot.q_min, robot.q_max, (n, robot.n_joints))
    if still is not None:
        q[:, still] = (robot.q_min[still] + robot.q_max[still]) / 2
    state = target_in_sensor(robot, robot_frames(robot), q, truth)
    position = state.position + rng.normal(0, SIGMA_T, (n, 3))
    quaternion = None
    if kind == "pose":
        tilt = rng.normal(0, SIGMA_R, (n, 3))
        quaternion = matrix_to_quaternion(state.rotation @ Rotation.from_rotvec(tilt).as_matrix())
    return SensorSamples(np.arange(n), np.arange(n, dtype=float), q, position=position, quaternion=quaternion)


def central_jacobian(model, x: np.ndarray) -> np.ndarray:
    """d residual / d x (P, M, n) by central differences; the residual is measured minus predicted."""
    numeric = np.zeros((*model.residuals(x, False).r.shape, len(x)))
    for k in range(len(x)):
        e = np.zeros(len(x))
        e[k] = STEP
        numeric[..., k] = -(model.residuals(x + e, False).r - model.residuals(x - e, False).r) / (2 * STEP)
    return numeric


@pytest.mark.parametrize("kind", ["pose", "point"])
@pytest.mark.parametrize("scale", [False, True])
@pytest.mark.parametrize("convention", ["paper", "standard"])
def test_jacobians_match_central_differences(kind, scale, convention):
    robot = rig(convention)
    samples = simulate(robot, np.zeros(len(chain_names(robot))), 15, 3, kind)
    model = PoseModel(robot, samples, 0.7, scale) if kind == "pose" else PointModel(robot, samples, scale)
    rng = np.random.default_rng(4)
    x = rng.normal(0, 3, len(model.names)) * model.scales   # far from zero: exact at any size
    res = model.residuals(x)
    assert np.abs(central_jacobian(model, x) - res.jac).max() < 1e-6 * np.abs(res.jac).max()
    numeric_q = np.zeros_like(res.jac_q)
    for i in range(robot.n_joints):
        dq = np.zeros_like(samples.q)
        dq[:, i] = STEP
        numeric_q[..., i] = -(model.evaluate(x, dq, False).r - model.evaluate(x, -dq, False).r) / (2 * STEP)
    assert np.abs(numeric_q - res.jac_q).max() < 1e-6 * np.abs(res.jac_q).max()


def _dh(convention: str, a, d, alpha, theta) -> np.ndarray:
    def trans(axis, v):
        m = np.eye(4)
        m[axis, 3] = v
        return m

    def rot(axis, v):
        m = np.eye(4)
        i, j = [(1, 2), (2, 0), (0, 1)][axis]
        m[i, i] = m[j, j] = np.cos(v)
        m[i, j], m[j, i] = -np.sin(v), np.sin(v)
        return m
    if convention == "standard":
        return trans(2, d) @ rot(2, theta) @ trans(0, a) @ rot(0, alpha)
    return trans(0, a) @ trans(2, d) @ rot(0, alpha) @ rot(2, theta)


@pytest.mark.parametrize("convention", ["paper", "standard"])
def test_forward_matches_the_explicit_matrix_product(convention):
    robot = replace(bundled_robot("paper-7dof"), convention=convention)
    rng = np.random.default_rng(5)
    q = rng.uniform(robot.q_min, robot.q_max, (6, robot.n_joints))
    state = forward(robot, q)
    s = robot.slm
    for p in range(len(q)):
        m = np.eye(4)
        for joint, qi in zip(robot.joints, q[p]):
            m = m @ _dh(convention, joint.a, joint.d, joint.alpha, joint.theta0 + qi)
        m = m @ _dh("paper", s.a, s.d, s.alpha, 0.0)
        ry = np.eye(4)
        ry[[0, 0, 2, 2], [0, 2, 0, 2]] = np.cos(s.beta), np.sin(s.beta), -np.sin(s.beta), np.cos(s.beta)
        m = m @ ry @ _dh("paper", 0.0, 0.0, 0.0, s.theta)
        assert np.allclose(state.origin[p], m[:3, 3], atol=1e-12)
        assert np.allclose(state.rotation[p], m[:3, :3], atol=1e-12)


def _truth(robot, model, fixed, rng) -> np.ndarray:
    """True errors within the tolerances on the parameters the fit estimates."""
    truth = np.zeros(len(model.names))
    free = np.array([n not in fixed for n in model.names])
    truth[free] = rng.uniform(-1, 1, free.sum()) * model.scales[free]
    return truth


@pytest.mark.parametrize("kind", ["pose", "point"])
def test_calibration_recovers_dh_errors_and_frames(kind):
    robot = rig("standard")
    zero = np.zeros(len(chain_names(robot)))
    probe = simulate(robot, zero, 60, 1, kind)
    model = PoseModel(robot, probe) if kind == "pose" else PointModel(robot, probe)
    held = np.array([n.startswith("base_") for n in model.names])  # the base is known: mask it
    absorbed = frames_first(model, NoiseModel(SIGMA_T), held)
    fixed = {n for n, h in zip(model.names, held) if h} | set(absorbed)
    truth = _truth(robot, model, fixed, np.random.default_rng(2))
    full = np.zeros(len(chain_names(robot)))
    full[model.index] = truth
    samples = simulate(robot, full, 60, 1, kind)
    options = SensorFitOptions(estimate=EstimateOptions(spot_sigma=SIGMA_T, fixed=tuple(sorted(n for n, h in zip(
        model.names, held) if h))), rotation_length=SIGMA_T / SIGMA_R)
    fit = calibrate(robot, samples, options)
    est = fit.estimate
    free = est.identifiable
    assert set(fit.absorbed) == absorbed.keys()
    assert free.sum() == len(model.names) - len(fixed)
    # 4.5 std: a 1-in-150000 event per parameter if the covariance is right
    assert np.all(np.abs(est.values[free] - truth[free]) < 4.5 * est.std[free])
    assert est.fit.chi2 < est.fit.dof + 6 * np.sqrt(2 * est.fit.dof)
    position, _ = pose_errors(fit.model, est.values)
    assert np.mean(position) < 2.0 * SIGMA_T * np.sqrt(3)   # near the noise, |N(0, s^2 I_3)| ~ 1.6 s
    # The calibrated robot file (D-H values and frames) predicts what the fit predicts.
    corrected = type(fit.model)(fit.corrected(robot), samples, *(() if kind == "point" else (fit.rotation_length,)))
    assert np.allclose(corrected.residuals(np.zeros(len(model.names)), False).r,
                       fit.model.residuals(est.values, False).r, atol=1e-12)


def test_masks_and_priors_hold_frame_parameters():
    robot = rig()
    samples = simulate(robot, np.zeros(len(chain_names(robot))), 30, 6, "pose")
    fixed = ("sensor_x", "target_rz", "a2")
    fit = calibrate(robot, samples, SensorFitOptions(estimate=EstimateOptions(fixed=fixed)))
    names = fit.model.names
    for name in fixed:
        assert fit.estimate.values[names.index(name)] == 0.0 and not fit.estimate.identifiable[names.index(name)]
    tight = calibrate(robot, simulate(robot, np.r_[np.zeros(len(chain_names(robot)) - 6), 0.01, 0, 0, 0, 0, 0], 30,
                                      6, "pose"),
                      SensorFitOptions(frame_prior_length=1e-6, rotation_length=1.0))
    # A 10 mm target offset the prior forbids ends up elsewhere, not in the target frame.
    assert abs(tight.estimate.values[tight.model.names.index("target_x")]) < 1e-5
    with pytest.raises(ValueError, match="unknown parameter"):
        calibrate(robot, samples, SensorFitOptions(estimate=EstimateOptions(fixed=("nope",))))


def test_sensor_scale_is_estimated_when_a_length_pins_it():
    robot = rig()
    truth = np.zeros(len(chain_names(robot)))
    samples = simulate(robot, truth, 60, 8, "point")
    stretched = replace(samples, position=samples.position * np.array([1.002, 0.999, 1.0]))
    fit = calibrate(robot, stretched, SensorFitOptions(estimate=EstimateOptions(spot_sigma=SIGMA_T), scale=True))
    names = fit.model.names
    values = fit.estimate.values
    # A common scale is not observable here (the frames absorb it): only the differences are.
    free = [n for n in ("scale_x", "scale_y", "scale_z") if fit.estimate.identifiable[names.index(n)]]
    assert free == ["scale_x", "scale_y"]
    assert abs(values[names.index("scale_x")] - 0.002) < 4.5 * fit.estimate.std[names.index("scale_x")]
    assert abs(values[names.index("scale_y")] + 0.001) < 4.5 * fit.estimate.std[names.index("scale_y")]


def test_sensor_samples_round_trip_and_validation():
    samples = simulate(rig(), np.zeros(len(chain_names(rig()))), 5, 9, "pose")
    position = samples.position.copy()
    position[2] = np.nan
    quaternion = samples.quaternion.copy()
    quaternion[2] = np.nan
    samples = replace(samples, position=position, quaternion=quaternion, extra={"temperature_c": np.arange(5.0)})
    text = format_sensor_samples(samples)
    back = parse_sensor_samples(text)
    assert back.kind == "pose" and list(back.extra) == ["temperature_c"]
    for a, b in ((back.q, samples.q), (back.position, samples.position), (back.quaternion, samples.quaternion)):
        assert np.array_equal(a, b, equal_nan=True)
    assert list(back.seen) == [True, True, False, True, True]
    point = replace(samples, quaternion=None)
    assert parse_sensor_samples(format_sensor_samples(point)).kind == "point"
    lines = text.splitlines()
    bad_norm, partial = lines[1].split(","), lines[1].split(",")
    bad_norm[9] = "0.9"     # qw
    partial[6] = ""         # x missing, y and z given
    cases = {
        "header": "pose,time,q1\n0,0,0\n",
        "x,y,z": "pose,stamp,q1,q2,q3,q4,y,x,z\n0,0,0,0,0,0,1,1,1\n",
        "quaternion norm": "\n".join([lines[0], ",".join(bad_norm)]),
        "only some": "\n".join([lines[0], ",".join(partial)]),
        "not increasing": "\n".join([lines[0], lines[1], lines[1].replace("0,0.0", "1,0.0", 1)]),
    }
    for what, bad in cases.items():
        with pytest.raises(InputError, match=what):
            parse_sensor_samples(bad, "s.csv", rig())


def test_robot_file_frames_convention_and_no_lasers_round_trip():
    robot = replace(rig("standard"), lasers=())
    text = dump_robot(robot)
    back = robot_from_dict(yaml.safe_load(text))
    assert back.convention == "standard" and back.lasers == () and "lasers" not in yaml.safe_load(text)
    for name, pose in robot_frames(robot).items():
        other = robot_frames(back)[name]
        assert np.allclose(other.rotation, pose.rotation, atol=1e-15) and np.array_equal(other.translation,
                                                                                           pose.translation)
    data = yaml.safe_load(text)
    assert robot_from_dict({k: v for k, v in data.items() if k != "convention"}).convention == "paper"
    for bad, where in (({**data, "lasers": [{"gamma": 0.1}]}, "lasers"),
                       ({**data, "convention": "craig"}, "convention")):
        with pytest.raises(InputError, match=where):
            robot_from_dict(bad)
    for frames, where in (({"camera": {}}, "frames"), ({"sensor": {"x": "a"}}, "frames.sensor.x"),
                          ({"sensor": {"qw": 0.1}}, "quaternion norm")):
        with pytest.raises(InputError, match=where):
            robot_frames(replace(robot, extra={"frames": frames}))


@pytest.mark.parametrize("kind", ["pose", "point"])
def test_lm_and_the_papers_ekf_reach_the_same_minimum(kind):
    robot = rig("standard")
    truth = np.zeros(len(chain_names(robot)))
    truth[[0, 2]] = 0.002, 0.005
    truth[-6:] = 0.003, -0.002, 0.001, 0.01, -0.01, 0.005
    samples = simulate(robot, truth, 40, 1, kind)
    model = PoseModel(robot, samples) if kind == "pose" else PointModel(robot, samples)
    fixed = tuple(n for n in model.names if n.startswith(("base_", "slm_")))
    fits = {method: estimate_model(model, EstimateOptions(method=method, spot_sigma=SIGMA_T, fixed=fixed,
                                                          ekf=EkfOptions(r=None)))
            for method in ("lm", "ekf")}
    free = fits["lm"].identifiable
    assert np.array_equal(free, fits["ekf"].identifiable) and fits["ekf"].fit.converged
    assert np.all(np.abs(fits["lm"].values - fits["ekf"].values)[free] < 1e-3 * fits["lm"].std[free])


def test_joint_effects_compose_with_the_pose_model():
    robot = rig("standard")
    samples = simulate(robot, np.zeros(len(chain_names(robot))), 12, 2, "pose")
    model = EffectModel(PoseModel(robot, samples, 0.5, True), [Periodic(joint=1), JointScale(joint=0)])
    x = np.random.default_rng(3).normal(0, 2, len(model.names)) * model.scales
    res = model.residuals(x)
    assert np.abs(central_jacobian(model, x) - res.jac).max() < 1e-6 * np.abs(res.jac).max()
    assert len(model.subset(np.arange(5)).samples) == 5 and model.subset(np.arange(5)).base.rotation_length == 0.5


def test_the_diagnosis_engine_selects_the_sensor_scale_on_point_data():
    """sensors.analysis runs diagnosis.run: no spot candidates, the sensor scale
    as an extra candidate, selected by the engine's rules when the sensor stretches."""
    robot = rig()
    samples = simulate(robot, np.zeros(len(chain_names(robot))), 80, 8, "point")
    stretched = replace(samples, position=samples.position * np.array([1.01, 0.995, 1.0]))
    options = SensorFitOptions(estimate=EstimateOptions(spot_sigma=SIGMA_T))
    data = sensor_data(robot, stretched, options)
    pool = [e for e in data.candidates() if supports(data.base(), e)]
    assert not any(isinstance(e, (ScreenShape, CameraDistortion)) for e in pool)
    diagnosis = diagnose(robot, stretched, options, DiagnoseOptions(spot_sigma=SIGMA_T, joint_sigma=0.0, max_effects=1))
    assert [e.label for e in diagnosis.final.effects] == ["sensor scale"]
    scale = next(e for e in diagnosis.parameters if e["name"] == "sensor_scale")["parameters"]
    # Only the differences of the axes' scales are observable (a common one the frames absorb).
    assert abs(scale[0]["value"] - 0.01) < 4.5 * scale[0]["std"]
    assert abs(scale[1]["value"] + 0.005) < 4.5 * scale[1]["std"]
    held = heldout_effects(robot, stretched, options, diagnosis.final.effects)
    assert np.mean(held.position) < np.mean(heldout_effects(robot, stretched, options, ()).position)


def test_calibrate_poses_says_a_still_joint_once(tmp_path, capsys):
    """A still joint is the data's, not a fit's: the frames-only and the full fit both
    find it, and the console and result.json say it once."""
    robot = rig("standard")
    save_sensor_samples(simulate(robot, np.zeros(len(chain_names(robot))), 40, 1, "pose", still=2),
                        tmp_path / "poses.csv")
    (tmp_path / "robot.yaml").write_text(dump_robot(robot))
    assert main(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "poses.csv"),
                 "--folds", "0", "--out", str(tmp_path / "out")]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "never moved" in line]
    assert len(lines) == 1 and lines[0].startswith("warning: q3 reads ")
    warnings = json.loads((tmp_path / "out" / "result.json").read_text())["warnings"]
    assert [w for w in warnings if "never moved" in w] == [lines[0].removeprefix("warning: ")]


def test_calibrate_poses_does_not_call_the_nominal_reference_a_failed_calibration(tmp_path, capsys):
    """Link lengths 6 and 5 cm off: the frames-only fit (the 'before' reference) misses the
    poses by over 10 mm RMS per value, the calibration fits them to the noise. The console
    said 'nominal (frames-only) fit: NOT A CALIBRATION: the calibrated model still misses...'
    (the tester's probe); a reference's miss is what calibration corrects, and the in-sample
    line states it."""
    robot = rig("standard")
    names = chain_names(robot)
    truth = np.zeros(len(names))
    truth[names.index("a2")], truth[names.index("d3")] = 0.06, -0.05
    save_sensor_samples(simulate(robot, truth, 40, 1, "pose"), tmp_path / "poses.csv")
    (tmp_path / "robot.yaml").write_text(dump_robot(robot))
    assert main(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "poses.csv"),
                 "--folds", "0", "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert result["insample"]["nominal_position_mm"]["rms"] > 10.0, result["insample"]
    assert "NOT A CALIBRATION" not in printed and not any("NOT A CALIBRATION" in w for w in result["warnings"])


def _errors(robot, seed: int, size: float = 1.0) -> np.ndarray:
    """A chain vector of D-H errors uniform within size x (10 mm, 1 deg), the frames as guessed."""
    truth = np.zeros(len(chain_names(robot)))
    truth[:robot.n_params] = np.random.default_rng(seed).uniform(-size, size, robot.n_params) * robot_scales(robot)
    return truth


def test_quaternions_written_in_xyzw_order_are_one_line_naming_the_columns(tmp_path):
    """ROS's and scipy's x,y,z,w under the file's qw,qx,qy,qz: refused when read (io/quaternion_order.py),
    not fitted into a NOT A CALIBRATION that blames the robot file; the file as written passes. Frames
    guessed a turn off change neither (the check fits them)."""
    from laser_calib.io.sensor_samples import load_sensor_samples

    robot = rig()
    for seed in range(3):
        truth = _errors(robot, seed)
        truth[robot.n_params:] = np.random.default_rng(seed).uniform(-0.5, 0.5, len(truth) - robot.n_params)
        samples = simulate(robot, truth, 30, seed, "pose")
        save_sensor_samples(samples, tmp_path / "good.csv")
        assert np.allclose(load_sensor_samples(tmp_path / "good.csv", robot).quaternion, samples.quaternion)
        swapped = replace(samples, quaternion=samples.quaternion[:, [1, 2, 3, 0]])
        save_sensor_samples(swapped, tmp_path / "xyzw.csv")
        with pytest.raises(InputError, match=r"xyzw\.csv: fields qw,qx,qy,qz: the orientations fit the arm only read "
                                             r"otherwise \(median rotation error [0-9.]+ deg as written, .* read in "
                                             r"x,y,z,w order .* or as the inverse rotations \(JPL's convention; negate "
                                             r"qx, qy, qz\).*: the orientations alone cannot tell these apart"):
            load_sensor_samples(tmp_path / "xyzw.csv", robot)
        # JPL's quaternions (Hamilton's conjugate) were advised to be reordered, and then failed
        save_sensor_samples(replace(samples, quaternion=samples.quaternion * [1, -1, -1, -1]), tmp_path / "jpl.csv")
        with pytest.raises(InputError, match=r"jpl\.csv: .* as the inverse rotations \(JPL's convention"):
            load_sensor_samples(tmp_path / "jpl.csv", robot)


def test_a_calibration_worse_than_the_robot_as_designed_on_held_out_poses_is_warned(tmp_path, capsys):
    """A robot built as designed: the calibration can only fit noise, and on 30 poses its 5-fold
    held-out position error exceeds the frames-only fit's (seed 6: 0.334 -> 0.358 mm). The figure is
    printed either way; the warning says what it means, on the console, in result.json and in the
    calibrated robot file (a CAUTION line of its header)."""
    robot = rig()
    (tmp_path / "robot.yaml").write_text(dump_robot(robot))
    save_sensor_samples(simulate(robot, _errors(robot, 6, 0.0), 30, 6, "pose"), tmp_path / "s.csv")
    assert main(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "s.csv"),
                 "--out", str(tmp_path / "out")]) == 0
    said = "5-fold held-out: the calibrated model misses these poses by more than the nominal D-H with its frames fitted"
    assert said in capsys.readouterr().err
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    assert any(w.startswith(said) for w in result["warnings"])
    # at the top of result.json too, as estimate writes it (it was a line among the warnings only)
    assert list(result)[:2] == ["failure", "caution"] and result["failure"] is None
    assert result["caution"].startswith(said)
    # and in the file written, which a user loads without the console (it was written as any calibration)
    assert f"\n# CAUTION: {said}" in (tmp_path / "out" / "robot_calibrated.yaml").read_text()
