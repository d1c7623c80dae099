"""A session bag as a crash, a full disk or another tool leaves it, read by estimate --bag and
diagnose --bag (cli/sample_sets.py, io/bag.py): a damaged segment is skipped and said, on the
console and in the files, and the rest calibrates; a torn or malformed metadata.yaml is one
line and exit 2; what the samples' joint names say that is no error (a gripper, two namings
mixed) is said. Before: any damaged segment refused the bag (the test set's topic was looked up
in the whole bag), a torn metadata.yaml gave a traceback, a YAML error spanned lines, and the
rest passed in silence."""

import json

import pytest
import yaml

from laser_calib.cli.main import main
from laser_calib.io.samples import load_samples
from test_bag_joint_names import NAMES, simulated, write_bag  # noqa: F401 (the fixture)


@pytest.fixture
def session(simulated, tmp_path):
    """The 16 poses to fit (segments bag_0 .. bag_15) and 8 test poses (bag_16 .. bag_23)."""
    cal, test = load_samples(simulated / "samples.csv"), load_samples(simulated / "case1_test.csv")
    return str(simulated / "robot_nominal.yaml"), write_bag(tmp_path / "bag", cal, lambda k, q: (NAMES, q), test)


def run(command, robot, path, out, *extra):
    return main([command, "--robot", robot, "--bag", str(path), *extra, "--out", str(out)])


@pytest.mark.parametrize("command", ["estimate", "diagnose"])
def test_a_damaged_segment_is_skipped_said_and_kept_in_the_files(session, tmp_path, capsys, command):
    robot, path = session
    damaged = path / "bag_3.mcap"
    damaged.write_bytes(damaged.read_bytes()[: len(damaged.read_bytes()) // 2])
    assert run(command, robot, path, tmp_path / "out") in (0, 1)
    said = f"{path}: segment bag_3.mcap (cannot read bag ("
    err = capsys.readouterr().err
    assert err.count(said) == 1 and "its samples are lost, the other segments were read" in err
    name = "result.json" if command == "estimate" else "diagnosis.json"
    written = json.loads((tmp_path / "out" / name).read_text())
    assert any(line.startswith(said) for line in written["warnings"])
    if command == "estimate":  # the 15 intact poses fitted, the 8 test poses tested
        assert written["inputs"]["test"] == f"{path} /test_samples"
        assert written["spot_error"]["test"]["after"]["all"]["n"] > 0


def test_a_missing_segment_is_named_by_its_own_path(session, tmp_path, capsys):
    robot, path = session
    (path / "bag_5.mcap").unlink()
    assert run("estimate", robot, path, tmp_path / "out") == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "bag_5.mcap" in line]
    assert len(lines) == 1 and str(path / "bag_5.mcap") in lines[0] and "bag-segments-" not in lines[0]


@pytest.mark.parametrize("tear", ["inside an entry", "bad yaml"])
def test_a_torn_metadata_file_is_one_line_and_exit_2(session, tmp_path, capsys, tear):
    robot, path = session
    text = (path / "metadata.yaml").read_text()
    if tear == "inside an entry":  # the last segment listed without its path: a KeyError in the split
        meta = yaml.safe_load(text)
        del meta["rosbag2_bagfile_information"]["files"][-1]["path"]
        text = yaml.safe_dump(meta)
    else:
        text = text.replace(":", ": [", 3)
    (path / "metadata.yaml").write_text(text)
    (path / "bag_2.mcap").write_bytes(b"not an mcap file")  # so that the segments are split
    assert run("estimate", robot, path, tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert err.startswith(f"laser-calib: {path}: cannot read bag (") and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_joint_names_given_twice_is_one_line(session, tmp_path, capsys):
    robot, path = session
    assert run("estimate", robot, path, tmp_path / "out", "--joint-names", "joint1", "joint1", "joint2",
               "joint3") == 2
    assert capsys.readouterr().err == "laser-calib: --joint-names: names 'joint1' twice\n"


def test_joints_the_robot_lacks_and_two_namings_are_said(simulated, tmp_path, capsys):
    robot = str(simulated / "robot_nominal.yaml")
    cal = load_samples(simulated / "samples.csv")
    gripper = write_bag(tmp_path / "gripper", cal, lambda k, q: (NAMES + ["gripper"], [*q, 0.01]))
    assert run("estimate", robot, gripper, tmp_path / "gripper out") == 0
    warnings = json.loads((tmp_path / "gripper out" / "result.json").read_text())["warnings"]
    assert f"{gripper} /samples: the samples also name gripper, which robot 'manipulator_4dof' does not have: " \
           "those readings are not used (the bag of another arm?)" in warnings
    mixed = write_bag(tmp_path / "mixed", cal, lambda k, q: (["a", "b", "c", "d"] if k == 5 else NAMES, q))
    assert run("estimate", robot, mixed, tmp_path / "mixed out") == 0
    assert f"{mixed} /samples: 1 of {len(cal)} samples (the first: sample 6) name none of the joints of robot " \
           "'manipulator_4dof' and were taken in its order" in capsys.readouterr().err


def test_a_bad_test_sample_names_its_topic(session, simulated, tmp_path, capsys):
    robot, _ = session
    cal, test = load_samples(simulated / "samples.csv"), load_samples(simulated / "case1_test.csv")
    test.q[3, 1] = float("nan")
    path = write_bag(tmp_path / "nan", cal, lambda k, q: (NAMES, q), test)
    assert run("diagnose", robot, path, tmp_path / "out") == 2
    assert capsys.readouterr().err == (f"laser-calib: {path} /test_samples: sample 4 (pose {test.pose[3]}): "
                                       "joint_positions[1] is not finite (nan)\n")


def test_the_bag_of_a_longer_arm_is_refused_by_its_extra_joint(simulated, tmp_path, capsys):
    """A D-H robot's joints are joint1..jointN; a sample naming joint5 for this 4-joint arm is a longer
    arm's. Before, joint1..4 were picked from its names and the refusal, if any, came from a joint range
    (pose 1, field q2 outside the joint range: another cause)."""
    robot = str(simulated / "robot_nominal.yaml")
    path = write_bag(tmp_path / "longer", load_samples(simulated / "samples.csv"),
                     lambda k, q: (NAMES + ["joint5"], [*q, 0.2]))
    assert run("estimate", robot, path, tmp_path / "out") == 2
    assert capsys.readouterr().err == (f"laser-calib: {path}: /samples message 1: joint 'joint5' is beyond the 4 "
                                       "joints of robot 'manipulator_4dof' (joint1 .. joint4): the readings of a "
                                       "longer arm?\n")
