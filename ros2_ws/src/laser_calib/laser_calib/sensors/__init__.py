"""Measurement models beside the laser spot: a 3-D point (laser tracker,
motion-capture marker) and a 6-DOF pose (a camera observing a target), with the
unknown fixed frames around the arm estimated jointly with the D-H errors."""

from .frames import FRAMES, Pose, robot_frames, with_frames
from .models import PointModel, PoseModel
from .samples import SensorSamples, load_sensor_samples, save_sensor_samples

__all__ = ["FRAMES", "Pose", "robot_frames", "with_frames", "PointModel", "PoseModel", "SensorSamples",
           "load_sensor_samples", "save_sensor_samples"]
