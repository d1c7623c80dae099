"""What `estimate` says of the noise it estimated, against what the hardware can do.

An effect the geometric model lacks, estimated as noise, leaves a fit that looks sound: joint
readings lagging the spots by 3 % of each move gave a joint-reading sigma of 0.50 deg, no warning,
and a model 18 mm off on test poses (a new user's probe). `diagnose` tests an estimated sigma
against the robot file's rated one (diagnosis.verdict); `estimate` says the same at a glance:
- against the robot file's spot_sigma / joint_reading_sigma (model.robot_file.rated_noise): an
  estimated sigma more than RATED_EXCESS times the rated one;
- with no rated joint-reading sigma: an estimated one above ENCODER_SIGMA.
"""

from __future__ import annotations

import numpy as np

from laser_calib.estimation.estimate import Estimate
from laser_calib.model.robot import Robot
from laser_calib.model.robot_file import rated_noise

# An estimated sigma this many times the rated one is no noise of that hardware: the estimate's
# relative spread is 1 / sqrt(2 m) on m residual values, a few % on any calibration.
RATED_EXCESS = 2.0
# rad (0.25 deg): four times the paper's joint disturbance (+-0.1 deg uniform, sigma 0.058 deg) and
# three times a 12-bit encoder's step (0.088 deg), the coarsest common on arms.
ENCODER_SIGMA = float(np.radians(0.25))
ADVICE = "run diagnose on these samples to find it"


def noise_warnings(robot: Robot, est: Estimate) -> list[str]:
    """The warnings (module docstring) for an estimate of ``robot``'s errors."""
    spot_rated, joint_rated = rated_noise(robot)
    said = []
    for name, value, estimated, rated, unit, factor, key in (
            ("spot", est.sigma, est.sigma_estimated, spot_rated, "mm", 1e3, "spot_sigma"),
            ("joint-reading", est.joint_sigma, est.joint_sigma_estimated, joint_rated, "deg", np.degrees(1.0),
             "joint_reading_sigma")):
        if estimated and rated is not None and value > RATED_EXCESS * rated:
            said.append(f"noise: the {name} sigma estimated from the residual, {value * factor:.3g} {unit}, is "
                        f"{value / rated:.1f} times the robot file's {key} ({rated * factor:.3g} {unit}): something "
                        f"the model lacks is taken as noise; {ADVICE}")
    if est.joint_sigma_estimated and joint_rated is None and est.joint_sigma > ENCODER_SIGMA:
        said.append(f"noise: the joint-reading sigma estimated from the residual is "
                    f"{np.degrees(est.joint_sigma):.3g} deg, coarser than encoders on arms read (12 bits: 0.088 deg "
                    "a step): if yours read better, something that moves with the joints (joint readings lagging "
                    f"the spots, compliance) is taken as noise; {ADVICE}, or give joint_reading_sigma in the robot "
                    "file")
    return said
