"""The calibration and test samples of `estimate` and `diagnose`: a samples CSV or a
recorded session bag, and a test set (--test, else a bag's own /test_samples).

Both commands read them here, so a session diagnosed from its bag sees the poses
its estimate saw, with the same checks and the same one-line errors.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from laser_calib.cli.arguments import require_measured
from laser_calib.io.bag import SAMPLES_TOPIC, TEST_SAMPLES_TOPIC, read_samples_checked, session_topic
from laser_calib.io.errors import InputError
from laser_calib.io.joint_names import RobotJoints
from laser_calib.io.samples import Samples, check_joint_range, check_spot_units, load_samples, without_unmeasured_test
from laser_calib.io.spot_columns import check_spot_columns
from laser_calib.model.robot import Robot


@dataclass(frozen=True)
class SampleSets:
    """The poses to fit and those to test on (None without a test set), each with where it came from
    (a file, or a bag and its topic): the name an error about them gives."""

    samples: Samples
    source: str
    test: Samples | None
    test_source: str | None


def add_sample_arguments(parser: argparse.ArgumentParser, samples_help: str = "samples CSV") -> None:
    """--samples or --bag (one of them), --joint-names (a bag's) and --test."""
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--samples", help=samples_help)
    source.add_argument("--bag", help="a recorded session bag (its /samples topic; its /test_samples, the "
                                      "session's held-out poses, are the test set unless --test is given)")
    parser.add_argument("--joint-names", nargs="+", metavar="NAME",
                        help="the names the bag's samples give the robot's joints, base to tip (the sequencer's "
                             "joint_names parameter); default: the robot's own")
    parser.add_argument("--test", help="test samples CSV: poses the fit never sees")


def read_sample_sets(args: argparse.Namespace, robot: Robot) -> SampleSets:
    """The sets add_sample_arguments named, checked against the robot; a set with nothing measured
    in it is bad input (require_measured)."""
    if args.joint_names and not args.bag:
        raise InputError("--joint-names", "names the joints of a bag's samples: it applies to --bag only")
    source = str(args.samples or args.bag)
    samples = bag_samples(args.bag, robot, args.joint_names) if args.bag else load_samples(args.samples, robot)
    test = test_source = None
    if args.test:
        test_source, test = args.test, load_samples(args.test, robot)
    elif args.bag:  # the session's held-out poses, as it tested them, if it had any
        test = bag_samples(args.bag, robot, args.joint_names, TEST_SAMPLES_TOPIC, required=False)
        test_source = None if test is None else f"{args.bag} {session_topic(args.bag, TEST_SAMPLES_TOPIC)}"
    require_measured(samples, source)
    if args.test:
        require_measured(test, test_source, "no spot is measured in the test set")
    samples, test = without_unmeasured_test(samples, test)
    return SampleSets(samples, source, test, test_source if test is not None else None)


def bag_samples(path: str, robot: Robot, joint_names: list[str] | None, topic: str = SAMPLES_TOPIC,
                required: bool = True) -> Samples | None:
    """Samples of a recorded session bag's ``topic`` (rosbags: no ROS runtime), each sample's
    joint_positions put in the robot's order by its joint_names: the robot's own, or
    ``joint_names`` (--joint-names, as the sequencer's parameter of that name gives them) base to tip.
    Their warnings (damaged segments skipped, joints the robot does not have) go with them into the
    command's warnings and files. Not ``required``: None for a bag without a sample on the topic."""
    joints = RobotJoints(robot, joint_names, "--joint-names") if joint_names else RobotJoints(robot)
    samples, _ = read_samples_checked(path, topic, joints, required)
    if samples is None:
        return None
    if samples.n_joints != robot.n_joints:
        raise InputError(path, f"{samples.n_joints} joints in the bag but robot '{robot.name}' has {robot.n_joints}")
    check_joint_range(samples.q, robot, path, samples.pose)
    check_spot_units(samples.spots, robot, path)
    check_spot_columns(robot, samples.q, samples.spots, path)
    return samples
