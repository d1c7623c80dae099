"""The verdict: the noise of the final residual, the test of its level and
the structure tests."""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from laser_calib.diagnosis.data import Data
from laser_calib.diagnosis.detector import Detection
from laser_calib.diagnosis.noise import pure_error
from laser_calib.diagnosis.options import (EXPLAINED, MIN_DETECTOR_POSES, MIN_REPEAT_DOF, STRUCTURE,
                                           UNDETERMINED, DiagnoseOptions)
from laser_calib.diagnosis.result import Analysis, Fitted, NoiseInfo, Prediction, Stage
from laser_calib.diagnosis.specification import Varying
from laser_calib.diagnosis.structure import Readings, joined, pose_covariates, pose_responses, structure_tests
from laser_calib.estimation.problem import pose_blocks, residuals_at
from laser_calib.estimation.redundancy import NOISE_RATIO
from laser_calib.measurement.base import NoiseModel, Residuals, whiten
from laser_calib.measurement.noise_components import boundary_p, deviance, noise_components
from laser_calib.report.statistics import worse_on_test_warning

# The start of the warning worse_on_test gives (the benches count the diagnoses that gave it).
WORSE_ON_TEST = "test: the final model misses the test poses by more than the geometric one"


def worse_on_test(stages: list[Stage], poses: np.ndarray | None) -> list[str]:
    """The warning when the final model misses the test poses by more than the geometric one (RMS
    over the measurements both predict), as `estimate` warns of a calibration worse than the nominal
    model on its test set (report.calibration.worse_on_test). The effects were chosen on the
    calibration poses; the one set they never saw says they do not carry over: a surface
    extrapolated beyond the calibration spots, an effect standing in for another, or a test set
    measured under other conditions. A per-pose rank test would miss the usual case: the effects
    help most poses a little and miss a few by much (a joint scale the test poses do not have: RMS
    1.8 -> 2.5 mm, Wilcoxon p = 0.02). When one test pose (ids ``poses`` (P,), None without a test
    set) carries most of the increase, the warning names it (report.statistics.worse_on_test_warning)."""
    first, last = stages[0].test, stages[-1].test
    if len(stages) < 2 or first is None or last is None or poses is None:
        return []
    return worse_on_test_warning(
        first, last, poses,
        WORSE_ON_TEST + " (RMS {before:.3g} mm -> {after:.3g} mm over the {count} measurements both predict)",
        "the effects chosen on the calibration poses do not carry over to them (an effect standing in for another, "
        "a surface extrapolated beyond the calibration spots, or test poses measured under other conditions)")


def verdict_noise(final: Fitted, samples: Readings, options: DiagnoseOptions,
                  rated: tuple[float | None, float | None] = (None, None)) -> NoiseInfo:
    """The noise model of the verdict and the test of the residual level.

    Components not given are estimated by maximum likelihood from the final
    residual (noise_components), so the structure tests weight every pose by
    its real noise. The level can then be tested only against what was given
    or measured: a chi^2 test when both components are given, a lack-of-fit F
    test against the scatter of repeated poses (pure error) when there are
    any and they scatter at all (copied rows do not); otherwise it is not
    tested. An estimated component with a rated value (rated_noise: what the
    robot file says the hardware can do) is tested against it (excess_tests).
    """
    est = final.estimate
    res = residuals_at(final.model, est.values, jacobian=True, parameters=False)  # by blocks: bounded transients
    m = int(res.valid.sum()) * res.r.shape[2]
    dof = max(round(m - final.n_free), 1)  # effective parameters: a penalised screen spends fewer than it has
    scale = math.sqrt(m / dof)
    spot, joint = noise_components(res, scale, options.spot_sigma, options.joint_sigma)
    sources = ("given" if options.spot_sigma is not None else "estimated",
               "given" if options.joint_sigma is not None else "estimated")
    noise = NoiseModel(spot, joint)
    pure, repeat_dof, repeat_rms = pure_error(samples, res, noise)
    excess = excess_tests(res, scale, (spot, joint), (options.spot_sigma, options.joint_sigma), rated)
    common = (spot, sources[0], joint, sources[1], repeat_dof, repeat_rms)
    if options.spot_sigma is not None and options.joint_sigma is not None:
        r, _ = whiten(res, noise.whitener(res))
        chi2 = float(r @ r)
        return NoiseInfo(*common, "chi^2", chi2, (dof,), float(stats.chi2.sf(chi2, dof)), excess)
    if repeat_dof >= MIN_REPEAT_DOF and dof > repeat_dof and pure > 0:  # repeats that never scatter: copies
        # Lack of fit: the whitened residual beyond the pure error of repeated poses.
        r, _ = whiten(res, noise.whitener(res))
        f = ((float(r @ r) - pure) / (dof - repeat_dof)) / (pure / repeat_dof)
        return NoiseInfo(*common, "lack-of-fit F", f, (dof - repeat_dof, repeat_dof),
                         float(stats.f.sf(f, dof - repeat_dof, repeat_dof)), excess)
    return NoiseInfo(*common, excess=excess)


def excess_tests(res: Residuals, scale: float, estimate: tuple[float, float], given: tuple[float | None, float | None],
                 rated: tuple[float | None, float | None]) -> tuple[tuple[str, float, float, float], ...]:
    """(component, estimate, rated, p) for each component estimated (not given)
    that has a rated value: the one-sided likelihood-ratio test of "its sigma
    is at most the rated one". Deviance at the maximum-likelihood estimate
    against the profile with the component held at its rated value (the other,
    when not given, re-estimated): chi^2(1) asymptotically, halved for the
    one-sided alternative (the null on the boundary). A sigma above what the
    hardware can do is structure the noise estimate took in (a joint error that
    follows the pose looks like joint-reading noise to a fit that has no term for it)."""
    value = deviance(res, scale)
    at_estimate = value(*estimate)
    out = []
    for index, name in enumerate(("spot", "joint-reading")):
        if given[index] is not None or rated[index] is None:
            continue
        held = tuple(rated[i] if i == index else given[i] for i in range(2))
        ratio = value(*noise_components(res, scale, *held)) - at_estimate if estimate[index] > rated[index] else 0.0
        out.append((name, estimate[index], rated[index], boundary_p(ratio)))
    return tuple(out)


def analysis(data: Data, fitted: Fitted, noise: NoiseModel) -> Analysis:
    """Structure tests of a fit's residual: the pose-level responses and
    covariates of every measurement model, and the data's measurement-level ones.
    Each is of its own pose, so they are formed block by block of poses (the
    Jacobians of one block at a time) and joined."""
    model, x = fitted.model, fitted.estimate.values
    resp, level_cov = [], []
    for index, block in pose_blocks(model):
        part = data if index == slice(None) else data.subset(np.arange(index.start, index.stop))
        res = block.residuals(x, True)
        block_resp, block_cov = part.series(block, x, res, noise)
        resp.append(pose_responses(model.robot, res, noise) + block_resp)
        level_cov.append(block_cov)
    cov = pose_covariates(model.robot, data.samples) + joined(level_cov)
    resp = joined(resp)
    return Analysis(structure_tests(resp, cov), resp, cov)


def excess_noise(noise: NoiseInfo, alpha: float) -> str | None:
    """The sentence saying an estimated noise component is significantly above its rated value, or None."""
    for name, value, limit, p in noise.excess:
        if p < alpha:
            unit, factor = ("mm", 1e3) if name == "spot" else ("deg", float(np.degrees(1.0)))
            return (f"the estimated {name} sigma, {value * factor:.3g} {unit}, is {value / limit:.2f} times what the "
                    f"robot file says the hardware can do ({limit * factor:.3g} {unit}; likelihood-ratio p = {p:.2g}): "
                    "structure taken as noise")
    return None


def evidence(after: Analysis, noise: NoiseInfo, detection: Detection, n_poses: int, alpha: float,
             varying: list[Varying] | tuple[Varying, ...] = ()) -> tuple[str, str]:
    """The verdict and its evidence (engine docstring, 3.); varying: the
    specification tests of the chosen form, strongest first (specification.py)."""
    tests = after.tests
    structure = bool(tests) and tests[0].p_adjusted < alpha
    level_fail = noise.level_p is not None and noise.level_p < alpha
    # given sigmas far above the residual (estimation.redundancy's NOISE_RATIO): the chi^2 test
    # passes whatever remains, so it is no test of the level
    overstated = noise.level_test == "chi^2" and noise.level_statistic / noise.level_dof[0] < NOISE_RATIO ** -2
    parts = []
    if tests:
        parts.append(("Structure: " if structure else "No covariate explains the residual; strongest: ")
                     + tests[0].sentence() + f", {len(tests)} tests.")
    sources = {"given": "given", "estimated": "estimated from the residual by maximum likelihood"}
    sigma_text = (f"spot sigma {noise.spot_sigma * 1e3:.3g} mm {sources[noise.spot_source]}, joint-reading sigma "
                  f"{np.degrees(noise.joint_sigma):.3g} deg {sources[noise.joint_source]}")
    if noise.level_test == "chi^2":
        parts.append(f"Level: chi^2 = {noise.level_statistic:.1f} on {noise.level_dof[0]} dof (ratio "
                     f"{noise.level_statistic / noise.level_dof[0]:.2f}, p = {noise.level_p:.2g}) with {sigma_text}"
                     + (": the residual exceeds the noise." if level_fail else
                        f": the residual is far below the given noise (about "
                        f"{np.sqrt(noise.level_statistic / noise.level_dof[0]):.2g} of it): the sigmas given are "
                        "overstated, and this test sees nothing." if overstated else "."))
    elif noise.level_test is not None:
        parts.append(f"Level: lack-of-fit F = {noise.level_statistic:.3g} on {noise.level_dof[0]}, "
                     f"{noise.level_dof[1]} dof against the scatter of repeated poses ({noise.repeat_rms * 1e3:.3g} "
                     f"mm RMS per coordinate; p = {noise.level_p:.2g})"
                     + (": the residual exceeds the noise" if level_fail else "") + f"; {sigma_text}.")
    else:
        repeats = ("no repeated poses" if not noise.repeat_dof else "too few repeated poses" if noise.repeat_rms
                   else "repeated poses without any scatter (copied rows?)")
        parts.append(f"The residual level is not tested: the noise is not fully given and there are {repeats} "
                     f"({sigma_text}).")
    detected = detection.p <= alpha and detection.gain > 0
    parts.append(("Detector: " if detected else "Detector, nothing significant: ") + detection.sentence() + ".")
    misspecified = bool(varying) and varying[0].p_adjusted < alpha
    if varying:
        parts.append(("Form: structure remains: " if misspecified else "Form, no parameter varies significantly; "
                      "strongest: ") + varying[0].sentence() + f", {len(varying)} tests.")
    excess = excess_noise(noise, alpha)
    if excess:
        parts.append(f"Noise: {excess}.")
    if structure or level_fail or detected or excess or misspecified:
        return STRUCTURE, " ".join(parts)
    if (noise.level_test is None or overstated) and n_poses < MIN_DETECTOR_POSES:
        parts.append(f"Undetermined: the level is not tested and {n_poses} poses are too few for the detector "
                     f"to see more than large structure (it needs about {MIN_DETECTOR_POSES}).")
        return UNDETERMINED, " ".join(parts)
    return EXPLAINED, " ".join(parts)


def with_left_out(verdict: str, evidence: str, left_out: int) -> tuple[str, str]:
    """The verdict once the measurements left out of the diagnosis are counted: ``left_out``
    units the geometric calibration rejected as gross outliers, which the final model does
    not fit either (screening.misfits). "Explained" speaks of the measurements fitted; of those left out
    the data cannot tell a wrong detection from structure the model lacks where they lie (a
    link's sag or a leaning screen is largest at grazing beams, whose spots the robust rule
    rejects), so "explained" becomes "undetermined"."""
    if verdict != EXPLAINED or not left_out:
        return verdict, evidence
    return UNDETERMINED, (f"{evidence} Undetermined: the residual of the measurements fitted is explained, but "
                          f"{left_out} measurement{'s' * (left_out > 1)} rejected as gross outliers, which the final "
                          "model does not fit either, may be wrong detections or structure the model lacks where "
                          "they lie (the notes list them).")


def predicted(verdict: str, evidence: str, prediction: Prediction | None, alpha: float) -> tuple[str, str]:
    """The verdict once the test poses are counted (prediction.py): a test set the final model
    predicts by more than the margin worse than it fits the calibration poses is structure they
    did not show, whatever they said; test measurements left out of that test as beyond the
    robust rule's limit make "explained" "undetermined", as the calibration's own do
    (with_left_out). A significant excess within the margin is warned of (prediction_warning)."""
    if prediction is None:
        return verdict, evidence
    failed = prediction.p_margin < alpha
    said = f"{evidence} {'Test poses: structure remains: ' if failed else 'Test poses: '}{prediction.sentence()}."
    if failed:
        return STRUCTURE, said
    if verdict == EXPLAINED and prediction.beyond:
        return UNDETERMINED, (f"{said} Undetermined: the final model misses those test measurements grossly; the "
                              "data cannot tell wrong detections from structure the model lacks where they lie.")
    return verdict, said


def prediction_warning(prediction: Prediction | None, alpha: float) -> list[str]:
    """The warning when the test poses are fitted significantly worse than the calibration poses but
    within the margin the verdict allows (predicted): at alpha, a chance once in 1 / alpha data sets."""
    if prediction is None or prediction.p >= alpha or prediction.p_margin < alpha:
        return []
    return [f"test: the test poses are fitted worse than the calibration poses (mean square {prediction.ratio:.2f} "
            f"times theirs, p = {prediction.p:.2g}; within {prediction.margin:g} times in RMS, which the verdict "
            "allows): chance at this rate, or conditions that differ between the two sets"]
