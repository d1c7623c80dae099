"""The command line end to end: simulate, estimate, identify, slm-calibrate."""

import json
import math

import numpy as np
import pytest

from laser_calib.cli.main import main
from laser_calib.model.kinematics import rot_x, rot_y
from laser_calib.model.robot_file import load_robot
from laser_calib.sim.simulation import bundled_robot


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


@pytest.mark.parametrize("method", ["lm", "ekf"])
def test_estimate_writes_calibrated_robot_result_and_report(simulated, tmp_path, method):
    out = tmp_path / "est"
    code = main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"),
                 "--samples", str(simulated / "case2_cal.csv"), "--test", str(simulated / "case2_test.csv"),
                 "--method", method, "--spot-sigma", "0.0011547", "--joint-sigma", "0.001", "--out", str(out)])
    assert code == 0
    result = json.loads((out / "result.json").read_text())
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


def test_identify_prints_the_table(simulated, capsys):
    robot = simulated / "robot_nominal.yaml"
    assert main(["identify", "--robot", str(robot), "--samples", str(simulated / "case3_cal.csv")]) == 0
    out = capsys.readouterr().out
    assert "numerical rank: 33" in out and "all parameters identifiable" in out


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
    from laser_calib.slm import calibrate, load_measurements
    _, angles = calibrate(bundled_robot("paper-4dof"), load_measurements(tmp_path / "slm.csv"), sigma)
    lasers = load_robot(out).lasers
    for (gamma, beta), fitted, laser in zip(truth, angles, lasers):
        assert abs(fitted.gamma - gamma) < 4 * fitted.gamma_std and abs(fitted.beta - beta) < 4 * fitted.beta_std
        assert (laser.gamma, laser.beta) == (fitted.gamma, fitted.beta)
