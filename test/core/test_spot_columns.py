"""A samples file with its spot columns swapped (l1 <-> l2, y <-> z) is refused at
reading, one line naming the file and the swap, exit 2; honest files never are."""

import numpy as np
import pytest

from laser_calib.cli.main import main
from laser_calib.io.samples import load_samples, save_samples
from laser_calib.io.spot_columns import SWAPS, swap_votes
from laser_calib.model.robot_file import load_robot


@pytest.fixture(scope="module", params=["paper-4dof", "paper-7dof"])
def simulated(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(request.param)
    assert main(["simulate", "--case", request.param, "--seed", "1", "--poses-per-span", "8",
                 "--spot-noise", "0.02", "--out", str(out)]) == 0
    return out


def _swapped(simulated, tmp_path, lasers, coords):
    samples = load_samples(simulated / "samples.csv")
    path = tmp_path / "swapped.csv"
    save_samples(type(samples)(samples.pose, samples.stamp, samples.q, samples.spots[:, lasers][:, :, coords]), path)
    return path


@pytest.mark.parametrize("swap", SWAPS, ids=["lasers", "y-z", "both"])
@pytest.mark.parametrize("command", ["estimate", "diagnose", "identify"])
def test_swapped_columns_are_refused_naming_the_file_and_the_swap(simulated, tmp_path, capsys, swap, command):
    label, lasers, coords = swap
    path = _swapped(simulated, tmp_path, lasers, coords)
    out = [] if command == "identify" else ["--out", str(tmp_path / "out")]
    assert main([command, "--robot", str(simulated / "robot_nominal.yaml"), "--samples", str(path)] + out) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"laser-calib: {path}: the spot columns look assigned wrongly: {label}.")
    assert "\n" not in err and not (tmp_path / "out").exists()


def test_a_negated_y_refused_as_a_swap_is_named_first(tmp_path, capsys):
    """The paper's 4-DOF lasers are mirror images about y: a file whose y is negated
    votes for l1 <-> l2 too, and the message names both, the closer one first."""
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--poses-per-span", "8", "--spot-noise", "0.02",
                 "--out", str(tmp_path)]) == 0
    samples = load_samples(tmp_path / "samples.csv")
    path = tmp_path / "mirrored.csv"
    save_samples(type(samples)(samples.pose, samples.stamp, samples.q, samples.spots * [-1, 1]), path)
    assert main(["estimate", "--robot", str(tmp_path / "robot_nominal.yaml"), "--samples", str(path),
                 "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err.startswith(f"laser-calib: {path}: the spot columns look assigned wrongly: y negated "
                                              "(the screen frame's y axis, or the image's, reversed), or l1_* and l2_* "
                                              "swapped")


def test_a_swapped_test_set_is_refused_too(simulated, tmp_path, capsys):
    path = _swapped(simulated, tmp_path, [1, 0], [0, 1])
    assert main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"), "--samples",
                 str(simulated / "samples.csv"), "--test", str(path), "--out", str(tmp_path / "out")]) == 2
    assert f"{path}: the spot columns look assigned wrongly" in capsys.readouterr().err


@pytest.mark.parametrize("case", ["paper-4dof", "paper-7dof"])
@pytest.mark.parametrize("seed", [0, 3])
@pytest.mark.parametrize("extra", [[], ["--random-errors"]])
def test_honest_sessions_give_no_pose_a_vote(tmp_path, case, seed, extra):
    """Nominal errors of 0.1 m to 0.8 m at some spots of the 7-DOF arm and 50 mm of spot
    noise still leave every pose far closer to its own laser's predicted spot."""
    assert main(["simulate", "--case", case, "--seed", str(seed), "--spot-noise", "0.05", "--out",
                 str(tmp_path)] + extra) == 0
    robot = load_robot(tmp_path / "robot_nominal.yaml")
    samples = load_samples(tmp_path / "samples.csv", robot)
    assert [v.votes for v in swap_votes(robot, samples.q, samples.spots)] == [0] * 5  # the swaps, then the mirrors


def test_a_few_gross_outliers_do_not_make_a_swap(simulated, tmp_path):
    robot = load_robot(simulated / "robot_nominal.yaml")
    samples = load_samples(simulated / "samples.csv", robot)
    spots = samples.spots.copy()
    spots[:3] = spots[:3, ::-1]  # three poses' lasers exchanged: outliers, not the file's columns
    path = tmp_path / "outliers.csv"
    save_samples(type(samples)(samples.pose, samples.stamp, samples.q, spots), path)
    assert len(load_samples(path, robot)) == len(samples)  # read, not refused
    assert swap_votes(robot, samples.q, spots)[0].votes <= 3


def test_spots_that_match_no_assignment_are_no_swap(simulated, tmp_path):
    """Made-up spots (a test's, another robot's) are far from the prediction both ways."""
    robot = load_robot(simulated / "robot_nominal.yaml")
    samples = load_samples(simulated / "samples.csv", robot)
    spots = np.random.default_rng(0).uniform(-0.9, 0.9, samples.spots.shape)
    path = tmp_path / "made_up.csv"
    save_samples(type(samples)(samples.pose, samples.stamp, samples.q, spots), path)
    assert len(load_samples(path, robot)) == len(samples)


def test_a_swapped_bag_is_refused_naming_the_bag(simulated, tmp_path, capsys):
    from laser_calib.io import bag
    from laser_calib.io.bag_writer import SegmentedBagWriter
    samples = load_samples(simulated / "samples.csv")
    store = bag.typestore()
    T = store.types
    kind = "laser_calib_interfaces/msg/Sample"
    writer = SegmentedBagWriter(tmp_path / "bag", tmp_path / ".recording",
                                {bag.SAMPLES_TOPIC: (kind, [bag.qos(True, True, 100)])}, store)
    for r in range(len(samples)):
        stamp = 1000 + r
        spots = [T["laser_calib_interfaces/msg/Spot"](float(y), float(z), True) for y, z in samples.spots[r, ::-1]]
        msg = T[kind](T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](stamp, 0), "screen"),
                      int(samples.pose[r]), [f"joint{i + 1}" for i in range(samples.n_joints)], samples.q[r], spots, 3)
        writer.write(bag.SAMPLES_TOPIC, stamp * 10 ** 9, store.serialize_cdr(msg, kind))
    writer.close()
    assert main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"), "--bag", str(tmp_path / "bag"),
                 "--out", str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err.startswith(f"laser-calib: {tmp_path / 'bag'}: the spot columns look assigned "
                                              "wrongly: l1_* and l2_* swapped")


def test_the_nodes_code_path_refuses_swapped_samples_too(simulated):
    """An Estimate request or a live session builds its samples from messages, not from a
    file: run_calibration (the nodes' path to calibrate) checks their columns itself."""
    from laser_calib.io.errors import InputError
    from laser_calib.session.estimate import estimate_options, run_calibration

    samples = load_samples(simulated / "samples.csv")
    swapped = type(samples)(samples.pose, samples.stamp, samples.q, samples.spots[:, [1, 0]])
    with pytest.raises(InputError, match="16 samples of an Estimate request: the spot columns look assigned wrongly"):
        run_calibration(load_robot(simulated / "robot_nominal.yaml"), swapped, estimate_options("lm", 0.0, False, True),
                        None, sources={"samples": "16 samples of an Estimate request"})
