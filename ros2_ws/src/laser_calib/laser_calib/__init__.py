"""ROS-free core of laser-based kinematic calibration (Park et al. 2012).

Modules: model (robot description and parameter vector), robot_file and
samples_file (the interchange formats of conventions.md), kinematics
(forward model and spots), jacobian (differential kinematics, eq. 5-12),
estimators (LM and the paper's EKF), identifiability, simulation, report.
Nothing here imports rclpy.
"""

__version__ = "0.1.0"
