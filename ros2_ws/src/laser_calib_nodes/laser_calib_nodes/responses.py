"""A batch estimate's Outcome (laser_calib.session.estimate) as the estimator answers it:
the Estimate service's response and the Calibrate action's result carry the same fields."""

from __future__ import annotations

import numpy as np

from laser_calib.model.robot import Robot
from laser_calib.report.files import calibrated_robot_yaml, report_markdown, result_json
from laser_calib.session.estimate import Outcome, laser_statistics

from laser_calib_nodes import common


def fill(response, outcome: Outcome, robot: Robot, count: int, stamp) -> None:
    """Set response's fields from outcome; count: the samples estimated from; stamp: now."""
    from laser_calib_interfaces.msg import DhParameters, SpotStatistics
    calibration = outcome.calibration
    est = calibration.estimate
    params = DhParameters()
    params.header.stamp = stamp
    params.header.frame_id = common.SCREEN_FRAME
    params.robot_name = robot.name
    params.method = calibration.options.method
    params.names = list(est.names)
    params.values = [float(v) for v in np.r_[calibration.calibrated.vector(), est.values[robot.n_params:]]]
    params.errors = [float(v) for v in est.errors]
    params.std = [float(v) for v in est.std]
    params.identifiable = [bool(v) for v in est.determined]  # a failed fit's undetermined: no value (errors NaN)
    params.iterations = int(est.fit.iterations)
    params.sample_count = count
    response.parameters = params
    for field in ("before", "after"):
        values = laser_statistics(calibration.spot_error["calibration"][field])
        msg = SpotStatistics()
        msg.mean, msg.std, msg.max = values["mean"], values["std"], values["max"]
        msg.count = values["count"]
        setattr(response, field, msg)
    response.diagnosis_json = outcome.diagnosis_json
    response.report_markdown = report_markdown(calibration)
    response.result_json = result_json(calibration)
    response.calibrated_robot_yaml = calibrated_robot_yaml(calibration)
    response.success = calibration.failure is None  # not converged, or lost measurements: written, not trusted
    response.message = outcome.message
