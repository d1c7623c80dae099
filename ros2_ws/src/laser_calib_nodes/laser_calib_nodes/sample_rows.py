"""The estimator's sample rows (pose id, stamp s, q (N,) rad, spots (2,2) m), from Sample
messages and joint-state pairs, and the sets an Estimate request or a Calibrate goal
names: its own samples and test samples, or those the node accumulated; and its options."""

from __future__ import annotations

import numpy as np

from laser_calib.cli.arguments import require_measured
from laser_calib.estimation.estimate import EstimateOptions
from laser_calib.io import bag
from laser_calib.io.errors import InputError
from laser_calib.io.samples import Samples, without_unmeasured_test
from laser_calib.model.robot import Robot
from laser_calib.session.estimate import estimate_options

Row = tuple[int, float, np.ndarray, np.ndarray]


def check_row(robot: Robot, row: Row, where: str) -> None:
    n = len(row[2])
    if n != robot.n_joints:
        raise InputError(where, f"{n} joint positions, robot '{robot.name}' has {robot.n_joints}")
    bad = np.flatnonzero(~np.isfinite(row[2]))
    if bad.size:
        raise InputError(where, f"joint_positions[{bad[0]}] is not finite ({row[2][bad[0]]})")


def row_from_msg(msg, where: str, joints, robot: Robot) -> Row:
    """A Sample message's row, its joints in the robot's order (joints: the node's JointStateReader)."""
    row = bag.sample_row_from_msg(msg, where, joints)
    check_row(robot, row, where)
    return row


def request_sets(node, request) -> tuple[Samples, Samples | None, dict]:
    """An Estimate request's (or a Calibrate goal's) samples, its test samples (None: none)
    and the sources run_calibration names: the robot, both sets and the compensator."""
    if request.use_accumulated and (request.samples or request.test_samples):   # the request's were dropped unsaid
        raise InputError("request", f"use_accumulated is true and the request holds {len(request.samples)} samples "
                         f"and {len(request.test_samples)} test samples: send samples or use_accumulated, not both")
    if request.use_accumulated:
        rows, test_rows = node.accumulated()
        refused = list(node.refused)
        if not rows:
            said = f"; the {len(refused)} received were refused, the first: {refused[0]}" if refused else ""
            raise InputError("request", f"use_accumulated is true but no samples have been accumulated yet{said}")
        by = f"accumulated by {node.get_fully_qualified_name()}" + (
            f" ({len(refused)} (test) samples refused besides, said in its log)" if refused else "")
    else:
        if not request.samples:
            raise InputError("request", "no samples (and use_accumulated is false)")
        rows, test_rows = (
            [row_from_msg(msg, f"request: {what} {k + 1} (pose {msg.pose})", node.joints, node.robot)
             for k, msg in enumerate(msgs)]
            for what, msgs in (("sample", request.samples), ("test sample", request.test_samples)))
        by = "of the request"
    sources = {"robot": node.robot_path, "samples": f"{len(rows)} samples {by}",
               "test": f"{len(test_rows)} test samples {by}" if test_rows else None,
               "compensator": node.compensator_path}
    test = bag.samples_from_rows(test_rows, "request: test_samples") if test_rows else None
    if test is not None and not request.use_accumulated:  # given, as a --test file is
        require_measured(test, "request: test_samples", "no spot is measured in the test set")
    samples, test = without_unmeasured_test(bag.samples_from_rows(rows, "request"), test)
    return samples, test, dict(sources, test=sources["test"] if test is not None else None)


def request_options(node, request) -> EstimateOptions:
    """An Estimate request's (or a Calibrate goal's) options, as the command line makes them of
    its own (session.estimate.estimate_options): a spot_sigma or joint_sigma left 0 is the node's
    parameter (parameters.noise). A bad value: InputError naming it."""
    return estimate_options(request.method, request.spot_sigma or node.spot_sigma, request.prior, request.robust,
                            request.joint_sigma or node.joint_sigma)


def sample_row(sample: Samples) -> Row:
    """The row of a one-pose sample (session.average's)."""
    return int(sample.pose[0]), float(sample.stamp[0]), sample.q[0], sample.spots[0]
