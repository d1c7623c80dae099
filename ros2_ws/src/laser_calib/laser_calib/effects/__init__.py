"""Effects the geometric (D-H) model lacks, as parameter blocks that plug into
the same estimators (base, joint, drift, screen), the model that carries them
(model.EffectModel), the library of candidates and the robot-file key
(catalog), their truth forms for the simulator (truth), residual analysis
against the covariates of the data (residuals), the noise in a residual
(noise) and the diagnosis report (report).
"""

from laser_calib.effects.base import JOINT, PARAM, SPOT, Effect, JointEffect, ParamEffect, SpotEffect, move_directions
from laser_calib.effects.catalog import KINDS, calibrated_model, candidates, effects_from_robot, effects_to_yaml
from laser_calib.effects.drift import Drift
from laser_calib.effects.joint import Backlash, Compliance, JointScale, Periodic, gravity_torques
from laser_calib.effects.effect_model import EffectModel
from laser_calib.effects.screen import CameraDistortion, ScreenShape
from laser_calib.effects.screen_spline import ScreenSpline

__all__ = ["JOINT", "PARAM", "SPOT", "Effect", "JointEffect", "ParamEffect", "SpotEffect", "move_directions",
           "KINDS", "calibrated_model", "candidates", "effects_from_robot", "effects_to_yaml", "Drift", "Backlash", "Compliance",
           "JointScale", "Periodic", "gravity_torques", "EffectModel", "CameraDistortion", "ScreenShape",
           "ScreenSpline"]
