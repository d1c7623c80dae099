"""What a diagnosis holds: the fitted stages, the selection rounds, the noise
and the tests of the verdict, and their JSON form."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from laser_calib.diagnosis.compensator import Compensator
from laser_calib.diagnosis.detector import Detection
from laser_calib.diagnosis.options import DiagnoseOptions
from laser_calib.diagnosis.specification import Varying
from laser_calib.diagnosis.structure import Readings, Series, Test
from laser_calib.effects.base import Effect
from laser_calib.effects.catalog import effects_to_yaml
from laser_calib.effects.effect_model import EffectModel
from laser_calib.estimation.estimate import Estimate
from laser_calib.estimation.failures import first_failure
from laser_calib.model.robot import Robot
from laser_calib.model.robot_file import with_held
from laser_calib.report.statistics import summary

@dataclass(frozen=True)
class Fitted:
    """A model fitted on the calibration poses: its estimate, held-out spot
    distances (P,L) in m from the cross-validation (NaN where no held-out
    prediction) and each pose's held-out chi^2 (P,) under the reference noise
    model, calibration distances (P,L), chi^2 under the reference noise model
    and BIC."""

    effects: tuple[Effect, ...]
    model: EffectModel
    estimate: Estimate
    cv: np.ndarray
    cv_chi2: np.ndarray
    cal: np.ndarray
    chi2: float
    n_values: int
    n_free: float  # effective parameters (fitter.effective_parameters): the count, less what priors hold

    @property
    def label(self) -> str:
        return " + ".join(["geometric"] + [e.label for e in self.effects])

    @property
    def dof(self) -> int:
        return max(self.n_values - self.n_free, 1)

    @property
    def bic(self) -> float:
        return self.n_values * math.log(max(self.chi2, 1e-300) / self.n_values) + self.n_free * math.log(self.n_values)


@dataclass(frozen=True)
class Ranked:
    """One candidate of a round: linearised held-out chi^2 per measured value
    (the ranking) and RMS (mm); for the shortlisted the fitted held-out chi^2
    per value and RMS (mm), the p of the fit test (Bonferroni-adjusted) and of
    the held-out test, the BIC change and the decision."""

    label: str
    linear_cv_chi2: float
    linear_cv_rms_mm: float
    cv_chi2: float | None = None
    cv_rms_mm: float | None = None
    p_fit: float | None = None
    p_heldout: float | None = None
    delta_bic: float | None = None
    outcome: str = "not shortlisted"


@dataclass(frozen=True)
class Stage:
    label: str
    fitted: Fitted
    test: np.ndarray | None  # (P_test, L) distances in m, NaN where not seen


@dataclass(frozen=True)
class NoiseInfo:
    """The noise the verdict uses (spot sigma m, joint sigma rad, each "given" or
    "estimated"), the degrees of freedom and pooled RMS per coordinate (m) of
    the scatter of repeated poses, the test of the residual level when there
    is one: its name, statistic, dof and p, and the tests of estimated
    components against their rated values."""

    spot_sigma: float
    spot_source: str
    joint_sigma: float
    joint_source: str
    repeat_dof: int = 0
    repeat_rms: float = 0.0
    level_test: str | None = None
    level_statistic: float | None = None
    level_dof: tuple[int, ...] | None = None
    level_p: float | None = None
    excess: tuple[tuple[str, float, float, float], ...] = ()  # (component, estimate, rated, p): verdict.excess_tests


@dataclass(frozen=True)
class Analysis:
    tests: list[Test]
    responses: list[Series]
    covariates: list[Series]


@dataclass(frozen=True)
class Prediction:
    """ratio: the test poses' mean square over the calibration's, their prediction
    variance allowed for (the F statistic on dof); p of "ratio 1", p_margin of "ratio at
    most margin^2" (diagnosis/prediction.py); beyond: how many test units were left out of
    it as beyond the robust rule's limit, and their names."""

    ratio: float
    dof: tuple[int, int]
    p: float
    p_margin: float
    margin: float
    beyond: int = 0
    beyond_named: str = ""

    def sentence(self) -> str:
        if not self.dof[0]:
            return (f"every test measurement ({self.beyond}) lies beyond the robust rule's limit "
                    f"({self.beyond_named}): the final model does not predict the test poses")
        text = (f"the test poses' whitened residual is {self.ratio:.2f} times the calibration poses' in mean square, "
                f"their prediction variance allowed for (predictive F on {self.dof[0]}, {self.dof[1]} dof: "
                f"p = {self.p:.2g} against 1, p = {self.p_margin:.2g} against {self.margin:g}^2)")
        if self.beyond:
            text += (f"; {self.beyond} test measurement{'s' * (self.beyond > 1)} beyond the robust rule's limit "
                     f"left out of it ({self.beyond_named})")
        return text


@dataclass(frozen=True)
class Diagnosis:
    robot: Robot
    samples: Readings
    test_samples: Readings | None
    stages: tuple[Stage, ...]
    rounds: tuple[tuple[Ranked, ...], ...]
    noise: NoiseInfo
    before: Analysis
    after: Analysis
    verdict: str
    evidence: str
    parameters: tuple[dict, ...]
    options: DiagnoseOptions
    wall_time: float
    merged: dict[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = field(default_factory=tuple)
    detection: Detection | None = None
    compensator: Compensator | None = None
    compensated_test: np.ndarray | None = None  # (P_test, L) m, the final model with the compensator
    nested: np.ndarray | None = None  # (P, L) m held out with the selection inside the folds (engine.nested_heldout)
    specification: tuple[Varying, ...] = ()  # the chosen form's tests, strongest first (specification.py)
    warnings: tuple[str, ...] = ()  # the diagnosis's own, beside its final fit's (verdict.worse_on_test)
    prediction: Prediction | None = None  # the test poses' predictive test (prediction.py), None without them

    @property
    def final(self) -> Fitted:
        return self.stages[-1].fitted

    @property
    def failure(self) -> str | None:
        """The final fit's warning that it is no calibration (NOT CONVERGED, NOT A CALIBRATION:
        estimation/failures.py), None when it is one: the robot it writes is then none."""
        return first_failure(self.final.estimate.warnings)

    @property
    def at_nominal(self) -> tuple[str, ...]:
        """What a failed final fit's file writes at nominal: what it kept but does not determine at its
        values (Estimate.undetermined), and the robot's errors it held, which a fit holds at its warm
        start, here the failed fit before it (the spots out of step with the joint readings: d2 held
        for the noise, written 0.75 m off under 'held at nominal'); none for a calibration."""
        if self.failure is None:
            return ()
        held = tuple(name for name in self.merged if name in self.robot.param_names)
        return (*self.final.estimate.undetermined, *held)

    def held_warnings(self) -> list[str]:
        """One line for the robot's errors held as merged: the console and report.md said nothing of
        them (only diagnosis.json and the robot file's header did)."""
        held = [name for name in self.robot.param_names if name in self.merged]
        if not held:
            return []
        total = len(self.robot.param_names)
        return [f"not separable: the data determine {total - len(held)} of the {total} geometric errors; held at "
                f"nominal before every fit, reported as combinations: {', '.join(held)}"]

    def calibrated_robot(self) -> Robot:
        """The robot with the geometric corrections and the ``effects:`` key
        (spot data: the base parameters are the D-H errors), at_nominal at zero: no
        geometric error, no effect (where every effect the diagnosis adds starts)."""
        final = self.final
        nominal = np.isin(final.model.names, self.at_nominal)
        geometric, values = final.model.split(np.where(nominal, 0.0, final.estimate.values))
        corrected = with_held(self.robot.with_errors(geometric), (*self.merged, *final.estimate.undetermined))
        extra = {k: v for k, v in corrected.extra.items() if k != "effects"}
        if final.effects:
            extra["effects"] = effects_to_yaml(final.effects, values)
        return replace(corrected, extra=extra)

    def to_json(self) -> dict:
        return {
            "robot": self.robot.name,
            # what the covariates q1..qN and the effects' joint numbers are: a URDF's joint names
            "joints": {f"q{i + 1}": name for i, name in enumerate(self.robot.joint_names)},
            "stages": [{"model": s.label, "cal": summary(s.fitted.cal, 1e3, "_mm"), "cv": summary(s.fitted.cv, 1e3, "_mm"),
                        "test": None if s.test is None else summary(s.test, 1e3, "_mm"),
                        "parameters": int(s.fitted.estimate.identifiable.sum()),
                        "bic": s.fitted.bic, "spot_sigma_m": s.fitted.estimate.sigma,
                        "chi2": s.fitted.estimate.fit.chi2, "dof": s.fitted.estimate.fit.dof}
                       for s in self.stages],
            "effects": list(self.parameters),
            "not_identifiable": dict(self.merged),
            "heldout_nested": None if self.nested is None else summary(self.nested, 1e3, "_mm"),
            "verdict": self.verdict,
            "evidence": self.evidence,
            "failure": self.failure,
            # the final fit's own warnings (held parameters, implausible values, ...), as `estimate` gives
            # them, the robot's errors the data cannot separate (held before every fit, so no fit says so),
            # then the diagnosis's (a test set the effects make worse)
            "warnings": list(self.final.estimate.warnings) + self.held_warnings() + list(self.warnings),
            "noise": {"spot_sigma_m": self.noise.spot_sigma, "spot_sigma_source": self.noise.spot_source,
                      "joint_sigma_rad": self.noise.joint_sigma, "joint_sigma_source": self.noise.joint_source,
                      "repeated_pose_dof": self.noise.repeat_dof,
                      "repeated_pose_rms_m": self.noise.repeat_rms, "level_test": self.noise.level_test,
                      "level_statistic": self.noise.level_statistic,
                      "level_dof": None if self.noise.level_dof is None else list(self.noise.level_dof),
                      "level_p": self.noise.level_p,
                      "above_rated": [{"component": c, "estimate": e, "rated": r, "p": p}
                                      for c, e, r, p in self.noise.excess]},
            "structure": {"before": [_test_json(t) for t in self.before.tests[:10]],
                          "after": [_test_json(t) for t in self.after.tests[:10]]},
            "selection": [[{k: v for k, v in r.__dict__.items()} for r in ranking] for ranking in self.rounds],
            "options": {k: v for k, v in self.options.__dict__.items()},
            "wall_time_s": self.wall_time,
            "notes": list(self.notes),
            "detector": None if self.detection is None else {
                "heldout_gain": self.detection.gain, "p": self.detection.p, "null_99": self.detection.null_99,
                "importance": [{"input": n, "mse_increase": v, "std": s} for n, v, s in self.detection.importance]},
            "specification": [{"parameter": v.parameter, "covariate": v.covariate, "F": v.f, "dof": list(v.dof),
                               "p": v.p, "p_adjusted": v.p_adjusted, "share": v.share, "shape": v.shape}
                              for v in self.specification[:10]],
            "test_prediction": None if self.prediction is None else {
                "ratio": self.prediction.ratio if math.isfinite(self.prediction.ratio) else None,
                "dof": list(self.prediction.dof), "p": self.prediction.p,
                "margin": self.prediction.margin, "p_margin": self.prediction.p_margin,
                "beyond_limit": self.prediction.beyond},
            "compensator": None if self.compensator is None else {
                "heldout_gain": self.compensator.heldout_gain, "file": "compensator.json",
                "targets": [t for t, u in zip(self.compensator.targets, self.compensator.used) if u],
                "test": None if self.compensated_test is None else summary(self.compensated_test, 1e3, "_mm")},
        }


def _test_json(t: Test) -> dict:
    return {"response": t.response, "covariate": t.covariate, "F": t.f, "dof": list(t.dof), "p": t.p,
            "p_adjusted": t.p_adjusted, "eta2": t.eta2}
