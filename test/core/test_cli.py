"""The command line end to end: simulate, estimate, identify, slm-calibrate."""

import json
import math
import re
from dataclasses import replace

import numpy as np
import pytest

from laser_calib.cli.main import main
from laser_calib.io.errors import InputError
from laser_calib.model.kinematics import rot_x, rot_y
from laser_calib.model.robot_file import load_robot, save_robot
from laser_calib.io.samples import load_samples, save_samples
from laser_calib.session.estimate import estimate_options, run_calibration, run_diagnosis
from laser_calib.sim.simulation import NoiseSpec, bundled_robot, measure, sample_poses, true_errors
from wrong_robot import prismatic_mismatch


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "--case", "paper-7dof", "--seed", "12", "--out", str(out)]) == 0
    return out


def test_simulate_writes_the_papers_sets(simulated):
    names = {p.name for p in simulated.iterdir()}
    assert {"robot_nominal.yaml", "robot_true.yaml", "samples.csv", "case1_cal.csv", "case1_test.csv",
            "case2_cal.csv", "case2_test.csv", "case3_cal.csv", "truth.json"} <= names
    assert len((simulated / "case3_cal.csv").read_text().splitlines()) == 61


@pytest.mark.parametrize("case", ["paper-4dof", None])
def test_simulate_names_the_files_it_wrote(tmp_path, capsys, case):
    """Its line said 'case1..3 calibration/test sets' where case3 has only case3_cal.csv, and left
    out truth.csv: now the names of what it wrote, each once."""
    robot = [] if case else ["--robot", str(tmp_path / "robot.yaml")]
    if not case:
        save_robot(bundled_robot("paper-4dof"), tmp_path / "robot.yaml")
    assert main(["simulate", *(["--case", case] if case else robot), "--seed", "1", "--poses-per-span", "6",
                 "--out", str(tmp_path / "sim")]) == 0
    said = re.findall(r"\b[\w]+\.(?:yaml|csv|json)\b", capsys.readouterr().out.split("/: ", 1)[1])
    assert sorted(said) == sorted(p.name for p in (tmp_path / "sim").iterdir())


@pytest.mark.parametrize("low, high", [(0.2, 0.3), (-0.3, -0.2)])
def test_simulate_a_robot_whose_joint_range_lies_beyond_the_small_span(tmp_path, low, high):
    """A joint range 0.2 .. 0.3 rad misses the small span's +-10 deg about zero: its small-range
    poses keep to within 10 deg of the range's end nearest zero, inside the range."""
    robot = bundled_robot("paper-4dof")
    joints = list(robot.joints)
    joints[3] = replace(joints[3], min=low, max=high)
    save_robot(replace(robot, joints=tuple(joints)), tmp_path / "robot.yaml")
    out = tmp_path / "sim"
    assert main(["simulate", "--robot", str(tmp_path / "robot.yaml"), "--seed", "1", "--poses-per-span", "10",
                 "--out", str(out)]) == 0
    q4 = load_samples(out / "samples.csv").q[:, 3]
    assert len(q4) == 20 and np.all((q4 >= low) & (q4 <= high))


def test_result_json_says_where_the_spot_sigma_came_from(simulated, tmp_path):
    """Without --spot-sigma the options said spot_sigma_source 'given' (spot_sigma null)."""
    for name, given in (("estimated", []), ("given", ["--spot-sigma", "0.001"])):
        out = tmp_path / name
        assert main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"), "--samples",
                     str(simulated / "case2_cal.csv"), *given, "--out", str(out)]) == 0
        result = json.loads((out / "result.json").read_text())
        assert result["options"]["spot_sigma_source"] == name
        assert result["spot_sigma_estimated"] == (result["options"]["spot_sigma"] is None) == (not given)


def test_result_json_notes_the_errors_fix_held(simulated, tmp_path):
    """The errors --fix held were 'identifiable': false with no note, the field the README uses
    for what the data cannot separate; the data's own have theirs."""
    out = tmp_path / "est"
    assert main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"), "--samples",
                 str(simulated / "case2_cal.csv"), "--fix", "a1", "d1", "--out", str(out)]) == 0
    errors = {e["name"]: e for e in json.loads((out / "result.json").read_text())["errors"]}
    assert [errors[name]["note"] for name in ("a1", "d1")] == ["held at nominal: --fix"] * 2
    assert not errors["a1"]["identifiable"] and "note" not in errors["alpha1"]


@pytest.mark.parametrize("method", ["lm", "ekf"])
def test_estimate_writes_calibrated_robot_result_and_report(simulated, tmp_path, method):
    out = tmp_path / "est"
    code = main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"),
                 "--samples", str(simulated / "case2_cal.csv"), "--test", str(simulated / "case2_test.csv"),
                 "--method", method, "--spot-sigma", "0.0011547", "--joint-sigma", "0.001", "--out", str(out)])
    assert code == 0
    result = json.loads((out / "result.json").read_text())
    assert result["failure"] is None and result["caution"] is None
    assert [e["name"] for e in result["errors"]][:4] == ["a1", "d1", "alpha1", "theta1"]
    assert all(e["identifiable"] and e["std"] > 0 for e in result["errors"])
    truth = json.loads((simulated / "truth.json").read_text())["errors"]
    for entry in result["errors"]:  # 4.5 std: a 1-in-150000 event per error if the std is right
        assert abs(entry["value"] - truth[entry["name"]]) < 4.5 * entry["std"], entry
    for set_name in ("calibration", "test"):
        before, after = (result["spot_error"][set_name][k]["all"]["mean_mm"] for k in ("before", "after"))
        assert after < before / 10
    calibrated = load_robot(out / "robot_calibrated.yaml")
    nominal = load_robot(simulated / "robot_nominal.yaml")
    values = np.array([result["errors"][i]["value"] for i in range(33)])
    assert np.allclose(calibrated.vector(), nominal.vector() + values)
    report = (out / "report.md").read_text()
    assert "convergence.png" in report and (out / "convergence.png").stat().st_size > 10000
    residuals = np.genfromtxt(out / "residuals.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    test = residuals[residuals["set"] == "test"]
    assert len(residuals) == 60 and len(test) == 30
    # The table's per-pose distances are the ones the result's statistics summarise.
    assert math.isclose(np.nanmean(test["l1_distance_m"]) * 1e3, result["spot_error"]["test"]["after"]["laser1"]["mean_mm"])


def test_test_poses_beyond_the_calibrated_joint_ranges_are_named(simulated, tmp_path, capsys):
    """The paper's case 1: calibrated within +-10 deg of zero, tested over the whole
    workspace: every joint's test readings leave the calibrated range, which the
    console and result.json say per joint; the calibration's own poses as the test
    set leave nothing."""
    out = tmp_path / "case1"
    assert main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"), "--samples",
                 str(simulated / "case1_cal.csv"), "--test", str(simulated / "case1_test.csv"), "--out", str(out)]) == 0
    printed = capsys.readouterr().err
    said = [w for w in json.loads((out / "result.json").read_text())["warnings"]
            if "outside the range the calibration covered" in w]
    assert [w.split(" of the test poses have ")[1].split()[0] for w in said] == [f"q{i + 1}" for i in range(7)]
    assert all(f"warning: {w}" in printed for w in said)
    assert main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"), "--samples",
                 str(simulated / "case1_cal.csv"), "--test", str(simulated / "case1_cal.csv"),
                 "--out", str(tmp_path / "same")]) == 0
    assert "outside the range the calibration covered" not in capsys.readouterr().err


def test_a_plot_failing_in_the_drawing_child_is_raised_by_the_command(simulated, tmp_path, monkeypatch):
    """estimate draws its plots in a forked child (report.files.write_outputs); the
    child inherits this failure, exits 1, and the command draws again in its own
    process, so the error is the command's own, never lost in the child."""
    def broken(*_args, **_kwargs):
        raise RuntimeError("no room for the histogram")
    monkeypatch.setattr("laser_calib.report.files.plot_histogram", broken)
    with pytest.raises(RuntimeError, match="no room for the histogram"):
        main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"),
              "--samples", str(simulated / "case3_cal.csv"), "--out", str(tmp_path / "est")])


def test_the_true_model_on_noise_free_data_is_checked_not_refused(tmp_path, capsys):
    """A correct robot file on noise-free data (a user's sanity check of the pipeline) leaves spot
    distances of nanometres; the histogram's bins ran backwards from their 1 um floor and numpy's
    'zero-size array' or 'bins must increase' was said as bad input, exit 2, no files."""
    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--spot-noise", "0", "--joint-noise-deg", "0",
                 "--out", str(sim)]) == 0
    out = tmp_path / "est"
    assert main(["estimate", "--robot", str(sim / "robot_true.yaml"), "--samples", str(sim / "case2_cal.csv"),
                 "--test", str(sim / "case2_test.csv"), "--out", str(out)]) == 0
    assert "fitted exactly" in capsys.readouterr().err
    assert (out / "histogram.png").stat().st_size > 0


def test_the_true_model_on_noise_free_data_is_diagnosed_explained(tmp_path, capsys):
    """The same check through diagnose, the noise estimated: the likelihood of a residual of 0 has no
    maximum (numpy's 'divide by zero in log' on the console), and the estimated spot sigma of 0 was
    said as 'laser-calib diagnose: spot sigma must be a positive number of metres', exit 2."""
    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--spot-noise", "0", "--joint-noise-deg", "0",
                 "--out", str(sim)]) == 0
    out = tmp_path / "diag"
    capsys.readouterr()
    assert main(["diagnose", "--robot", str(sim / "robot_true.yaml"), "--samples", str(sim / "samples.csv"),
                 "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert "verdict: explained" in printed.out and "Warning" not in printed.err, printed
    assert json.loads((out / "diagnosis.json").read_text())["effects"] == []


@pytest.mark.parametrize("command", ["estimate", "diagnose"])
def test_one_pose_copied_onto_every_row_is_too_few_values(tmp_path, capsys, command):
    """A logger that wrote one sample 50 times: estimate said '27 mm -> 0.000 mm' and exit 0, diagnose
    'structure remains' with F = 7.7e+282. Copies neither determine nor check anything: the rows
    are counted as the one they copy."""
    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--out", str(sim)]) == 0
    samples = load_samples(sim / "samples.csv")
    copies = replace(samples, q=np.repeat(samples.q[:1], len(samples), 0),
                     spots=np.repeat(samples.spots[:1], len(samples), 0))
    save_samples(copies, tmp_path / "copies.csv")
    capsys.readouterr()
    assert main([command, "--robot", str(sim / "robot_nominal.yaml"), "--samples", str(tmp_path / "copies.csv"),
                 "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"laser-calib: {tmp_path / 'copies.csv'}: 4 measured values (not counting {len(samples) - 1} rows that copy "
        "another row exactly) reach only 4 of the model's 21 parameters and cannot determine and check even those; "
        "measure more poses or use the prior")
    assert not (tmp_path / "out").exists()


def test_repeated_poses_give_iso9283_repeatability(tmp_path):
    """30 poses each measured twice with Gaussian spot noise sigma: per laser, the two
    visits lie |d|/2 from their barycentre, so RP = |d|/2 (S_l = 0) with d ~ N(0, 2 sigma^2 I):
    E[RP] = sigma sqrt(pi)/2, std of the mean over 30 poses 0.463 sigma / sqrt(30)."""
    sigma, rng = 1e-3, np.random.default_rng(4)
    nominal = bundled_robot("paper-7dof")
    true = nominal.with_errors(true_errors(nominal, rng))
    q = sample_poses([nominal, true], 30, rng)
    measured, _ = measure(true, np.vstack([q, q]), rng, NoiseSpec(spot=sigma, joint=0.0, distribution="normal"))
    save_samples(replace(measured, pose=np.tile(np.arange(30), 2)), tmp_path / "twice.csv")
    save_robot(nominal, tmp_path / "robot.yaml")
    out = tmp_path / "est"
    assert main(["estimate", "--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "twice.csv"),
                 "--spot-sigma", str(sigma), "--out", str(out)]) == 0
    iso = json.loads((out / "result.json").read_text())["iso9283_spot"]["calibration"]
    for laser in ("laser1", "laser2"):
        seen = iso[laser]["poses"]
        assert seen >= 25 and iso[laser]["visits"] == 2 * seen
        expected, spread = sigma * math.sqrt(math.pi) / 2 * 1e3, 0.463 * sigma / math.sqrt(seen) * 1e3
        assert abs(iso[laser]["RP"]["mean"] - expected) < 4 * spread, iso[laser]


def test_residuals_csv_says_which_spots_were_fitted_rejected_or_refused(tmp_path):
    """Nothing measured is lost: a spot the robust rule rejected and one refused before the fit
    (outside the screen) keep their rows, each laser's _fit column saying what became of it."""
    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--out", str(sim)]) == 0
    samples = load_samples(sim / "case3_cal.csv")
    robot = load_robot(sim / "robot_nominal.yaml")
    spots = samples.spots.copy()
    spots[3, 0] += 0.2                                            # 200 mm off: an outlier
    spots[7, 1] = [0.0, 1.5 * robot.screen.half_z]                # beyond the screen's edge
    save_samples(replace(samples, spots=spots), tmp_path / "bad.csv")
    assert main(["estimate", "--robot", str(sim / "robot_nominal.yaml"), "--samples", str(tmp_path / "bad.csv"),
                 "--out", str(tmp_path / "out")]) == 0
    rows = np.genfromtxt(tmp_path / "out" / "residuals.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    status = {(int(r["pose"]), j): str(r[f"l{j}_fit"]) for r in rows for j in (1, 2)}
    assert status.pop((int(samples.pose[3]), 1)) == "rejected" and status.pop((int(samples.pose[7]), 2)) == "refused"
    assert set(status.values()) == {"fitted"}


def test_a_minimum_that_lost_measurements_exits_3_with_its_files(tmp_path, capsys):
    """A revolute joint marked prismatic: the fit moves two beams off the screen to drop
    them. That is no calibration: an error line and exit 3, as for NOT CONVERGED."""
    sim, wrong = prismatic_mismatch(tmp_path)
    out = tmp_path / "out"
    assert main(["estimate", "--robot", str(wrong), "--samples", str(sim / "samples.csv"), "--out", str(out)]) == 3
    assert any(line.startswith("error: NOT A CALIBRATION: the fit lost") for line in capsys.readouterr().err.splitlines())
    assert "NO CALIBRATION: NOT A CALIBRATION" in (out / "robot_calibrated.yaml").read_text()
    assert (out / "result.json").exists()
    # The nodes' path (the Estimate service, the Calibrate action, the sequencer) says it as success false.
    outcome = run_calibration(load_robot(wrong), load_samples(sim / "samples.csv"),
                              estimate_options("lm", 0.0, False, True), None)
    assert outcome.calibration.failure.startswith("NOT A CALIBRATION: the fit lost")
    # With its diagnosis (the nodes' estimate.diagnose), which starts from that fit and refuses the robot file:
    # said beside the failure, not instead of it (the session ended with exit 2, as for bad input, unsaid)
    diagnosed = run_calibration(load_robot(wrong), load_samples(sim / "samples.csv"),
                                estimate_options("lm", 0.0, False, True), None, diagnose=True)
    assert diagnosed.calibration.failure == outcome.calibration.failure
    assert diagnosed.message.startswith(outcome.calibration.summary() + "; diagnosis skipped: robot: the nominal model's "
                                        "beams meet the screen at "), diagnosed.message


def test_a_miss_the_estimated_joint_noise_takes_up_is_no_calibration(tmp_path, capsys):
    """Joint 3 of the 4-DOF arm marked prismatic, 8 poses, plain least squares, both sigmas
    estimated: a joint-reading sigma of 5.6 deg takes up the misfit, the spot sigma is 6.5 mm, and
    the spot sigma was all the residual-level check saw: exit 0 for a model missing its spots by
    69 mm (mean). The raw residual is what the model misses (estimation.failures.residual_level)."""
    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--poses-per-span", "8", "--out", str(sim)]) == 0
    robot = load_robot(sim / "robot_nominal.yaml")
    joints = list(robot.joints)
    joints[2] = replace(joints[2], prismatic=True)
    save_robot(replace(robot, joints=tuple(joints)), tmp_path / "wrong.yaml")
    capsys.readouterr()
    out = tmp_path / "out"
    assert main(["estimate", "--robot", str(tmp_path / "wrong.yaml"), "--samples", str(sim / "case1_cal.csv"),
                 "--no-robust", "--out", str(out)]) == 3
    err = capsys.readouterr().err
    assert "error: NOT A CALIBRATION: the calibrated model still misses the measurements by" in err, err
    assert json.loads((out / "result.json").read_text())["joint_sigma_estimated"]


def test_spots_out_of_step_with_the_joint_readings_are_no_calibration(tmp_path, capsys):
    """Each pose's spots paired with the previous pose's joint readings (a sync fault): the
    fit misses the spots by hundreds of mm, which no camera does (estimation.failures.
    MAX_RESIDUAL). Before, that was exit 0 and a calibration file (this session: every
    parameter held, the residual 0.4 m). No spot here is an outlier of the others (all miss
    by hundreds of mm), so the robust rule rejects none and the fit is plain least squares's,
    which also moves some beams off the screen and stops unconverged: more failure lines,
    each one."""
    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-7dof", "--seed", "1", "--out", str(sim)]) == 0
    samples = load_samples(sim / "case3_cal.csv")
    lagged = type(samples)(samples.pose[1:], samples.stamp[1:], samples.q[1:], samples.spots[:-1])
    save_samples(lagged, tmp_path / "lagged.csv")
    out = tmp_path / "out"
    assert main(["estimate", "--robot", str(sim / "robot_nominal.yaml"), "--samples", str(tmp_path / "lagged.csv"),
                 "--out", str(out)]) == 3
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error: ")]
    assert any("NOT A CALIBRATION: the calibrated model still misses the measurements by" in e for e in errors), errors
    assert all(e.startswith(("error: NOT A CALIBRATION: ", "error: NOT CONVERGED: ")) for e in errors), errors
    assert "NO CALIBRATION: NOT A CALIBRATION" in (out / "robot_calibrated.yaml").read_text()
    # the honest file of the same poses is a calibration
    assert main(["estimate", "--robot", str(sim / "robot_nominal.yaml"), "--samples", str(sim / "case3_cal.csv"),
                 "--out", str(tmp_path / "honest")]) == 0


def test_calibrate_poses_with_a_wrong_joint_type_is_no_calibration(tmp_path, capsys):
    """The real UR10e's elbow marked prismatic in its URDF: before, exit 0 with a
    calibrated URDF 0.9 m off its poses."""
    from pathlib import Path
    real = Path(__file__).resolve().parents[2] / "data" / "real" / "ur10e_mocap"
    urdf = tmp_path / "prismatic.urdf"
    urdf.write_text((real / "ur10_robot.urdf").read_text().replace('name="elbow_joint" type="revolute"',
                                                                     'name="elbow_joint" type="prismatic"'))
    assert main(["calibrate-poses", "--robot", str(urdf), "--base", "base_link", "--tip", "wrist_3_link",
                 "--samples", str(real / "calibration.csv"), "--out", str(tmp_path / "out")]) == 3
    assert "error: NOT A CALIBRATION: the calibrated model still misses" in capsys.readouterr().err


@pytest.mark.parametrize("poses_per_span", [25, 10, 8])
def test_diagnose_on_a_wrong_robot_file_says_the_fit_moved_the_beams_off_the_screen(tmp_path, capsys, poses_per_span):
    """A revolute joint marked prismatic: the nominal model's beams meet the screen, but the
    geometric fit moves them off it, and the fit the diagnosis starts from there has no spot
    or too few to fit (which, of a wrong model's fit, differs between machines' BLAS). Not
    the data's words ("no measured spot", "measure more poses"): one line naming the robot
    file and what to check in it, exit 2. At 20 poses the outlier screening's estimate
    refused every spot its wrong minimum's beams missed, and said "no measured spot"."""
    sim, wrong = prismatic_mismatch(tmp_path, poses_per_span)
    capsys.readouterr()
    out = tmp_path / "out"
    assert main(["diagnose", "--robot", str(wrong), "--samples", str(sim / "samples.csv"), "--out", str(out)]) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("laser-calib")]
    assert len(errors) == 1 and errors[0].startswith(f"laser-calib: {wrong}: the nominal model's beams meet the screen "
                                                     "at "), errors
    assert re.search(r", but the fit moved (every beam off it|all but \d+ beams off it, too few to fit \d+ "
                     r"parameters): the robot model is likely wrong; check its joint types, axes and units$", errors[0])
    assert not out.exists()
    # The nodes' path (the Estimate service or Calibrate action with diagnose) refuses it as bad input too.
    with pytest.raises(InputError, match="^robot: the nominal model's beams meet the screen"):
        run_diagnosis(load_robot(wrong), load_samples(sim / "samples.csv"), estimate_options("lm", 0.0, False, True),
                      None)


def test_estimate_on_a_wrong_robot_file_is_no_calibration_not_missing_spots(tmp_path, capsys):
    """The same wrong file, 20 poses: the nominal model refuses 7 spots as impossible, and
    the minimum reached is judged again for them; it had moved every other beam off the
    screen too, and the second fit refused those as well and said "no measured spot to
    fit" (exit 2, the data blamed). The judging again only readmits: the first fit's loss
    is NOT A CALIBRATION (exit 3), its files written."""
    sim, wrong = prismatic_mismatch(tmp_path, 10)
    capsys.readouterr()
    assert main(["estimate", "--robot", str(wrong), "--samples", str(sim / "samples.csv"),
                 "--out", str(tmp_path / "out")]) == 3
    captured = capsys.readouterr()
    assert "no measured spot" not in captured.err
    assert "error: NOT A CALIBRATION: " in captured.err and (tmp_path / "out" / "result.json").exists()


def test_diagnose_with_every_spot_missing_says_so(simulated, tmp_path, capsys):
    """Where the spots really are missing, the words stay the data's, naming the file (as estimate's)."""
    samples = load_samples(simulated / "samples.csv")
    save_samples(replace(samples, spots=np.full_like(samples.spots, np.nan)), tmp_path / "none.csv")
    assert main(["diagnose", "--robot", str(simulated / "robot_nominal.yaml"), "--samples", str(tmp_path / "none.csv"),
                 "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"laser-calib: {tmp_path / 'none.csv'}: no measured spot (every spot field empty)"]


def test_a_diagnosis_whose_final_fit_is_no_calibration_says_so_in_its_files(tmp_path):
    """A real diagnosis whose final fit is marked NOT CONVERGED (no small data set found makes
    the diagnosis's own fits fail while its folds succeed): its JSON, report and calibrated
    robot file say it is no calibration, as `diagnose` then exits 3 (cli/diagnose.py)."""
    from laser_calib.diagnosis.engine import DiagnoseOptions, diagnose, write_outputs
    from laser_calib.sim.simulation import paper_session

    session = paper_session("paper-4dof", seed=1, n_per_span=8)
    diagnosis = diagnose(session.nominal, session.samples, options=DiagnoseOptions(method="lm", max_effects=0))
    assert diagnosis.failure is None
    final = diagnosis.stages[-1]
    stopped = "NOT CONVERGED: lm stopped after 100 iterations; the values are not a minimum"
    estimate = replace(final.fitted.estimate, warnings=final.fitted.estimate.warnings + (stopped,))
    failed = replace(diagnosis, stages=diagnosis.stages[:-1] + (replace(final, fitted=replace(final.fitted,
                                                                                              estimate=estimate)),))
    assert failed.failure == stopped
    result = write_outputs(failed, tmp_path)
    assert result["failure"] == stopped == json.loads((tmp_path / "diagnosis.json").read_text())["failure"]
    assert f"**Error: {stopped}.**" in (tmp_path / "report.md").read_text()
    assert f"NO CALIBRATION: {stopped}" in (tmp_path / "robot_calibrated.yaml").read_text()


def test_estimate_names_test_spots_where_the_robot_files_screen_surface_extrapolates(tmp_path, capsys):
    """The paper's case 1: calibrated on small-range poses, tested over the whole workspace.
    With a screen surface in the robot file, the test spots beyond the calibration spots'
    hull are predicted by extrapolation, and estimate says so, as diagnose does."""
    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--out", str(sim)]) == 0
    with_screen = tmp_path / "with_screen.yaml"
    with_screen.write_text((sim / "robot_nominal.yaml").read_text() + "effects:\n  - {type: screen_shape, half_y: "
                           "1.0, half_z: 1.0, u: 0.0, v: 0.0, uu: 0.0, uv: 0.0, vv: 0.0}\n")
    args = ["estimate", "--samples", str(sim / "case1_cal.csv"), "--test", str(sim / "case1_test.csv")]
    assert main(args + ["--robot", str(with_screen), "--out", str(tmp_path / "surface")]) == 0
    said = [line for line in capsys.readouterr().err.splitlines() if "outside the convex hull" in line]
    assert len(said) == 1 and said[0].startswith("warning: test: ") and "screen_shape" in said[0]
    assert main(args + ["--robot", str(sim / "robot_nominal.yaml"), "--out", str(tmp_path / "flat")]) == 0
    assert "outside the convex hull" not in capsys.readouterr().err  # a flat screen is known everywhere


def test_identify_prints_the_table(simulated, capsys):
    robot = simulated / "robot_nominal.yaml"
    assert main(["identify", "--robot", str(robot), "--samples", str(simulated / "case3_cal.csv")]) == 0
    out = capsys.readouterr().out
    assert "numerical rank: 33" in out and "all parameters identifiable" in out


def test_identify_where_no_beam_reaches_the_screen_is_one_line(simulated, tmp_path, capsys):
    """Both lasers turned away from the screen: identify printed '0 spots ... numerical rank: 0',
    exit 0, where estimate refuses the same files."""
    import yaml
    data = yaml.safe_load((simulated / "robot_nominal.yaml").read_text())
    data["lasers"] = [{"gamma": 3.0, "beta": 0.0}, {"gamma": -3.0, "beta": 0.0}]
    robot = tmp_path / "away.yaml"
    robot.write_text(yaml.safe_dump(data))
    samples = simulated / "case3_cal.csv"
    assert main(["identify", "--robot", str(robot), "--samples", str(samples)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"laser-calib: {robot}: no measured spot of {samples} is reached: at every one the nominal model's beam misses "
        "the screen; check the joint readings' units (radians; metres for a prismatic joint) and the robot file "
        "(lengths in metres, joint zeros, the laser module, the screen)"]


def test_plan_for_a_robot_without_lasers_names_its_file(tmp_path, capsys):
    robot_path = tmp_path / "robot.yaml"
    save_robot(replace(bundled_robot("paper-4dof"), lasers=()), robot_path)
    assert main(["plan", "--robot", str(robot_path), "--n", "10", "--out", str(tmp_path / "poses.csv")]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"laser-calib: {robot_path}: pose planning needs a robot with joints and the two-laser module ('slm:' and "
        "'lasers:')"]


@pytest.mark.parametrize("field, value, says", [
    ("u", "1e11", "1e+11 m is not a plausible spot coordinate on the fixture (over 100 m): lengths are in metres "
                  "(this looks like millimetres)"),
    ("v", "500", "500 m is not a plausible spot coordinate on the fixture (over 100 m): lengths are in metres (this "
                 "looks like millimetres or centimetres)")])
def test_slm_spot_coordinates_beyond_any_fixture_are_refused(tmp_path, capsys, field, value, says):
    """u = 1e11 m (a typo) gave beta +0.0005 +- 0.009 deg where the slope says 1.15 deg, exit 0."""
    rows = ["laser,distance,u,v"] + [f"{j},{d},{0.02 * d},{(0.5 if j == 1 else -0.7) * d}"
                                     for j in (1, 2) for d in (0.5, 1.0, 1.5)]
    first = dict(zip(("laser", "distance", "u", "v"), rows[1].split(",")), **{field: value})
    rows[1] = ",".join(first.values())
    (tmp_path / "slm.csv").write_text("\n".join(rows) + "\n")
    robot_path = tmp_path / "robot.yaml"
    save_robot(bundled_robot("paper-4dof"), robot_path)
    assert main(["slm-calibrate", "--robot", str(robot_path), "--measurements", str(tmp_path / "slm.csv"),
                 "--out", str(tmp_path / "out.yaml")]) == 2
    assert capsys.readouterr().err.splitlines() == [f"laser-calib: {tmp_path / 'slm.csv'}: line 2, field {field}: {says}"]


def test_slm_calibrate_recovers_the_laser_angles(tmp_path, capsys):
    """Spots at three fixture distances, noise 0.1 mm; the angles of eq. 16."""
    rng = np.random.default_rng(0)
    truth = [(math.radians(-27.80), math.radians(1.27)), (math.radians(31.07), math.radians(0.82))]
    sigma = 1e-4
    rows = ["laser,distance,u,v"]
    for j, (gamma, beta) in enumerate(truth):
        direction = rot_x(gamma) @ rot_y(beta) @ np.array([0.0, 0.0, 1.0])
        offset = rng.uniform(-0.05, 0.05, 2)
        for distance in (0.5, 0.75, 1.0, 1.25):
            u, v = offset + distance * direction[:2] / direction[2] + rng.normal(0, sigma, 2)
            rows.append(f"{j + 1},{distance},{float(u)!r},{float(v)!r}")
    (tmp_path / "slm.csv").write_text("\n".join(rows) + "\n")
    robot_path = tmp_path / "robot.yaml"
    from laser_calib.model.robot_file import save_robot
    save_robot(bundled_robot("paper-4dof"), robot_path)
    out = tmp_path / "robot_slm.yaml"
    assert main(["slm-calibrate", "--robot", str(robot_path), "--measurements", str(tmp_path / "slm.csv"),
                 "--spot-sigma", str(sigma), "--out", str(out)]) == 0
    assert capsys.readouterr().err == ""  # no spot rejected, no warning
    from laser_calib.slm import calibrate, load_measurements
    angles = calibrate(bundled_robot("paper-4dof"), load_measurements(tmp_path / "slm.csv"), sigma).angles
    lasers = load_robot(out).lasers
    for (gamma, beta), fitted, laser in zip(truth, angles, lasers):
        assert abs(fitted.gamma - gamma) < 4 * fitted.gamma_std and abs(fitted.beta - beta) < 4 * fitted.beta_std
        assert (laser.gamma, laser.beta) == (fitted.gamma, fitted.beta)


def test_slm_calibrate_of_a_robot_with_a_module_but_no_lasers_is_one_line(tmp_path, capsys):
    """A robot file with 'slm:' and no 'lasers:' (import-positioner writes one) was an IndexError
    traceback, exit 1, at the nominal angles' check."""
    robot_path = tmp_path / "robot.yaml"
    save_robot(replace(bundled_robot("paper-4dof"), lasers=()), robot_path)
    rows = ["laser,distance,u,v"] + [f"{j},{d},{0.02 * d},{(0.5 if j == 1 else -0.7) * d}"
                                     for j in (1, 2) for d in (0.5, 1.0, 1.5)]
    (tmp_path / "slm.csv").write_text("\n".join(rows) + "\n")
    assert main(["slm-calibrate", "--robot", str(robot_path), "--measurements", str(tmp_path / "slm.csv"),
                 "--out", str(tmp_path / "out.yaml")]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"laser-calib: {robot_path}: has no laser module ('slm:' and 'lasers:'): slm-calibrate writes the robot "
        "file with its lasers' angles; give the robot with its SLM"]


@pytest.mark.parametrize("argv", [["bag"], ["--rate", "20", "bag", "--topics", "samples", "/test_samples", "--quiet"],
                                  ["bag", "--exclude", "/spots", "--wait-for", "samples", "--wait-timeout", "2.5"]])
def test_replay_hands_its_options_to_the_node_as_parsed(argv):
    """`laser-calib replay` takes the replay node's arguments (one definition) and hands them on
    whole: before, it knew --rate only, and --topics or --wait-for were refused."""
    import argparse
    from laser_calib.cli.arguments import add_replay_arguments, replay_argv
    parser = argparse.ArgumentParser()
    add_replay_arguments(parser)
    parsed = parser.parse_args(argv)
    assert parser.parse_args(replay_argv(parsed)) == parsed


@pytest.mark.parametrize("flags, spot_sigma, joint_sigma", [
    ([], 0.0, -1.0), (["--spot-sigma", "0.001"], 0.001, -1.0), (["--joint-sigma", "0"], 0.0, 0.0),
    (["--joint-sigma", "0.002"], 0.0, 0.002), (["--spot-sigma", "0.001", "--joint-sigma", "0.002"], 0.001, 0.002)])
def test_the_ros_noise_values_give_the_command_lines_options(tmp_path, flags, spot_sigma, joint_sigma):
    """The estimator node's spot_sigma and joint_sigma (parameters, or an Estimate request's), whose
    'not given' are 0 and -1 (a ROS parameter cannot be None), make the options that `laser-calib
    estimate` makes of --spot-sigma and --joint-sigma: without --joint-sigma, the joint-reading
    sigma is estimated with the spot sigma when that is estimated, else 0; --joint-sigma 0 is none."""
    from laser_calib.cli.main import _options, build_parser
    args = build_parser().parse_args(["estimate", "--robot", "r.yaml", "--samples", "s.csv",
                                      "--out", str(tmp_path / "out"), *flags])
    assert estimate_options("lm", spot_sigma, False, True, joint_sigma) == _options(args)


@pytest.mark.parametrize("value", [-3.0, -0.5, 0.6, math.nan, math.inf])
def test_a_ros_joint_sigma_that_is_no_joint_noise_is_refused(value):
    with pytest.raises(InputError, match=r"^joint_sigma: .* is not a plausible joint-reading noise .*, or 0 for none, "
                                         r"or -1 for not given"):
        estimate_options("lm", 0.0, False, True, value)
