"""Pose planning: constraints, the D-criterion with the full noise, the poses file."""

import io
from pathlib import Path

import numpy as np
import pytest
import yaml

from laser_calib.cli import main as cli
from laser_calib.model.kinematics import predict
from laser_calib.model.robot_file import load_robot
from laser_calib.planning import PRIOR, PlanOptions, candidate_poses, d_optimal, plan, whitened_jacobians
from laser_calib.session.poses import format_poses
from laser_calib.model.robot_file import save_robot
from laser_calib.report.progress import Progress
from laser_calib.sim.simulation import bundled_robot

ROOT = Path(__file__).resolve().parents[2]

SPOT, JOINT = 2e-3 / np.sqrt(3), np.deg2rad(0.1) / np.sqrt(3)


@pytest.fixture
def run():
    """The command line's entry point (exit status, one line on bad input)."""
    return cli.main


def log_det(g: np.ndarray) -> float:
    info = PRIOR * np.eye(g.shape[2]) + np.einsum("pik,pil->kl", g, g)
    return float(np.linalg.slogdet(info)[1])


def test_whitened_jacobian_carries_spot_and_joint_noise():
    robot = bundled_robot("paper-7dof")
    q = candidate_poses(robot, 3, np.random.default_rng(1), 0.1)
    g = whitened_jacobians(robot, q, SPOT, JOINT)
    p = predict(robot, q, jacobian=True)
    scales = np.where(np.arange(robot.n_params) % 4 < 2, 0.010, np.deg2rad(1.0))
    scales[-5:] = [0.010, 0.010, np.deg2rad(1), np.deg2rad(1), np.deg2rad(1)]
    for k in range(len(q)):
        j = p.jacobian[k].reshape(4, -1) * scales
        jq = p.jacobian[k].reshape(4, -1)[:, 3:4 * robot.n_joints:4]
        cov = SPOT ** 2 * np.eye(4) + JOINT ** 2 * jq @ jq.T
        assert np.allclose(g[k].T @ g[k], j.T @ np.linalg.solve(cov, j), rtol=1e-9, atol=1e-9)


def test_plan_respects_limits_and_screen_and_beats_random_designs():
    robot = bundled_robot("paper-7dof")
    options = PlanOptions(12, SPOT, JOINT, candidates=400, margin=0.1, seed=3)
    result = plan(robot, options)
    assert result.q.shape == (12, 7) and len({tuple(r) for r in result.q}) == 12
    assert np.all(result.q >= robot.q_min) and np.all(result.q <= robot.q_max)
    spots = predict(robot, result.q)
    assert spots.hit.all() and np.all(np.abs(spots.spots) <= 1.0 - 0.1)
    # The same candidates drawn at random, many times: the plan's criterion is above all of them.
    q = candidate_poses(robot, 400, np.random.default_rng(3), 0.1)
    g = whitened_jacobians(robot, q, SPOT, JOINT)[:, :, result.free]
    rng = np.random.default_rng(0)
    best_random = max(log_det(g[rng.choice(400, 12, replace=False)]) for _ in range(50))
    assert result.log_det == pytest.approx(log_det(whitened_jacobians(robot, result.q, SPOT, JOINT)[:, :, result.free]))
    assert result.log_det > best_random
    greedy, greedy_value = d_optimal(g, 12, passes=0)
    assert result.log_det >= greedy_value - 1e-9 and log_det(g[greedy]) == pytest.approx(greedy_value)


def test_joint_noise_steers_the_plan_to_shorter_beams():
    robot = bundled_robot("paper-7dof")
    full = plan(robot, PlanOptions(15, SPOT, JOINT, candidates=500, seed=1))
    naive = plan(robot, PlanOptions(15, SPOT, 0.0, candidates=500, seed=1))
    # Long beams turn the joint disturbance into spot motion: the full noise model avoids them.
    assert predict(robot, full.q).k.mean() < predict(robot, naive.q).k.mean()


def test_plan_command_writes_the_pose_list(run, tmp_path, capsys):
    out = tmp_path / "poses.csv"
    robot_file = tmp_path / "robot.yaml"
    save_robot(bundled_robot("paper-4dof"), robot_file)
    assert run(["plan", "--robot", str(robot_file), "--n", "8", "--candidates", "300", "--out", str(out)]) == 0
    lines = out.read_text().splitlines()
    assert lines[0] == "pose,q1,q2,q3,q4" and len(lines) == 9
    q = np.loadtxt(out, delimiter=",", skiprows=1)
    assert list(q[:, 0]) == list(range(8)) and predict(bundled_robot("paper-4dof"), q[:, 1:]).hit.all()
    assert format_poses(q[:, 1:]) == out.read_text()
    assert "over 19 identifiable errors; these poses determine 19 of them)" in capsys.readouterr().out
    # one pose: 4 values; the criterion's prior gave a log det "over 19 identifiable errors" and no more
    assert run(["plan", "--robot", str(robot_file), "--n", "1", "--candidates", "300", "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert "these poses determine 4 of them)" in printed.out, printed
    assert "warning: 1 poses give 4 values and determine 4 of the 19 errors" in printed.err, printed
    assert run(["plan", "--robot", str(robot_file), "--n", "0", "--out", str(out)]) == 2
    assert run(["plan", "--robot", str(robot_file), "--n", "4", "--margin", "0.99", "--candidates", "50",
                "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "at least 1" in err[0] and "inside the screen" in err[1]


def _exhaustive(g: np.ndarray, n: int, passes: int) -> list[int]:
    """Greedy and Fedorov exchange with every candidate's gain recomputed at every step."""
    def gains(info):
        inverse = np.linalg.inv(info)
        return np.linalg.slogdet(np.eye(4) + g @ inverse @ g.transpose(0, 2, 1))[1]
    info, chosen = PRIOR * np.eye(g.shape[2]), []
    for _ in range(n):
        gain = gains(info)
        gain[chosen] = -np.inf
        chosen.append(int(np.argmax(gain)))
        info = info + g[chosen[-1]].T @ g[chosen[-1]]
    for _ in range(passes):
        swapped = False
        for slot in range(n):
            reduced = info - g[chosen[slot]].T @ g[chosen[slot]]
            gain = gains(reduced)
            own = gain[chosen[slot]]
            gain[chosen] = -np.inf
            best = int(np.argmax(gain))
            if gain[best] > own + 1e-9:
                chosen[slot], info, swapped = best, reduced + g[best].T @ g[best], True
        if not swapped:
            break
    return chosen


def test_lazy_search_chooses_what_the_exhaustive_search_chooses():
    robot = bundled_robot("paper-7dof")
    q = candidate_poses(robot, 600, np.random.default_rng(5), 0.1)
    g = whitened_jacobians(robot, q, SPOT, JOINT)
    calls = []
    index, value = d_optimal(g, 20, passes=3, progress=lambda done, total, note: calls.append((done, total)))
    assert list(index) == _exhaustive(g, 20, 3)
    assert value == pytest.approx(log_det(g[index]), rel=1e-12)
    assert calls[0] == (1, 80) and calls[-1] == (80, 80) and [d for d, _ in calls] == sorted(d for d, _ in calls)


def test_progress_off_a_terminal_is_plain_lines():
    stream = io.StringIO()
    progress = Progress("plan", unit="pose", stream=stream, interval=0.0, delay=0.0)
    for done in (1, 2, 3):
        progress(done, 10, "greedy")
    progress.close()
    lines = stream.getvalue().splitlines()
    assert len(lines) == 3 and "\r" not in stream.getvalue()
    assert lines[-1].startswith("plan: 3/10 pose,") and "s left" in lines[-1] and lines[-1].endswith("; greedy")


def test_progress_says_its_header_once_the_work_has_begun():
    """The step's header line: at its first call, else at its end without an error, never
    after an error raised before any call (the error line alone)."""
    stream = io.StringIO()
    with Progress("lm", stream=stream, interval=0.0, delay=10.0, header="estimating") as progress:
        assert stream.getvalue() == ""
        progress(1, 5)
        progress(2, 5)
    assert stream.getvalue() == "estimating\n"
    stream = io.StringIO()
    with Progress("lm", stream=stream, header="estimating"):
        pass
    assert stream.getvalue() == "estimating\n"
    stream = io.StringIO()
    with pytest.raises(ValueError), Progress("lm", stream=stream, header="estimating"):
        raise ValueError("too few values")
    assert stream.getvalue() == ""


def test_progress_restarts_its_rate_when_the_count_falls_back():
    """A second fit reports from 1 again: its rate is its own, not the first fit's."""
    stream = io.StringIO()
    progress = Progress("lm", stream=stream, interval=0.0, delay=0.0)
    progress(1, None)
    progress._start -= 100.0  # the first fit ran for 100 s
    progress(1, None)
    assert "0.01 it/s" in stream.getvalue().splitlines()[-1]
    progress(2, None)
    progress._start -= 100.0
    progress(1, None)  # the next fit
    assert " 0 s elapsed" in stream.getvalue().splitlines()[-1]


def test_progress_of_many_short_runs_still_prints_every_interval():
    """The diagnosis restarts the count for every model, each run shorter than
    the delay: the lines follow the step's clock, not each run's."""
    stream = io.StringIO()
    progress = Progress("diagnose", unit="fit", stream=stream, interval=10.0, delay=2.0)
    for run in range(30):
        for done in (1, 2, 3):
            progress(done, 3)
            progress._first -= 0.5  # half a second per fit: 45 s in all, 1.5 s per run
            if progress._last_line is not None:
                progress._last_line -= 0.5
    lines = stream.getvalue().splitlines()
    assert 4 <= len(lines) <= 6  # the first after 2 s, then one every 10 s of the 45


def test_too_few_candidates_on_the_screen_say_how_rare_a_hit_is_and_what_to_change():
    """Beams 0.9 m inside a screen of half size 1 m: few draws hit; the line gives the share
    that did and every way out (fewer candidates, a lower margin), not the margin alone."""
    robot = bundled_robot("paper-4dof")
    with pytest.raises(ValueError, match=r"found only \d+ of 500 poses with both beams 0.9 m inside the screen \(the arm on its side of it\), in "
                                         r"\d+ drawn within the joint limits \([0-9.e-]+ % hit\): ask for fewer "
                                         "candidates, lower the margin"):
        candidate_poses(robot, 500, np.random.default_rng(0), 0.9, max_tries=3)


def test_a_plan_keeps_the_arm_on_its_side_of_the_screen(tmp_path):
    """A beam meets the screen forward (k > 0) from either side, but an arm cannot reach through
    it: a UR10e standing 1 m in front of the screen (the real one's URDF, data/real/) was planned
    with its laser module 0.16 m behind the screen at 5 of 30 poses, spots counted."""
    urdf = (ROOT / "data" / "real" / "ur10e_mocap" / "ur10_robot.urdf").read_text()
    screen = ('<link name="screen"/><joint name="screen_to_world" type="fixed"><parent link="screen"/>'
              '<child link="world"/><origin xyz="1.0 -1.1 -0.9" rpy="0 0 3.141592653589793"/></joint>')
    (tmp_path / "ur10e.urdf").write_text(urdf.replace("</robot>", screen + "</robot>"))
    (tmp_path / "ur10e.yaml").write_text("urdf: ur10e.urdf\nbase: screen\ntip: tool0\n"
                                         "slm: {a: 0.05, d: 0.0, alpha: 0.0, theta: 3.1416}\n"
                                         "lasers: [{gamma: -0.5236}, {gamma: 0.5236}]\n")
    robot = load_robot(tmp_path / "ur10e.yaml")
    drawn = predict(robot, np.random.default_rng(0).uniform(*robot.pose_range(), (2000, robot.n_joints)))
    assert (drawn.hit.all(axis=1) & (drawn.state.origin[:, 0] < 0)).any()   # beams on the screen from behind
    state = predict(robot, candidate_poses(robot, 300, np.random.default_rng(1), 0.02)).state
    assert (state.origin[:, 0] > 0).all() and (state.joint_origin[..., 0] > 0).all()


def test_a_plan_says_what_its_poses_determine_at_its_noise(tmp_path, capsys):
    """By rank alone, a joint that barely moves (+-0.002 rad) 'determined' all 33 errors; estimate
    and identify, at the same noise, held 4 of them (std beyond STD_FACTOR tolerance scales): the
    plan now counts by their rule."""
    robot = bundled_robot("paper-7dof")
    limits = [dict(min=float(low), max=float(high)) for low, high in zip(*robot.pose_range())]
    limits[3] = dict(min=-1.002, max=-0.998)
    save_robot(robot, tmp_path / "robot.yaml")
    text = (tmp_path / "robot.yaml").read_text()
    data = yaml.safe_load(text)
    for joint, bounds in zip(data["joints"], limits):
        joint.update(bounds)
    (tmp_path / "narrow.yaml").write_text(yaml.safe_dump(data))
    assert cli.main(["plan", "--robot", str(tmp_path / "narrow.yaml"), "--n", "30", "--seed", "2",
                     "--out", str(tmp_path / "poses.csv")]) == 0
    printed = capsys.readouterr()
    determined = int(printed.out.split("these poses determine ")[1].split()[0])
    assert determined < 33 and "or wider joint ranges if a joint barely moves" in printed.err, printed


def test_a_plan_too_small_to_estimate_the_noise_says_so(tmp_path, capsys):
    """5 poses of the 4-DOF arm give 20 values for 19 errors: the plan said nothing, and estimate
    then refused the data (NOT A CALIBRATION: the sigma from 1 residual degree of freedom)."""
    robot_file = tmp_path / "robot.yaml"
    save_robot(bundled_robot("paper-4dof"), robot_file)
    said = {}
    for n in (5, 7):
        assert cli.main(["plan", "--robot", str(robot_file), "--n", str(n), "--seed", "1",
                         "--out", str(tmp_path / f"poses{n}.csv")]) == 0
        said[n] = capsys.readouterr().err
    assert ("rests on 1 spare values" in said[5] and "from 1 or 2 spare values it is no calibration; plan at "
            "least 7 poses, or give the noise" in said[5]), said[5]
    assert "spare values" not in said[7], said[7]
