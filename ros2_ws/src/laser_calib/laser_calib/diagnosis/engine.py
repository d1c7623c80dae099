"""Diagnosis: find what the geometric model lacks, name it, add it, check the rest.

diagnose(robot, samples, test, spot_sigma, joint_sigma) runs the engine, run(),
on laser spot data (SpotData). run(data, options) works on any data set that
gives a base measurement model, its candidate effects and its measurement-level
covariates (the Data protocol; sensor_data.SensorData for point and pose
sensors, which adds the sensor's scale as a candidate); candidates the base
model cannot carry (screen and lens effects without spots) are dropped. It runs:

0. the units the geometric estimate refuses (gross outliers, impossible
   spots) are left out of everything below and listed (diagnosis.screening).
1. the geometric fit (estimation.estimate_model, as every fit here). Noise
   components not given are estimated from its residual by maximum
   likelihood (noise_components) and the fit repeated with them: this is the
   reference noise model every later fit, test and whitening uses (an effect
   still in the residual inflates it, which only makes the tests cautious);
   the final model's reported values and standard deviations are of a refit
   at the noise of its own residual (Fitter.at_noise).
   Parameters the nominal geometry cannot separate stay fixed in every fit, as
   do those the data set fixes (data.fixed).
2. rounds of selection over the effect library (effects.catalog.candidates:
   each effect at each joint, length/covariate or target where the data can
   show it). A round screens every candidate with the linearised
   cross-validation (one Gauss-Newton solve per fold at the current fit,
   effect parameters starting at 0) and ranks them by held-out chi^2 (each
   held-out pose's residual whitened by the reference noise model); it fits
   the ``shortlist`` best jointly with the geometric errors and the effects
   already in (warm start) and cross-validates them with full fits per fold
   (the same seeded folds for every model). A candidate passes when
     - the fit improves: F test of the chi^2 decrease, F = (Δchi^2/Δk) /
       (chi^2/dof), Bonferroni-adjusted over the round's candidates, p < alpha
       (this carries the multiplicity of picking the best of many), and
     - the held-out error improves: one-sided paired t test over the
       calibration poses of the held-out chi^2 (current model minus
       candidate), p < alpha, and
     - its BIC = M ln(chi^2/M) + k ln M is lower (M measured values, k free
       parameters), and it is physical (diagnosis.selection: a parameter that
       can be reported, sensor-side values within their sensor's limits).
   Of those that pass, the one with the lowest held-out chi^2 is added, unless
   another is not significantly worse (paired p >= 0.05) and has a lower BIC
   (the simpler explanation of the same held-out error, used for the figures;
   the group is reported as such and never makes the verdict "explained"). Rounds repeat until none passes or ``max_effects`` are in.
3. the verdict (verdict_noise, _evidence): structure tests of the final
   residual against every covariate (effects.residuals, Bonferroni-adjusted),
   weighted by the noise (components not given re-estimated from the final
   residual), and a test of the residual level where the noise is known: a
   chi^2 test when spot and joint sigma are both given, else a lack-of-fit F
   test against the scatter of repeated poses when the data has any, else
   none (and the evidence says so); the flexible detector (detector.py) and
   the specification test of the chosen form (specification.py: does any
   parameter of the final model vary with a covariate). "explained" when no
   test is significant at alpha, "structure remains" otherwise, with the
   strongest test as evidence; "undetermined" instead of "explained" where the
   level is untested and the poses are too few for the detector, where the data
   cannot tell effects apart, or where measurements the geometric calibration
   refused stay left out (verdict.with_left_out).
   With more than SELECTION_POSES poses the rounds run on that many (runs of
   consecutive poses spread over the session, selection_rows) and each stage
   is then refitted and cross-validated on all poses, warm from its fit there:
   the rounds' fits and folds cost a bounded time, while every figure and
   test of the stages is of all poses (the nested held-out error likewise:
   per outer fold the selection on at most SELECTION_POSES training poses,
   the chosen model refitted on all of them, every held-out pose scored).
   The structure and specification tests see every pose; the detector (and
   the compensator it may give) sees at most DETECTOR_POSES of them
   (detector_rows): its cost and memory grow with the poses times its basis
   (about 1,500 columns per value; at 5,000 poses it took three quarters of the
   whole diagnosis of 10,000), and its power at 2,000 poses (8,000 spot
   values for sub-models of at most 13 columns) is plenty for what it looks for.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from laser_calib.diagnosis.compensation import backfit
from laser_calib.diagnosis.data import Data, SpotData, supports
from laser_calib.diagnosis.detector import detect
from laser_calib.diagnosis.fitter import Fitter, distances
from laser_calib.diagnosis.options import MIN_TRAINING_RATIO, DiagnoseOptions
from laser_calib.diagnosis.prediction import predictive_test
from laser_calib.diagnosis.result import Diagnosis, Stage
from laser_calib.diagnosis.screening import Refused, misfits, screened, screened_again, taken_back_by_either
from laser_calib.diagnosis.selection import ambiguous_verdict, parameter_report, select
from laser_calib.diagnosis.specification import covariate_table, drift_covariates, load_table, specification_tests
from laser_calib.diagnosis.verdict import (analysis, evidence, predicted, prediction_warning, verdict_noise,
                                           with_left_out, worse_on_test)
from laser_calib.diagnosis.writer import write_outputs
from laser_calib.effects.base import Effect
from laser_calib.effects.effect_model import EffectModel
from laser_calib.effects.joint import gravity_torques
from laser_calib.effects.screen import Surface, extrapolation_note
from laser_calib.estimation.failures import first_failure
from laser_calib.estimation.folds import kfold_labels, test_range_warnings
from laser_calib.estimation.problem import pose_blocks, residuals_at
from laser_calib.io.errors import InputError
from laser_calib.io.revisits import repeat_warnings
from laser_calib.io.samples import Samples, reading_warnings
from laser_calib.measurement.base import NoiseModel
from laser_calib.model.robot import Robot
from laser_calib.model.robot_file import held, rated_noise

__all__ = ["DiagnoseOptions", "Diagnosis", "diagnose", "run", "supports", "write_outputs"]


def diagnose(robot: Robot, samples: Samples, test: Samples | None = None, spot_sigma: float | None = None,
             joint_sigma: float | None = None, options: DiagnoseOptions | None = None,
             sources: dict | None = None) -> Diagnosis:
    """Diagnose, select and add effects (module docstring). spot_sigma (m) and
    joint_sigma (rad) override those of ``options``; sources: the files of the
    samples and the test set, named in the notes. ValueError (InputError) on
    bad input."""
    options = options or DiagnoseOptions()
    options = replace(options, spot_sigma=spot_sigma if spot_sigma is not None else options.spot_sigma,
                      joint_sigma=joint_sigma if joint_sigma is not None else options.joint_sigma)
    for name, s in (("samples", samples), ("test", test)):
        if s is not None and s.n_joints != robot.n_joints:
            raise InputError(name, f"{s.n_joints} joint columns but robot '{robot.name}' has {robot.n_joints} joints")
    missing = [c for c in samples.extra if test is not None and c not in test.extra]
    if missing:
        raise InputError("test", f"no column '{missing[0]}' (the calibration samples have it, and an effect may "
                                 "follow it)")
    notes = []
    if "effects" in robot.extra:
        notes.append("the input robot's effects key was not used: the diagnosis starts from the geometric model")
    notes += repeat_warnings(samples, test, robot.joint_names, sources or {})
    if held(robot):
        notes.append(f"held at nominal, as the calibration that wrote the robot file held them (its key held): "
                     f"{', '.join(held(robot))}")
    diagnosis = run(SpotData(robot, samples, held(robot)), options, None if test is None else SpotData(robot, test),
                    tuple(notes))
    # warnings, as estimate gives them
    return replace(diagnosis, warnings=(*reading_warnings(samples, test), *diagnosis.warnings))


class TooFewPoses(InputError):
    """A data limit, not a failure: too few poses to cross-validate (minimum_poses)."""

    def __init__(self, n_poses: int, needed: int):
        super().__init__("samples", f"{n_poses} poses, at least {needed} needed for the diagnosis")
        self.n_poses, self.needed = n_poses, needed


def minimum_poses(n_errors: int, values_per_pose: float, folds: int) -> int:
    """The fewest poses the diagnosis runs on: one per fold (estimation.folds.kfold_labels), and
    the smallest training fold (all poses but the largest fold) holding at least as many
    measured values as there are geometric errors, below which its estimate is refused
    (estimate_model)."""
    n = folds
    while values_per_pose > 0 and (n - math.ceil(n / folds)) * values_per_pose < n_errors:
        n += 1
    return n


def minimum_poses_nested(needed: int, folds: int) -> int:
    """The fewest poses whose every training part (all poses but the largest fold,
    kfold_labels) holds ``needed``: a diagnosis run again inside the folds needs as many."""
    n = needed
    while n - math.ceil(n / folds) < needed:
        n += 1
    return n


def run(data: Data, options: DiagnoseOptions, test: Data | None = None, notes: tuple[str, ...] = ()) -> Diagnosis:
    """The diagnosis engine (module docstring) on any data set: the geometric
    fit of data.base(), selection over the candidates the base model supports,
    the verdict; test (the same kind of data) predicted at every stage."""
    start = time.perf_counter()
    notes = list(notes)
    n_poses = len(data.samples.q)
    needed = minimum_poses(len(data.base().names) - len(data.fixed), data.measured_values() / max(n_poses, 1),
                           options.folds)
    if n_poses < needed:
        raise TooFewPoses(n_poses, needed)
    kept, refused = screened(data, options)
    if refused is None:
        return diagnosed(data, options, test, notes, start)
    diagnosis = diagnosed(kept, options, test, notes + refused.note(data, options), start)
    again = screened_again(data, diagnosis.final, diagnosis.noise, refused)
    if again is None or again.units.any():
        # The kept data may not show the effect whose far end the refused units are (a curved
        # screen's sag at its corners): the effects selected on every unit judge them too.
        final = selected(data, options, [], "selection with the refused units")[2][-1]
        again = taken_back_by_either(again, screened_again(data, final, diagnosis.noise, refused))
    if again is None:
        return counted(data, diagnosis, refused)
    return counted(data, diagnosed(data.without(again.units), options, test, notes + again.note(data, options),
                                   start), again)


def counted(data: Data, diagnosis: Diagnosis, refused: Refused) -> Diagnosis:
    """The diagnosis whose verdict counts the rejected units its final model does not fit
    (screening.misfits, verdict.with_left_out)."""
    verdict, said = with_left_out(diagnosis.verdict, diagnosis.evidence,
                                  misfits(data, diagnosis.final, diagnosis.noise, refused))
    return replace(diagnosis, verdict=verdict, evidence=said)


def diagnosed(data: Data, options: DiagnoseOptions, test: Data | None, notes: list[str], start: float) -> Diagnosis:
    """run() on the data the screening kept."""
    n_poses = len(data.samples.q)
    needed = minimum_poses(len(data.base().names) - len(data.fixed), data.measured_values() / max(n_poses, 1),
                           options.folds)
    fitter, on, fits, rounds, alternatives = selected(data, options, notes, "selection")
    if on is not data:
        notes.append(f"effects selected on {len(on.samples.q)} of the {n_poses} poses ({SELECTION_RUNS} runs of "
                     "consecutive poses spread over the session); each stage refitted and cross-validated on all poses, "
                     "which every figure and test is of (the selection rounds' figures are of the poses selected on)")
        scorer = fitter.on(data, "all poses")
        fits = [scorer.fit(f.effects, f.estimate.values) for f in fits]
        fitter = scorer
    nested = None
    training = n_poses - math.ceil(n_poses / options.folds)  # poses of the smallest training part
    if options.nested and training < needed:
        notes.append(f"no held-out error with the selection inside the folds: a training part of {n_poses} poses "
                     f"holds {training}, the diagnosis needs {needed}")
    elif options.nested:
        nested = nested_heldout(data, options)
    return finish(data, options, test, fitter, fits, rounds, alternatives, nested, notes, start)


def selected(data: Data, options: DiagnoseOptions, notes: list[str], stage: str):
    """select() on at most SELECTION_POSES of the poses (selection_rows): its Fitter, the
    data it selected on (``data`` itself when it has no more), the stages' fits there, the
    rounds and the alternatives."""
    rows = selection_rows(len(data.samples.q), options.seed)
    on = data if rows is None else data.subset(rows)
    fitter = Fitter(on, options, stage)
    fits, rounds, alternatives = select(fitter, candidate_pool(on, fitter, options, notes), options)
    return fitter, on, fits, rounds, alternatives


def candidate_pool(data: Data, fitter: Fitter, options: DiagnoseOptions, notes: list[str]) -> list[Effect]:
    """The candidates the base model supports, none when a training fold is too
    small to select on (the reason appended to ``notes``)."""
    pool = [c for c in data.candidates() if supports(fitter.base, c)]
    training_values = data.measured_values() * (options.folds - 1) / options.folds
    n_errors = len(fitter.base.names) - len(data.fixed)
    needed = MIN_TRAINING_RATIO * n_errors
    if training_values < needed:
        # With a training fold barely determining the geometric errors, held-out
        # errors are dominated by the fold's own ill-conditioning and the selection
        # adds effects on chance (seen: a 0.17 deg 'backlash' on 20 effect-free poses).
        per_pose = data.measured_values() / max(len(data.samples.q), 1)
        notes.append(f"too few poses to select effects: a training fold holds {training_values:.0f} measured "
                     f"values for {n_errors} geometric errors (needs {needed:.0f}, about "
                     f"{math.ceil(needed * options.folds / (options.folds - 1) / max(per_pose, 1e-9))} poses); "
                     "only the geometric model and the residual tests are reported")
        pool = []
    return pool


def nested_heldout(data: Data, options: DiagnoseOptions) -> np.ndarray:
    """(P,L) held-out spot distances (m) of the whole procedure, selection
    included: per outer fold (a split unlike the selection's), the selection
    on the other folds alone, the pose predicted by the model it chose there."""
    n_poses = len(data.samples.q)
    fold = kfold_labels(n_poses, options.folds, options.seed + 1)
    whole = data.base()
    out = None
    for k in range(options.folds):
        train, held = np.flatnonzero(fold != k), np.flatnonzero(fold == k)
        inner = data.subset(train)
        stage = f"nested fold {k + 1}/{options.folds}"
        fitter, on, fits, _, _ = selected(inner, options, [], stage)
        chosen = fits[-1]
        values = chosen.estimate.values
        if on is not inner:  # the chosen model fitted on every training pose
            if options.progress is not None:
                options.progress(0, None, f"{stage}: {chosen.label} on all {len(train)} training poses")
            values = fitter.on(inner, stage).estimate(chosen.effects, values)[1].values
        predicted = distances(EffectModel(whole, chosen.effects).subset(held), values)
        out = np.full((n_poses,) + predicted.shape[1:], np.nan) if out is None else out
        out[held] = predicted
    return out


def finish(data: Data, options: DiagnoseOptions, test: Data | None, fitter: Fitter, fits, rounds, alternatives,
           nested: np.ndarray | None, notes: list[str], start: float) -> Diagnosis:
    """The stages' test errors, the verdict, the detector and the compensator."""
    final = fits[-1]
    if options.progress is not None:
        options.progress(0, None, "the verdict's noise and structure tests")
    noise = verdict_noise(final, data.samples, options, rated_noise(data.robot))
    if options.spot_sigma is None or options.joint_sigma is None:
        fits = fits[:-1] + [fitter.at_noise(final, noise.spot_sigma, noise.joint_sigma)]
        final = fits[-1]
    stages = []
    for fitted in fits:
        test_d = None if test is None else distances(EffectModel(test.base(), fitted.effects),
                                                      fitted.estimate.values)
        stages.append(Stage(fitted.label, fitted, test_d))
    if test is not None:
        notes.extend(test_range_warnings(data.samples.q, test.samples.q, "test", data.robot.joint_names))
    if isinstance(test, SpotData):
        beyond = extrapolation_note([e.label for e in final.effects if isinstance(e, Surface)], data.samples.spots,
                                    test.samples.spots)
        if beyond:
            notes.append(beyond)
    noise_model = NoiseModel(noise.spot_sigma, noise.joint_sigma)
    before, after = analysis(data, fits[0], noise_model), analysis(data, final, noise_model)
    samples = data.samples
    # Whitened by the verdict's noise model: every value then has unit variance, which the
    # permutation test needs (the poses' residuals exchangeable under "no structure").
    detector_noise = noise_model
    rows = detector_rows(len(samples.q), options.seed)
    seen = final.model if rows is None else final.model.subset(rows)
    if options.progress is not None:
        options.progress(0, None, f"detector on {len(seen.samples.q)} poses")
    values = final.estimate.values
    detection = detect(final.model.names, residuals_at(seen, values, jacobian=True), detector_noise, seen.samples.q,
                       seen.samples.stamp, dict(seen.samples.extra), fitter.fold if rows is None else fitter.fold[rows],
                       options.seed)
    if options.progress is not None:
        options.progress(0, None, f"specification tests on {len(samples.q)} poses")
    # the final model's residuals and Jacobians block by block of poses: the test keeps only sums
    blocks = ((index, block.residuals(values, True)) for index, block in pose_blocks(final.model))
    varying = specification_tests(final.model.names, final.estimate.identifiable, blocks, noise_model,
                                  covariate_table(samples.q, samples.stamp, dict(samples.extra)),
                                  final.model.n_geometric, load_table(gravity_torques(data.robot, samples.q)),
                                  drift_covariates(final.effects))
    verdict, said = evidence(after, noise, detection, len(samples.q), options.alpha, varying)
    parameters = parameter_report(final, alternatives)
    verdict, said = ambiguous_verdict(verdict, said, parameters)
    prediction = None if test is None else predictive_test(final, test, noise_model)
    verdict, said = predicted(verdict, said, prediction, options.alpha)
    compensator = compensated = None
    if options.compensate and detection.p <= options.alpha and detection.gain > 0:
        failed = first_failure(final.estimate.warnings)
        if failed:  # a regression of what a wrong model misses would be a file `estimate --compensator` applies
            notes.append(f"no learned compensator: the final fit is no calibration ({failed.split(':')[0]})")
        else:
            compensator = backfit(detection, seen, final.estimate.values, fitter.fit_options, detector_noise,
                                  fitter.fold if rows is None else fitter.fold[rows])
            if test is not None:
                compensated = distances(compensator.apply(EffectModel(test.base(), final.effects)),
                                        compensator.values)
    merged = {**fitter.merged, **final.estimate.identifiability.merged}
    return Diagnosis(data.robot, data.samples, None if test is None else test.samples, tuple(stages), tuple(rounds),
                     noise, before, after, verdict, said, parameters, replace(options, progress=None),
                     time.perf_counter() - start, merged, tuple(notes), detection, compensator, compensated, nested,
                     tuple(varying), tuple(worse_on_test(stages, None if test is None else test.samples.pose)
                                           + prediction_warning(prediction, options.alpha)), prediction)



# Poses the detector sees at most, in DETECTOR_RUNS runs of consecutive poses: the
# detector's move inputs are the sign and size of the last move in row order, which a run keeps
# (only its first pose's is taken from the run before), and the runs spread over the
# whole session, so a slow change with the stamp stays in view.
DETECTOR_POSES = 2000
DETECTOR_RUNS = 10
# Poses the selection rounds see at most, in SELECTION_RUNS runs (as the detector's: the
# approach directions of backlash and the stamps of a drift keep their meaning). Its cost
# is the rounds' fits times the folds, per pose, and the nested held-out error repeats it
# per outer fold; 2,000 poses (8,000 spot values for ~40 parameters) resolve a library
# effect far below the noise, and every stage is then refitted and scored on all poses.
SELECTION_POSES = 2000
SELECTION_RUNS = 10


def session_runs(n_poses: int, limit: int, runs: int, seed: int) -> np.ndarray | None:
    """(limit,) sorted pose indices, None for all when there are no more than ``limit``:
    one run of consecutive poses at a seeded place in each of ``runs`` equal parts of the
    sequence."""
    if n_poses <= limit:
        return None
    rng = np.random.default_rng(seed)
    edges = np.linspace(0, n_poses, runs + 1).astype(int)
    length = limit // runs
    starts = [rng.integers(lo, hi - length + 1) for lo, hi in zip(edges[:-1], edges[1:])]
    return np.concatenate([np.arange(start, start + length) for start in starts])


def detector_rows(n_poses: int, seed: int) -> np.ndarray | None:
    """The DETECTOR_POSES poses the detector sees (session_runs), None for all."""
    return session_runs(n_poses, DETECTOR_POSES, DETECTOR_RUNS, seed)


def selection_rows(n_poses: int, seed: int) -> np.ndarray | None:
    """The SELECTION_POSES poses the selection rounds see (session_runs), None for all."""
    return session_runs(n_poses, SELECTION_POSES, SELECTION_RUNS, seed)
