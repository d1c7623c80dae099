"""estimate --bag reads each sample's joint_positions by its joint_names (io/joint_names.py, the
rule of the estimator node and the sequencer): a sequencer or another tool may list the joints in
another order than the robot file. Before, the names were ignored and a bag in reversed order was
fitted as readings of the wrong joints; a sample the rule refuses is one line and exit 2."""

import json

import numpy as np
import pytest

from laser_calib.cli.main import main
from laser_calib.io import bag
from laser_calib.io.bag_writer import SegmentedBagWriter
from laser_calib.io.samples import load_samples

SAMPLE = "laser_calib_interfaces/msg/Sample"
NAMES = ["joint1", "joint2", "joint3", "joint4"]  # the D-H robot's default names (paper-4dof)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("paper-4dof")
    assert main(["simulate", "--case", "paper-4dof", "--seed", "1", "--poses-per-span", "8", "--out", str(out)]) == 0
    return out


def write_bag(path, samples, labelled, test=None):
    """The samples (and the test samples on /test_samples, after them) as a session bag, one
    segment per sample as the sequencer writes it; ``labelled(k, q)``: sample k's (joint_names,
    joint_positions) from its readings q, robot order."""
    store = bag.typestore()
    T = store.types
    sets = {bag.SAMPLES_TOPIC: samples, bag.TEST_SAMPLES_TOPIC: test}
    topics = {topic: (SAMPLE, [bag.qos(True, True, 100)]) for topic, written in sets.items() if written is not None}
    writer = SegmentedBagWriter(path, path.parent / f".{path.name}", topics, store)
    stamp = 1000
    for topic in topics:
        for k in range(len(sets[topic])):
            stamp += 1
            names, positions = labelled(k, sets[topic].q[k])
            spots = [T["laser_calib_interfaces/msg/Spot"](float(y), float(z), bool(np.isfinite(y)))
                     for y, z in sets[topic].spots[k]]
            msg = T[SAMPLE](T["std_msgs/msg/Header"](T["builtin_interfaces/msg/Time"](stamp, 0), "screen"),
                            int(sets[topic].pose[k]), names, np.array(positions), spots, 3)
            writer.write(topic, stamp * 10 ** 9, store.serialize_cdr(msg, SAMPLE))
            writer.rotate()
    writer.close()
    return path


def estimate(simulated, path, out):
    return main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"), "--bag", str(path), "--out", str(out)])


def test_a_bag_in_another_joint_order_gives_the_same_calibration(simulated, tmp_path):
    samples = load_samples(simulated / "samples.csv")
    labels = {"robot order": lambda k, q: (NAMES, q),
              "reversed": lambda k, q: (NAMES[::-1], q[::-1]),
              "unnamed": lambda k, q: ([], q),
              # a D-H robot's joints under the arm's own names (none of joint1..N): taken in their order
              "arm's names": lambda k, q: (["base", "shoulder", "elbow", "wrist"], q)}
    errors = {}
    for label, labelled in labels.items():
        path = write_bag(tmp_path / label.replace(" ", "_").replace("'", ""), samples, labelled)
        assert estimate(simulated, path, tmp_path / f"out {label}") == 0, label
        result = json.loads((tmp_path / f"out {label}" / "result.json").read_text())
        errors[label] = [(e["name"], e["value"], e["std"]) for e in result["errors"]]
    for label in labels:
        assert errors[label] == errors["robot order"], label  # the same numbers, reordered exactly


@pytest.mark.parametrize("names, problem", [
    (NAMES[:-1] + ["gripper"], "joint 'joint4' (robot 'manipulator_4dof') is not in the sample's joint_names "
                               "(joint1, joint2, joint3, gripper)"),
    (NAMES[:-1], "3 joint_names but 4 joint_positions"),
    # the robot's default names mixed with others: a mix-up, not the arm's own naming
    (["joint1", "joint2", "elbow", "wrist"], "joint 'joint3' (robot 'manipulator_4dof') is not in the sample's "
                                             "joint_names (joint1, joint2, elbow, wrist)"),
    # names not the robot's (taken in its order) with one twice: two readings under one name
    (["q1", "q1", "q3", "q4"], "joint 'q1' is named twice in the sample's joint_names"),
], ids=["joint missing", "names and positions differ in length", "default names mixed with others",
        "the arm's own names, one twice"])
def test_a_sample_the_rule_refuses_is_one_line_naming_the_bag_and_the_message(simulated, tmp_path, capsys,
                                                                              names, problem):
    """Message 6 alone is wrong, in its own segment: refused, not skipped as a damaged segment."""
    samples = load_samples(simulated / "samples.csv")
    path = write_bag(tmp_path / "bag", samples, lambda k, q: (names, q) if k == 5 else (NAMES, q))
    assert estimate(simulated, path, tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert err == f"laser-calib: {path}: /samples message 6: {problem}\n"
    assert not (tmp_path / "out").exists()


def test_joint_names_given_map_a_bag_the_robots_names_do_not(simulated, tmp_path, capsys):
    """A sequencer given the driver's names (joint_names parameter) writes them in its samples; for
    a robot whose own names they are not, --joint-names says which is which, as that parameter
    did. Before, estimate had no way to read such a bag: refused, or (a D-H robot's names mixed
    with others) nothing to say."""
    samples = load_samples(simulated / "samples.csv")
    driver = ["joint1", "joint2", "elbow", "wrist"]  # refused without --joint-names (above)
    ordered = write_bag(tmp_path / "ordered", samples, lambda k, q: (NAMES, q))
    path = write_bag(tmp_path / "driver", samples, lambda k, q: (driver[::-1], q[::-1]))
    assert estimate(simulated, ordered, tmp_path / "out ordered") == 0
    assert main(["estimate", "--robot", str(simulated / "robot_nominal.yaml"), "--bag", str(path),
                 "--joint-names", *driver, "--out", str(tmp_path / "out driver")]) == 0
    errors = [[(e["name"], e["value"], e["std"]) for e in json.loads((tmp_path / out / "result.json").read_text())
               ["errors"]] for out in ("out ordered", "out driver")]
    assert errors[1] == errors[0]
    capsys.readouterr()
    robot = str(simulated / "robot_nominal.yaml")
    for args, line in (
            (["--bag", str(path), "--joint-names", *driver[:3]], "--joint-names: 3 names, robot 'manipulator_4dof' has "
                                                                  "4 joints"),
            (["--samples", str(simulated / "samples.csv"), "--joint-names", *driver],
             "--joint-names: names the joints of a bag's samples: it applies to --bag only")):
        assert main(["estimate", "--robot", robot, *args, "--out", str(tmp_path / "refused")]) == 2
        assert capsys.readouterr().err == f"laser-calib: {line}\n"
        assert not (tmp_path / "refused").exists()
