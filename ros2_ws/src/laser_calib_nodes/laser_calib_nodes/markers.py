"""What the estimator publishes after each online update: the parameters
(DhParameters) and the RViz view, the measured spots, the spots the current
estimate predicts and the two beams of the latest pose (MarkerArray, frame
`screen`)."""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from laser_calib.model.kinematics import predict
from laser_calib.model.robot import Robot

from laser_calib_nodes import common

MAX_POINTS = 2000  # per laser and kind: the latest poses' spots
LASER_COLOURS = ((1.0, 0.1, 0.1), (0.1, 0.9, 0.1))
PREDICTED_COLOUR = (0.2, 0.4, 1.0)


def online_parameters(robot: Robot, errors: np.ndarray, std: np.ndarray, identifiable: np.ndarray, count: int,
                      stamp):
    """The online EKF's state, (n_params,) each, as DhParameters (values: nominal + error, NaN errors as 0)."""
    from laser_calib_interfaces.msg import DhParameters
    msg = DhParameters()
    msg.header.stamp = stamp
    msg.header.frame_id = common.SCREEN_FRAME
    msg.robot_name = robot.name
    msg.method = "ekf"
    msg.names = list(robot.param_names)
    msg.values = [float(v) for v in robot.vector() + np.nan_to_num(errors)]
    msg.errors = [float(v) for v in errors]
    msg.std = [float(v) for v in std]
    msg.identifiable = [bool(v) for v in identifiable]
    msg.iterations = 0
    msg.sample_count = count
    return msg


def screen_point(spot: np.ndarray) -> Point:
    """A (2,) spot (y, z) on the screen plane x = 0."""
    return Point(x=0.0, y=float(spot[0]), z=float(spot[1]))


def calibration_markers(robot: Robot, q: np.ndarray, measured: np.ndarray, errors: np.ndarray,
                        stamp) -> MarkerArray:
    """q (P, n_joints), measured (P, 2, 2) spots (NaN: not seen), errors (n_params,) current estimate."""
    prediction = predict(robot, q, np.nan_to_num(errors))

    def marker(ns: str, ident: int, kind: int, scale: float, colour, alpha=1.0) -> Marker:
        m = Marker()
        m.header.stamp = stamp
        m.header.frame_id = common.SCREEN_FRAME
        m.ns, m.id, m.type, m.action = ns, ident, kind, Marker.ADD
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = scale
        m.color = ColorRGBA(r=colour[0], g=colour[1], b=colour[2], a=alpha)
        return m

    array = MarkerArray()
    for j in range(2):
        points = marker("measured", j, Marker.SPHERE_LIST, 0.01, LASER_COLOURS[j])
        points.points = [screen_point(s) for s in measured[:, j] if np.isfinite(s).all()]
        predicted = marker("predicted", j, Marker.SPHERE_LIST, 0.006, PREDICTED_COLOUR, 0.8)
        hit = prediction.hit[:, j]
        predicted.points = [screen_point(s) for s in prediction.spots[hit, j]]
        beam = marker("beams", j, Marker.LINE_LIST, 0.003, LASER_COLOURS[j], 0.7)
        if hit[-1]:
            origin = prediction.state.origin[-1]
            beam.points = [Point(x=float(origin[0]), y=float(origin[1]), z=float(origin[2])),
                           screen_point(prediction.spots[-1, j])]
        array.markers += [points, predicted, beam]
    return array
