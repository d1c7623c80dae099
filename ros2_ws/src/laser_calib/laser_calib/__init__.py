"""ROS-free core of laser-based kinematic calibration (Park et al. 2012).

Modules: model (robot description and parameter vector), robot_file and
samples_file (the interchange formats of conventions.md), kinematics
(forward model and spots), jacobian (differential kinematics, eq. 5-12),
estimators (LM and the paper's EKF), identifiability, simulation, report.
Nothing here imports rclpy.
"""

import os

# The matrices here are small (at most a few thousand rows by ~50 columns): BLAS
# threads only contend for the cores (seen: 7 ms single-threaded against up to
# 260 ms with two threads on a busy 2-core machine). Set before numpy loads;
# an explicit setting by the user wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
