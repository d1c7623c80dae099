"""A calibration's figures are over the measurements it fitted: a spot or pose the
robust rule rejected, or one refused before the fit, is reported apart (its count and
errors), not averaged into what the calibration achieved; its row stays in
residuals.csv with its status. A test set's figures stay over all its spots."""

import json
import math
from dataclasses import replace

import numpy as np

from laser_calib.cli.main import main
from laser_calib.io.samples import load_samples, save_samples
from laser_calib.io.sensor_samples import save_sensor_samples
from laser_calib.measurement.chain import chain_names
from laser_calib.model.robot_file import dump_robot, load_robot
from laser_calib.session.estimate import estimate_options, run_calibration
from test_sensors import SIGMA_T, rig, simulate


def _rows(path):
    return np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8")


def test_estimate_figures_are_over_the_spots_fitted(tmp_path, capsys):
    """The tester's two probes in one file: a spot 0.3 m off (rejected) and a pose's
    spots typed in mm (refused). Before, the headline averaged them in (1.7 mm became
    7.8 mm, or 25 m); now the calibration's figures are over the fitted spots, and the
    rejected and refused ones have their own entry, console lines and report table."""
    sim = tmp_path / "sim"
    assert main(["simulate", "--case", "paper-4dof", "--seed", "5", "--out", str(sim)]) == 0
    samples = load_samples(sim / "case2_cal.csv")
    spots = samples.spots.copy()
    spots[4, 0, 0] += 0.3                    # 300 mm off: an outlier the robust rule rejects
    spots[2] *= 1e3                          # both spots typed in mm: outside the screen, refused
    save_samples(replace(samples, spots=spots), tmp_path / "bad.csv")
    out = tmp_path / "out"
    capsys.readouterr()
    assert main(["estimate", "--robot", str(sim / "robot_nominal.yaml"), "--samples", str(tmp_path / "bad.csv"),
                 "--test", str(sim / "case2_test.csv"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    result = json.loads((out / "result.json").read_text())
    rows = _rows(out / "residuals.csv")
    cal, test = rows[rows["set"] == "calibration"], rows[rows["set"] == "test"]

    def distances_mm(table, status, model=""):
        return np.concatenate([table[f"{model}l{j}_distance_m"][table[f"l{j}_fit"] == status] * 1e3 for j in (1, 2)])

    fitted = result["spot_error"]["calibration"]
    assert fitted["after"]["all"]["n"] == int(samples.seen.sum()) - 3
    for model, label in (("", "after"), ("nominal_", "before")):   # residuals.csv, result.json agree
        assert math.isclose(fitted[label]["all"]["mean_mm"], distances_mm(cal, "fitted", model).mean())
    assert fitted["after"]["all"]["max_mm"] < 10.0                  # noise of +-2 mm, not the 0.3 m spot
    not_fitted = result["spot_error_not_fitted"]
    assert sorted(not_fitted) == ["refused", "rejected"]
    assert not_fitted["refused"]["after"]["all"]["n"] == 2 and not_fitted["rejected"]["after"]["all"]["n"] == 1
    assert math.isclose(not_fitted["rejected"]["after"]["all"]["max_mm"], distances_mm(cal, "rejected").max())
    assert not_fitted["rejected"]["after"]["all"]["max_mm"] > 250.0
    # the test set is poses the fit never saw: all its spots count
    assert result["spot_error"]["test"]["after"]["all"]["n"] == int(np.isfinite(test["l1_distance_m"]).sum()
                                                                    + np.isfinite(test["l2_distance_m"]).sum())

    headline = next(line for line in printed if line.startswith("calibration  mean spot error"))
    after = fitted["after"]["all"]
    assert f"-> {after['mean_mm']:.3f} mm" in headline and f"{after['n']} spots fitted" in headline
    assert any(line.startswith("calibration  rejected, not fitted: ") and "1 spots)" in line for line in printed)
    assert any(line.startswith("calibration  refused, not fitted: ") and "2 spots)" in line for line in printed)
    report = (out / "report.md").read_text()
    assert f"| calibration | after | 1 | {fitted['after']['laser1']['n']} | " in report
    assert "| calibration, rejected | after | 1 | 1 | " in report
    assert "| calibration, refused | after | 2 | 1 | " in report

    # the nodes' summary line (the Estimate service's message) says the same
    outcome = run_calibration(load_robot(sim / "robot_nominal.yaml"), load_samples(tmp_path / "bad.csv"),
                              estimate_options("lm", 0.0, False, True), None)
    assert f"{fitted['after']['all']['n']} spots fitted, 1 rejected, 2 refused" in outcome.calibration.summary()


def test_calibrate_poses_residuals_say_which_poses_were_rejected_and_its_figures_leave_them_out(tmp_path, capsys):
    """One point 0.3 m off: the robust fit rejects it. residuals.csv's 'fit' column says so
    (before: no column said it); the in-sample figures are over the fitted poses (before:
    its max was the rejected pose's), the rejected one's in insample_not_fitted."""
    robot = rig()
    samples = simulate(robot, np.zeros(len(chain_names(robot))), 40, 9, "point")
    position = samples.position.copy()
    position[11] += 0.3 * np.array([0.6, -0.8, 0.0])
    save_sensor_samples(replace(samples, position=position), tmp_path / "points.csv")
    (tmp_path / "robot.yaml").write_text(dump_robot(robot))
    capsys.readouterr()
    assert main(["calibrate-poses", "--robot", str(tmp_path / "robot.yaml"), "--samples", str(tmp_path / "points.csv"),
                 "--sigma", str(SIGMA_T), "--folds", "0", "--out", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    result = json.loads((tmp_path / "out" / "result.json").read_text())
    rows = _rows(tmp_path / "out" / "residuals.csv")
    assert result["rejected_poses"] == [11]
    status = dict(zip(rows["pose"].tolist(), rows["fit"].tolist()))
    assert status.pop(11) == "rejected" and set(status.values()) == {"fitted"}

    fitted, rejected = rows["fit"] == "fitted", rows["fit"] == "rejected"
    insample = result["insample"]["position_mm"]
    assert insample["n"] == 39 and math.isclose(insample["max"], rows["position_m"][fitted].max() * 1e3)
    assert insample["max"] < 5.0                                       # noise of 0.2 mm, not the 0.3 m point
    apart = result["insample_not_fitted"]["rejected"]["position_mm"]
    assert apart["n"] == 1 and math.isclose(apart["max"], rows["position_m"][rejected].max() * 1e3)
    assert "in-sample (39 poses fitted) position error" in printed
    assert "in-sample, rejected poses not fitted (1) position error" in printed
