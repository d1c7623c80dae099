"""The diagnosis: each library effect found on both arms and its size recovered;
nothing added to data without effects; structure reported for effects outside
the library; noise from repeated poses; the command line and its files.

Effects are sized by visibility (effects.truth.sized): the chi^2 excess they
leave in the geometric fit, so that every case is equally visible whatever the
arm's lever arms; random signs and shapes come from the seed.
"""

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats
from scipy.spatial import Delaunay

from cli_status import exit_status
from laser_calib.cli.main import main as cli_main
from laser_calib.diagnosis.detector import MAX_PERMUTATIONS
from laser_calib.diagnosis.engine import diagnose, write_outputs
from laser_calib.diagnosis.compensator import load_compensator
from laser_calib.diagnosis.options import EXPLAINED, STRUCTURE, UNDETERMINED, DiagnoseOptions
from laser_calib.diagnosis.verdict import WORSE_ON_TEST
from laser_calib.diagnosis.writer import robot_header
from laser_calib.effects.effect_model import EffectModel
from laser_calib.measurement.spot import SpotModel
from laser_calib.effects import Backlash, Compliance, Drift, JointScale, Periodic, calibrated_model
from laser_calib.effects.catalog import camera_distortion, effects_to_yaml, screen_shape
from laser_calib.effects.joint import gravity_torques
from laser_calib.estimation.estimate import EstimateOptions
from laser_calib.sim.effect_truth import (TEMPERATURE, ForeignError, ForeignJointError, draw_truth, effect_session, hooks,
                                      sized, true_offsets_rms)
from laser_calib.model.robot_file import load_robot, save_robot
from laser_calib.session.estimate import estimate_options, run_calibration
from laser_calib.io.samples import Samples, load_samples, save_samples
from laser_calib.sim.simulation import NoiseSpec, bundled_robot, measure, sample_poses, true_errors

NOISE = NoiseSpec(spot=0.5e-3, joint=float(np.deg2rad(0.02)))
VISIBLE = 200.0
SEED = 11

# Placements: a joint where the effect shows (scale and periodic: a joint with a
# wide range; compliance: a joint whose gravity torque changes), a length, the
# screen and the camera.
LIBRARY = {
    "paper-7dof": {"joint_scale": lambda r, c: JointScale(joint=4),
                   "compliance": lambda r, c: Compliance.make(r, c, 3),
                   "periodic": lambda r, c: Periodic(joint=0),
                   "backlash": lambda r, c: Backlash(joint=5),
                   "drift": lambda r, c: Drift.make(r, c, "slm_x", "stamp"),
                   "screen_shape": lambda r, c: screen_shape(r),
                   "camera_distortion": lambda r, c: camera_distortion(r)},
    "paper-4dof": {"joint_scale": lambda r, c: JointScale(joint=3),
                   "compliance": lambda r, c: Compliance.make(r, c, 1),
                   "periodic": lambda r, c: Periodic(joint=3),
                   "backlash": lambda r, c: Backlash(joint=2),
                   "drift": lambda r, c: Drift.make(r, c, "a2", TEMPERATURE),
                   "screen_shape": lambda r, c: screen_shape(r),
                   "camera_distortion": lambda r, c: camera_distortion(r)},
}


def diagnose_main(argv: list[str]) -> int:
    return cli_main(["diagnose", *argv])


def library_session(arm, kind, n_cal=80, n_test=40, seed=SEED, visible=VISIBLE):
    def make(robot, errors, context, rng):
        return [sized(robot, errors, context, draw_truth(LIBRARY[arm][kind](robot, context), rng), NOISE, visible)]

    return effect_session(arm, seed, make, n_cal, n_test, NOISE)


# The held-out error with the selection nested in the folds is 6x the time and changes no verdict, effect
# or evidence (only its figure and a note): tested by the command line's test.
UNNESTED = DiagnoseOptions(nested=False)


def run(session, **kw):
    kw.setdefault("options", UNNESTED)
    return diagnose(session.nominal, session.cal, session.test, spot_sigma=NOISE.spot_sigma,
                    joint_sigma=NOISE.joint_sigma, **kw)


def not_worse_on_test(diagnosis) -> bool:
    """One-sided Wilcoxon over test poses: the final model's squared spot
    distances are not significantly larger than the geometric fit's (p >= 0.01)."""
    first, last = diagnosis.stages[0].test, diagnosis.stages[-1].test
    both = np.isfinite(first) & np.isfinite(last)
    difference = (np.where(both, last, 0.0) ** 2 - np.where(both, first, 0.0) ** 2).sum(axis=1)
    difference = difference[difference != 0]
    return len(difference) < 6 or stats.wilcoxon(difference, alternative="greater").pvalue >= 0.01


@pytest.mark.parametrize("arm, kind", [(arm, kind) for arm in LIBRARY for kind in LIBRARY[arm]])
def test_library_effect_is_found_and_its_size_recovered(arm, kind):
    session = library_session(arm, kind)
    truth = session.truth[0]
    diagnosis = run(session)
    assert [e.label for e in diagnosis.final.effects] == [truth.effect.label]
    report = diagnosis.parameters[0]
    reported = [(k, p) for k, p in enumerate(report["parameters"]) if p["value"] is not None]
    assert reported, "every parameter reported as inseparable"
    for k, p in reported:
        assert abs(p["value"] - truth.values[k]) < 4 * p["std"], (p, truth.values[k])
    for p in report["parameters"]:
        assert (p["value"] is None) == ("note" in p)
    # An effect the data cannot tell from another is never the explanation, and the robot file says
    # which member it holds (the 4-DOF compliance of joint 2 and a periodic error of it, at this seed).
    header = robot_header(diagnosis, diagnosis.to_json())
    for group in (p for p in diagnosis.parameters if not p["determined"]):
        assert diagnosis.verdict != EXPLAINED and f"Not one cause: {group['group']}" in header
    # A screen surface is known where the calibration spots are: the test spots beyond them are counted.
    if kind == "screen_shape":
        spots = session.test.spots[session.test.seen]
        beyond = int((Delaunay(session.cal.spots[session.cal.seen]).find_simplex(spots) < 0).sum())
        named = [n for n in diagnosis.notes if "outside the convex hull of the calibration spots" in n]
        assert len(named) == (1 if beyond else 0)
        assert not named or named[0].startswith(f"{beyond} of {len(spots)} test spots")
    # Held-out error goes down on the calibration poses (cross-validated) and on the test poses.
    cv = [stage.fitted.cv for stage in diagnosis.stages]
    assert np.nanmean(cv[-1] ** 2) < np.nanmean(cv[0] ** 2)
    assert not_worse_on_test(diagnosis)


def test_a_test_set_the_effects_do_not_carry_over_to_is_warned_of():
    """The calibration poses have a joint scale error, the test poses (the same robot and commanded
    poses, measured again) do not: the diagnosis finds the scale on the calibration poses, and
    applying it misses the test poses by more than the geometric model does. That is said in
    diagnosis.json's warnings (the console's and the report's); on a test set like the calibration
    set it is not."""
    scaled = library_session("paper-4dof", "joint_scale")
    unscaled = effect_session("paper-4dof", SEED, lambda r, e, c, rng: [], 80, 40, NOISE)
    diagnosis = run(replace(scaled, test=unscaled.test))
    assert [e.kind for e in diagnosis.final.effects] == ["joint_scale"]
    warned = [w for w in diagnosis.to_json()["warnings"] if w.startswith(WORSE_ON_TEST)]
    assert len(warned) == 1, diagnosis.to_json()["warnings"]
    assert not diagnosis.failure
    assert not run(scaled).warnings


@pytest.mark.parametrize("arm", list(LIBRARY))
def test_data_without_effects_is_explained_and_nothing_is_added(arm):
    session = effect_session(arm, SEED, lambda r, e, c, rng: [], 80, 40, NOISE)
    diagnosis = run(session)
    assert diagnosis.verdict == EXPLAINED, diagnosis.evidence
    assert diagnosis.final.effects == ()
    assert len(diagnosis.stages) == 1
    # nothing in the residual: the sequential permutation test stopped before its last batch
    assert diagnosis.detection.p > diagnosis.options.alpha
    assert diagnosis.detection.permutations < MAX_PERMUTATIONS


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_one_pose_measured_again_and_again_is_pure_noise():
    """The spot position was the measured one, whose noise is the residual's own: one pose
    measured 40 times, spot noise alone, 'followed spot_z' at p = 1e-26 (eta^2 0.86) and the
    verdict was 'structure remains' (a new user's probe). The covariate is now where the model
    puts the spot. The screen spline over its spots, all in two places, kept a mode of bending
    -4e-16 (the eigensolver's rounding), whose prior printed numpy's 'invalid value encountered in
    sqrt' (CI's log)."""
    robot = bundled_robot("paper-7dof")
    rng = np.random.default_rng(5)
    true = robot.with_errors(true_errors(robot, rng))
    q = np.repeat(sample_poses([robot, true], 1, rng, "whole"), 40, axis=0)
    samples, _ = measure(true, q, rng, NoiseSpec(spot=1e-3, joint=0.0))
    diagnosis = diagnose(robot, samples, options=UNNESTED)
    assert diagnosis.verdict != STRUCTURE, diagnosis.evidence


def step(robot, joint):
    """A joint offset that jumps halfway through the session (a slipped coupling)."""
    return ForeignJointError("step", joint, lambda s: np.where(s.stamp > s.stamp.max() / 2, 1e-3, 0.0))


def coupling(robot, joint):
    """The joint follows the next joint's reading (a cable-driven joint)."""
    return ForeignJointError("coupling", joint, lambda s: 1e-3 * s.q[:, joint + 1])


# Joint 2 on both arms: its next joint is not parallel to it (on the 4-DOF arm,
# joints 3 and 4 are, and a joint-3 error following q4 is a joint-4 scale error).
@pytest.mark.parametrize("arm, outside", [(arm, o) for arm in LIBRARY for o in (step, coupling)])
def test_effect_outside_the_library_leaves_structure(arm, outside):
    def make(robot, errors, context, rng):
        return [sized(robot, errors, context, outside(robot, 1), NOISE, VISIBLE)]

    session = effect_session(arm, SEED, make, 80, 40, NOISE)
    diagnosis = run(session)
    assert diagnosis.verdict == STRUCTURE
    assert diagnosis.after.tests[0].p_adjusted < diagnosis.options.alpha
    assert not_worse_on_test(diagnosis)


def test_a_text_column_is_tested_as_categories():
    """Every other pose measured on a second fixture that turns joint 2 (a text column,
    conventions.md: offered to residual analysis): the structure analysis names the
    fixture, and the verdict is not "explained". Without the column, nothing names it."""
    def make(robot, errors, context, rng):
        on_b = ForeignJointError("fixture B", 1, lambda s: 1e-3 * (s.pose % 2))
        return [sized(robot, errors, context, on_b, NOISE, VISIBLE)]

    session = effect_session("paper-4dof", SEED, make, 80, 40, NOISE)
    fixture = np.where(session.cal.pose % 2, "B", "A")
    labelled = replace(session, cal=replace(session.cal, labels={"fixture": fixture}))
    diagnosis = run(labelled)
    found = [t for t in diagnosis.before.tests if t.covariate == "fixture" and t.p_adjusted < diagnosis.options.alpha]
    assert found and found[0].covariate_unit == "category", [t.sentence() for t in diagnosis.before.tests[:5]]
    assert diagnosis.verdict != EXPLAINED
    assert not [t for t in run(session).before.tests if t.covariate == "fixture"]


def repeated_session(arm, truth, seed=SEED, n=40, repeats=2):
    """Poses measured ``repeats`` times in a row (the readings repeat exactly)."""
    rng = np.random.default_rng(seed)
    nominal = bundled_robot(arm)
    errors = true_errors(nominal, rng)
    true = nominal.with_errors(errors)
    q = np.repeat(sample_poses([nominal, true], n, rng), repeats, axis=0)
    stamps = 10.0 * np.arange(len(q))
    context = Samples(np.arange(len(q)), stamps, q, np.full((len(q), 2, 2), np.nan))
    offsets, transform = hooks([sized(nominal, errors, context, t, NOISE, VISIBLE) for t in truth(nominal)])
    samples, _ = measure(true, q, rng, NOISE, stamps, None, offsets, transform)
    return nominal, samples


@pytest.mark.parametrize("arm", list(LIBRARY))
def test_noise_level_from_repeated_poses(arm):
    """Without --spot-sigma, the scatter of repeated poses gives the noise and
    the lack-of-fit test of the level; a coupling the library lacks is flagged."""
    nominal, samples = repeated_session(arm, lambda robot: [])
    diagnosis = diagnose(nominal, samples, options=UNNESTED)
    assert diagnosis.noise.level_test == "lack-of-fit F"
    assert diagnosis.noise.repeat_dof > 0
    assert diagnosis.verdict == EXPLAINED, diagnosis.evidence
    nominal, samples = repeated_session(arm, lambda robot: [coupling(robot, 1)])
    assert diagnose(nominal, samples, options=UNNESTED).verdict == STRUCTURE


def test_command_line_writes_diagnosis_robot_and_report(tmp_path):
    session = library_session("paper-4dof", "backlash", n_cal=60, n_test=30)
    save_robot(session.nominal, tmp_path / "robot.yaml")
    save_samples(session.cal, tmp_path / "cal.csv")
    save_samples(session.test, tmp_path / "test.csv")
    out = tmp_path / "out"
    status = diagnose_main(["--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "cal.csv"),
                            "--test", str(tmp_path / "test.csv"), "--spot-sigma", str(NOISE.spot_sigma),
                            "--joint-sigma", str(NOISE.joint_sigma), "--out", str(out)])
    assert status == 0
    result = json.loads((out / "diagnosis.json").read_text())
    assert [s["model"] for s in result["stages"]] == ["geometric", "geometric + backlash (joint 3)"]
    for stage in result["stages"]:
        for key in ("cal", "cv", "test"):
            assert set(stage[key]) >= {"mean_mm", "rms_mm", "max_mm"}
    assert result["effects"][0]["name"] == "backlash" and result["effects"][0]["where"] == "joint 3"
    assert {"name", "value", "std"} <= set(result["effects"][0]["parameters"][0])
    assert result["verdict"] in (EXPLAINED, STRUCTURE) and result["evidence"]
    # The command line always gives the held-out error with the selection nested in the folds.
    assert result["heldout_nested"]["n"] == result["stages"][-1]["cv"]["n"]
    report = (out / "report.md").read_text()
    assert "![residual](residual.png)" in report and (out / "residual.png").exists()
    # The 4-DOF arm's merged errors are said as estimate says them (only the JSON and the file's header did).
    held = f"not separable: the data determine 19 of the 21 geometric errors; held at nominal before every fit, " \
           f"reported as combinations: {', '.join(result['not_identifiable'])}"
    assert held in result["warnings"] and held in report and len(result["not_identifiable"]) == 2
    # The chosen form's tests, in the report and the JSON (the 10 strongest, strongest first).
    assert "## Specification of the chosen form" in report
    adjusted = [v["p_adjusted"] for v in result["specification"]]
    assert len(adjusted) == 10 and adjusted == sorted(adjusted)
    # The calibrated robot file predicts the test poses as the final model did.
    robot = load_robot(out / "robot_calibrated.yaml")
    assert robot.extra["effects"][0]["type"] == "backlash"
    test = load_samples(tmp_path / "test.csv", robot)
    model, x = calibrated_model(robot, test)
    res = model.residuals(x, False)
    rms = np.sqrt(np.mean(np.linalg.norm(res.r, axis=-1)[res.valid] ** 2)) * 1e3
    assert rms == pytest.approx(result["stages"][-1]["test"]["rms_mm"], rel=1e-6)


def test_the_final_fits_warnings_reach_the_console_the_json_and_the_report(tmp_path, capsys):
    """A spot sigma given 10x too small: the final fit's chi^2 warning, which `estimate` prints,
    was in none of the diagnosis's outputs (only a failure was)."""
    session = library_session("paper-4dof", "backlash", n_cal=40, n_test=5)
    save_robot(session.nominal, tmp_path / "robot.yaml")
    save_samples(session.cal, tmp_path / "cal.csv")
    out = tmp_path / "out"
    status = diagnose_main(["--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "cal.csv"),
                            "--spot-sigma", str(NOISE.spot_sigma / 10), "--joint-sigma", str(NOISE.joint_sigma),
                            "--out", str(out)])
    assert status == 0
    warnings = json.loads((out / "diagnosis.json").read_text())["warnings"]
    assert any(w.startswith("chi^2/dof = ") for w in warnings), warnings
    printed = [line[len("warning: "):] for line in capsys.readouterr().err.splitlines() if line.startswith("warning: ")]
    assert printed == warnings
    report = (out / "report.md").read_text()
    assert all(f"**Warning:** {w}." in report for w in warnings)
    # the nodes' estimate with its diagnosis: the line they log names the verdict and those warnings
    options = estimate_options("lm", NOISE.spot_sigma / 10, False, True)
    outcome = run_calibration(session.nominal, session.cal, replace(options, joint_sigma=NOISE.joint_sigma), None,
                              diagnose=True)
    verdict = json.loads(outcome.diagnosis_json)["verdict"]
    assert f"; diagnosis: {verdict}; diagnosis's final fit: chi^2/dof = " in outcome.message and outcome.warned


@pytest.mark.parametrize("given", [False, True])
def test_the_final_fits_warnings_say_where_its_spot_sigma_came_from(given, tmp_path, capsys):
    """A large periodic error: the geometric fit's residual is 4x the spot noise. With --spot-sigma
    (4x the noise too) the final fit's warnings say the sigma was given and its residual is far
    below it. Without it, the final fit runs at the noise of its own residual (Fitter.at_noise):
    nothing is held for noise and no line calls its residual far below the sigma. Before, it ran
    at the geometric fit's: parameters held and 'far below the spot sigma the diagnosis estimated
    from the geometric fit's residual' (and before that, 'given')."""
    session = library_session("paper-4dof", "periodic", n_cal=40, n_test=5, visible=5000.0)
    save_robot(session.nominal, tmp_path / "robot.yaml")
    save_samples(session.cal, tmp_path / "cal.csv")
    sigma = ["--spot-sigma", "0.002"] if given else []
    assert diagnose_main(["--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "cal.csv"), *sigma,
                          "--out", str(tmp_path / "out")]) == 0
    printed = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning: ")]
    if given:
        held = [line for line in printed if "rank deficient" in line]
        assert len(held) == 1 and "parameters at the spot sigma given (" in held[0], printed
        assert any("far below the spot sigma given, " in line for line in printed), printed
    else:
        assert not any("far below" in line or "rank deficient" in line or "given" in line for line in printed), printed


@pytest.mark.parametrize("args, text", [
    (["--samples", "missing.csv"], "missing.csv"),
    (["--spot-sigma", "-1"], "positive"),
    (["--folds", "1"], "folds"),
])
def test_command_line_bad_input_exits_2_with_one_line(tmp_path, capsys, args, text):
    save_robot(bundled_robot("paper-4dof"), tmp_path / "robot.yaml")
    session = effect_session("paper-4dof", 1, lambda r, e, c, rng: [], 12, 4, NOISE)
    save_samples(session.cal, tmp_path / "cal.csv")
    base = {"--robot": str(tmp_path / "robot.yaml"), "--samples": str(tmp_path / "cal.csv"),
            "--out": str(tmp_path / "out")}
    for key, value in zip(args[::2], args[1::2]):
        base[key] = value
    argv = [item for pair in base.items() for item in pair]
    status = exit_status(["diagnose", *argv])  # argparse rejects some values itself
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2
    assert text in err[-1]


def test_test_set_without_a_calibration_covariate_is_bad_input():
    session = library_session("paper-4dof", "drift", n_cal=60, n_test=20)
    test = Samples(session.test.pose, session.test.stamp, session.test.q, session.test.spots, {})
    with pytest.raises(ValueError, match=TEMPERATURE):
        diagnose(session.nominal, session.cal, test, spot_sigma=NOISE.spot_sigma)


def test_written_outputs_are_plain_json(tmp_path):
    session = library_session("paper-7dof", "periodic", n_cal=60, n_test=20)
    diagnosis = run(session)
    result = write_outputs(diagnosis, tmp_path)
    text = (tmp_path / "diagnosis.json").read_text()
    assert "NaN" not in text and json.loads(text) == json.loads(json.dumps(result))


def test_too_few_poses_to_select_effects_adds_none_and_says_so():
    """20 effect-free 7-DOF poses: a 5-fold training set of 16 poses (64 values)
    barely determines 33 errors; selecting on it once added a chance 'backlash'."""
    session = effect_session("paper-7dof", SEED, lambda r, e, c, rng: [], 20, 10, NOISE)
    diagnosis = run(session)
    assert diagnosis.final.effects == () and len(diagnosis.stages) == 1
    assert any("too few poses to select effects" in note for note in diagnosis.notes)


def test_outside_effect_with_only_the_spot_sigma_given_is_not_explained():
    """Issue 13's 7-DOF case: the joint-reading noise, estimated, absorbs a
    coupling the library lacks; the flexible detector still sees it and names
    the readings it follows."""
    def make(robot, errors, context, rng):
        return [sized(robot, errors, context, coupling(robot, 1), NOISE, VISIBLE)]

    session = effect_session("paper-7dof", SEED, make, 80, 40, NOISE)
    diagnosis = diagnose(session.nominal, session.cal, session.test, spot_sigma=NOISE.spot_sigma, options=UNNESTED)
    assert diagnosis.noise.level_test is None
    assert diagnosis.detection.p <= diagnosis.options.alpha, diagnosis.evidence
    # significant only after every permutation is drawn (an early stop has p >= 10 / 999)
    assert diagnosis.detection.permutations == MAX_PERMUTATIONS
    assert diagnosis.verdict == STRUCTURE
    top = [name for name, _, _ in diagnosis.detection.importance[:4]]
    assert {"q2", "q3"} & set(top), top


def stops_short(robot, joint):
    """The joint stops short of where it was sent by a share of the move (a servo
    that settles inside its dead band against friction): the reading is where it
    was sent. The sign of the move alone is backlash, which takes part of it."""
    return ForeignJointError("stops short", joint,
                             lambda s: -1e-3 * np.diff(s.q[:, joint], prepend=0.0))


@pytest.mark.parametrize("arm", list(LIBRARY))
def test_an_error_following_the_size_of_the_last_move_is_seen_and_named(arm):
    """Before the detector had the size of each joint's last move among its inputs
    (only its sign), these were p 0.42 (4-DOF) and 0.25 (7-DOF); the 4-DOF arm's joint 3
    at seed 12 was p 0.29 and "explained"."""
    def make(robot, errors, context, rng):
        return [sized(robot, errors, context, stops_short(robot, 1), NOISE, VISIBLE)]

    session = effect_session(arm, SEED, make, 80, 40, NOISE)
    diagnosis = diagnose(session.nominal, session.cal, session.test, spot_sigma=NOISE.spot_sigma, options=UNNESTED)
    assert diagnosis.detection.p <= diagnosis.options.alpha, diagnosis.evidence
    assert diagnosis.verdict == STRUCTURE
    assert diagnosis.detection.importance[0][0] == "step2", diagnosis.detection.importance[:3]


def test_learned_compensator_is_saved_loaded_and_predicts_as_in_the_diagnosis(tmp_path):
    def make(robot, errors, context, rng):
        return [sized(robot, errors, context, coupling(robot, 1), NOISE, VISIBLE)]

    session = effect_session("paper-4dof", SEED, make, 80, 40, NOISE)
    # every unit fitted on both sides, as `estimate --no-robust` below fits them (at this seed the
    # robust rule would leave one spot of the coupling's far end out of the diagnosis)
    diagnosis = run(session, options=DiagnoseOptions(nested=False, robust=False))
    assert diagnosis.compensator is not None, diagnosis.evidence
    result = write_outputs(diagnosis, tmp_path)
    assert result["compensator"]["file"] == "compensator.json"
    compensator = load_compensator(tmp_path / "compensator.json")
    model = EffectModel(SpotModel(session.nominal, session.test), diagnosis.final.effects)
    spots = compensator.predict(model)
    d = np.linalg.norm(session.test.spots - spots, axis=-1)
    assert np.allclose(d[session.test.seen], diagnosis.compensated_test[session.test.seen], atol=1e-12)
    # It never stands in for a physical effect: the calibrated robot file is the physical model alone.
    assert "compensator" not in load_robot(tmp_path / "robot_calibrated.yaml").extra
    # `estimate` applies it: on the nominal robot with the diagnosis's effects (the model it was made
    # for, docs/effects.md), it refits the errors with the compensation, holding what the diagnosis held
    # (the file's model.held: the user gave them with --fix, and without it the compensation's offsets
    # made d4 and slm_z barely separable: d4 written 48 mm), and predicts the test poses as the diagnosis did.
    effects = effects_to_yaml(diagnosis.final.effects, diagnosis.final.model.split(diagnosis.final.estimate.values)[1])
    save_robot(replace(session.nominal, extra={**session.nominal.extra, "effects": effects}), tmp_path / "robot.yaml")
    save_samples(session.cal, tmp_path / "cal.csv")
    save_samples(session.test, tmp_path / "test.csv")
    args = ["estimate", "--samples", str(tmp_path / "cal.csv"), "--test", str(tmp_path / "test.csv"),
            "--spot-sigma", str(NOISE.spot_sigma), "--joint-sigma", str(NOISE.joint_sigma), "--no-robust",
            "--compensator", str(tmp_path / "compensator.json")]
    assert diagnosis.merged and set(compensator.held) == set(diagnosis.merged)
    assert cli_main(args + ["--robot", str(tmp_path / "robot.yaml"), "--out", str(tmp_path / "e")]) == 0
    estimated = json.loads((tmp_path / "e" / "result.json").read_text())
    assert estimated["compensator"]["targets"] == result["compensator"]["targets"]
    held = {e["name"]: e for e in estimated["errors"] if e["name"] in diagnosis.merged}
    assert all(e["value"] is None and "compensator's fit" in e["note"] for e in held.values()), held
    assert any("as the fit of the compensator" in w for w in estimated["warnings"]), estimated["warnings"]
    assert not any("makes the calibration worse" in w for w in estimated["warnings"]), estimated["warnings"]
    # Another unit of the arm, without the coupling: the compensator's offsets are errors its fit cannot
    # remove (0.43 -> 0.65 mm, nothing said): the same fit without it is better, and the warning says so.
    other_unit = effect_session("paper-4dof", SEED + 1, lambda *_: [], 80, 40, NOISE)
    save_samples(other_unit.cal, tmp_path / "other_cal.csv")
    save_samples(other_unit.test, tmp_path / "other_test.csv")
    assert cli_main(args[:1] + ["--samples", str(tmp_path / "other_cal.csv"), "--test", str(tmp_path / "other_test.csv")]
                    + args[5:] + ["--robot", str(tmp_path / "robot.yaml"), "--out", str(tmp_path / "o")]) == 0
    warned = [w for w in json.loads((tmp_path / "o" / "result.json").read_text())["warnings"]
              if "makes the calibration worse than the same fit without it" in w]
    assert len(warned) == 1 and "calibration RMS" in warned[0] and "test RMS" in warned[0], warned
    assert estimated["spot_error"]["test"]["after"]["all"]["mean_mm"] == pytest.approx(
        np.nanmean(diagnosis.compensated_test) * 1e3, rel=1e-6)
    # Made for that model: a robot file with another effect is not it (one line, exit 2).
    other = effects + [{"type": "backlash", "joint": 1, "b": 0.0}]
    save_robot(replace(session.nominal, extra={**session.nominal.extra, "effects": other}), tmp_path / "other.yaml")
    assert cli_main(args + ["--robot", str(tmp_path / "other.yaml"), "--out", str(tmp_path / "n")]) == 2


def test_a_link_length_following_another_joint_is_compensated_through_its_own_direction(tmp_path):
    """A hose that winds with joint 1 pulls link 2's offset d2 (no library effect has a length
    following a joint): the detector regresses the residual on each link's length directions
    too, so the compensator carries d2 as a function of q1 and comes within issue 13's 25 % of
    the model that knows the true offsets."""
    def hose(robot, samples):
        out = np.zeros((len(samples), robot.n_params))
        out[:, robot.param_names.index("d2")] = np.cos(samples.q[:, 0] + 0.5)
        return out

    def make(robot, errors, context, rng):
        return [sized(robot, errors, context, ForeignError("d2 ~ cos(q1 + 0.5)", hose), NOISE, VISIBLE)]

    session = effect_session("paper-4dof", SEED, make, 80, 40, NOISE)
    diagnosis = run(session)
    assert diagnosis.verdict != EXPLAINED, diagnosis.evidence
    compensator = diagnosis.compensator
    assert compensator is not None, diagnosis.evidence
    assert [t for t, u in zip(compensator.targets, compensator.used) if u] == ["d2"]
    assert diagnosis.detection.importance[0][0] == "q1", diagnosis.detection.importance
    true_rms = true_offsets_rms(session, session.truth[0], EstimateOptions(spot_sigma=NOISE.spot_sigma,
                                                                           joint_sigma=NOISE.joint_sigma))
    compensated = diagnosis.compensated_test[session.test.seen]
    assert np.sqrt(np.mean(compensated ** 2)) * 1e3 <= 1.25 * true_rms
    # A file written before the length directions (version 1: angle targets, "coef_rad") still loads.
    compensator.save(tmp_path / "v2.json")
    old = json.loads((tmp_path / "v2.json").read_text())
    old["version"], old["coef_rad"] = 1, old.pop("coef")
    (tmp_path / "v1.json").write_text(json.dumps(old))
    assert np.array_equal(load_compensator(tmp_path / "v1.json").coef, compensator.coef)


def test_estimate_fits_the_effects_of_the_robot_file(tmp_path):
    """A robot file with an ``effects:`` key is the model with those effects: `estimate` fits
    their parameters with the geometric errors (from the file's values) and writes them back."""
    session = library_session("paper-4dof", "backlash")
    truth = session.truth[0]
    start = truth.effect.to_yaml(np.zeros(len(truth.values)))
    save_robot(replace(session.nominal, extra={**session.nominal.extra, "effects": [start]}), tmp_path / "robot.yaml")
    save_samples(session.cal, tmp_path / "cal.csv")
    assert cli_main(["estimate", "--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "cal.csv"),
                     "--spot-sigma", str(NOISE.spot_sigma), "--joint-sigma", str(NOISE.joint_sigma),
                     "--out", str(tmp_path / "e")]) == 0
    entry = json.loads((tmp_path / "e" / "result.json").read_text())["errors"][-1]
    assert entry["name"] == truth.effect.names[0] and entry["unit"] == "rad"
    assert abs(entry["value"] - truth.values[0]) < 4 * entry["std"]
    written = load_robot(tmp_path / "e" / "robot_calibrated.yaml").extra["effects"]
    assert written == [truth.effect.to_yaml(np.array([entry["value"]]))]


def test_estimated_noise_far_above_the_rated_noise_is_structure():
    """The robot file says its encoders read to 0.002 deg; the data scatter as
    0.02 deg joint noise would, which the maximum-likelihood estimate finds.
    Rated at what the simulated encoders do, the one-sided likelihood-ratio test passes."""
    session = effect_session("paper-4dof", SEED, lambda r, e, c, rng: [], 80, 40, NOISE)

    def rated(sigma):
        return replace(session.nominal, extra={**session.nominal.extra, "joint_reading_sigma": sigma})

    diagnosis = diagnose(rated(float(np.deg2rad(0.002))), session.cal, session.test, spot_sigma=NOISE.spot_sigma,
                         options=UNNESTED)
    assert diagnosis.verdict == STRUCTURE
    assert "robot file says the hardware can do" in diagnosis.evidence
    honest = diagnose(rated(NOISE.joint_sigma), session.cal, session.test, spot_sigma=NOISE.spot_sigma,
                      options=UNNESTED)
    assert honest.verdict == EXPLAINED, honest.evidence
    (component, _, limit, p), = honest.noise.excess
    assert component == "joint-reading" and limit == NOISE.joint_sigma and p >= honest.options.alpha


def test_untested_level_and_too_few_poses_for_the_detector_is_undetermined():
    session = effect_session("paper-4dof", SEED, lambda r, e, c, rng: [], 20, 10, NOISE)
    diagnosis = diagnose(session.nominal, session.cal, session.test, spot_sigma=NOISE.spot_sigma, options=UNNESTED)
    assert diagnosis.verdict == UNDETERMINED, diagnosis.evidence
    assert "too few for the detector" in diagnosis.evidence


def test_overstated_noise_is_no_test_of_the_level():
    """Sigmas given ten times the real ones: chi^2 at 1 % of its dof passes whatever remains, so with
    too few poses for the detector the verdict is undetermined, as with the level untested (it said
    'explained', helper probe), and the evidence says the sigmas are overstated; given right, the
    level is tested and the same poses are explained."""
    session = effect_session("paper-4dof", SEED, lambda r, e, c, rng: [], 20, 10, NOISE)
    over = diagnose(session.nominal, session.cal, session.test, spot_sigma=10 * NOISE.spot_sigma,
                    joint_sigma=10 * NOISE.joint_sigma, options=UNNESTED)
    assert over.verdict == UNDETERMINED and "the sigmas given are overstated" in over.evidence, over.evidence
    right = diagnose(session.nominal, session.cal, session.test, spot_sigma=NOISE.spot_sigma,
                     joint_sigma=NOISE.joint_sigma, options=UNNESTED)
    assert right.verdict == EXPLAINED and "overstated" not in right.evidence, right.evidence


def test_a_library_effect_standing_in_for_a_foreign_one_is_not_explained():
    """Issue 13: a stiffness that changes with another joint's angle (a counterbalance
    spring): compliance approximates it, the residual level passes, and the
    specification test of the chosen form names the parameter that is not constant."""
    def varying_stiffness(robot, samples):
        offsets = np.zeros((len(samples.q), robot.n_params))
        offsets[:, robot.param_names.index("theta4")] = gravity_torques(robot, samples.q)[:, 3] * (
            1 + 0.8 * np.sin(samples.q[:, 0]))
        return offsets

    def make(robot, errors, context, rng):
        return [sized(robot, errors, context, ForeignError("stiffness of joint 4 ~ q1", varying_stiffness),
                      NOISE, VISIBLE)]

    session = effect_session("paper-4dof", SEED, make, 80, 40, NOISE)
    diagnosis = run(session)
    assert diagnosis.verdict == STRUCTURE, diagnosis.evidence
    top = diagnosis.specification[0]
    assert top.p_adjusted < diagnosis.options.alpha, diagnosis.evidence
    assert (top.parameter in ("theta4", "compliance4") and top.covariate == "q1"), top.sentence()
    assert "varies with q1" in diagnosis.evidence



def test_the_final_models_stds_are_at_the_noise_of_its_own_residual():
    """No noise given: the reference noise model, estimated from the geometric fit's residual,
    holds a strong effect's misfit (here the spot sigma about 3 times the noise), and the final
    model's standard deviations were that many times too wide. They are at the noise of the final
    residual: as wide as with the true noise given, within what a sigma estimated from some 300
    degrees of freedom can miss (about 4 % per standard deviation; 0.8-1.25 is over 5 of them)."""
    session = library_session("paper-7dof", "periodic", visible=2000.0)
    options = DiagnoseOptions(nested=False, compensate=False)
    given = run(session, options=options)
    estimated = diagnose(session.nominal, session.cal, session.test, options=options)
    assert [e.label for e in estimated.final.effects] == [e.label for e in given.final.effects] == \
        [session.truth[0].effect.label]
    stds = [np.array([p["std"] for p in d.parameters[0]["parameters"]]) for d in (given, estimated)]
    assert np.all((0.8 < stds[1] / stds[0]) & (stds[1] / stds[0] < 1.25)), stds
