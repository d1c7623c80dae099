"""The batch estimate as the nodes run it (ROS-free): the command line's code path.

Both the estimator's Estimate service and the sequencer's local mode call
run_calibration: report.calibration.calibrate (what `laser-calib estimate
--test` runs), the files written from its result when there is a folder for
them, and the diagnosis on request (`laser-calib diagnose --test`), both with
the session's held-out test poses when it measured any. The service fills its
response from the result object: success is false for an estimate that is no
calibration (Calibration.failure), as the command line exits 3 for it.
"""

from __future__ import annotations

import json
import math
import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from laser_calib.diagnosis.compensator import Compensator
from laser_calib.diagnosis.engine import DiagnoseOptions, TooFewPoses, diagnose, write_outputs as write_diagnosis
from laser_calib.estimation.estimate import METHODS, EstimateOptions
from laser_calib.io.errors import InputError
from laser_calib.io.samples import Samples, check_spot_units
from laser_calib.io.spot_columns import check_spot_columns
from laser_calib.measurement.noise_bounds import (JOINT_SIGMA_NOT_GIVEN, joint_sigma_or_unset_problem,
                                                  spot_sigma_or_zero_problem)
from laser_calib.model.robot import Robot
from laser_calib.report.calibration import Calibration, calibrate
from laser_calib.report.files import write_outputs
from laser_calib.session.folder import outermost_missing, refuse_finished


def estimate_options(method: str, spot_sigma: float, prior: bool, robust: bool,
                     joint_sigma: float = JOINT_SIGMA_NOT_GIVEN) -> EstimateOptions:
    """EstimateOptions from ROS-style values, as the command line makes them from its options:
    method '' = 'lm'; spot_sigma 0 = estimate it (no --spot-sigma); joint_sigma (rad)
    JOINT_SIGMA_NOT_GIVEN (-1) = no --joint-sigma (None: estimated from the residual), 0 = no
    joint-reading noise, > 0 = that sigma. A bad value: InputError."""
    method = method or "lm"
    if method not in METHODS:
        raise InputError("method", f"expected one of {', '.join(METHODS)}, got {method!r}")
    if problem := spot_sigma_or_zero_problem(spot_sigma):
        raise InputError("spot_sigma", problem)
    if problem := joint_sigma_or_unset_problem(joint_sigma):
        raise InputError("joint_sigma", problem)
    return EstimateOptions(method=method, spot_sigma=spot_sigma or None,
                           joint_sigma=None if joint_sigma == JOINT_SIGMA_NOT_GIVEN else joint_sigma,
                           prior=bool(prior), robust=bool(robust))


def online_options(spot_sigma: float, joint_sigma: float = JOINT_SIGMA_NOT_GIVEN) -> EstimateOptions:
    """The estimator node's online EKF options for its spot_sigma and joint_sigma parameters: a
    running filter has no residual to estimate them from, so spot_sigma 0 is the core's default
    and a joint sigma not given is 0 (laser_calib.estimation.online)."""
    return estimate_options("ekf", spot_sigma, False, False, joint_sigma)


@dataclass(frozen=True)
class Outcome:
    """What a ROS answer carries: the calibration and the diagnosis's JSON ('' when not run)."""

    calibration: Calibration
    diagnosis_json: str

    @property
    def diagnosis(self) -> dict:
        return json.loads(self.diagnosis_json) if self.diagnosis_json else {}

    @property
    def message(self) -> str:
        """The calibration's summary line, then the diagnosis's verdict and its final fit's
        warnings, or why the diagnosis was skipped."""
        diagnosis = self.diagnosis
        said = [self.calibration.summary()]
        if "skipped" in diagnosis:
            said.append(diagnosis["skipped"])
        elif diagnosis:
            said += [f"diagnosis: {diagnosis['verdict']}"] + [f"diagnosis's final fit: {w}" for w in diagnosis["warnings"]]
        return "; ".join(said)

    @property
    def warned(self) -> bool:
        return warned(self.calibration.estimate.warnings, self.diagnosis_json)


def warned(estimate_warnings, diagnosis_json: str) -> bool:
    """Whether an estimate (its warnings) or its diagnosis's final fit (diagnosis_json's, '' when
    not run) warned: the nodes then log a WARN. An Outcome's, or an Estimate response's."""
    return bool(estimate_warnings) or bool(diagnosis_json and json.loads(diagnosis_json).get("warnings"))


def run_calibration(robot: Robot, samples: Samples, options: EstimateOptions, out_dir: str | Path | None,
                    diagnose: bool = False, sources: dict | None = None, compensator: Compensator | None = None,
                    test: Samples | None = None) -> Outcome:
    """calibrate() (what `laser-calib estimate` runs: the robot file's effects, and the
    learned compensator when given), its files into out_dir when given; ValueError
    from the estimate (too few spots, ...) becomes an InputError, but numpy's LinAlgError (a fault of
    ours, raised as it is); the diagnosis's InputError, after an estimate
    that is no calibration, its 'skipped' reason. test: held-out samples (never fitted) for the test
    figures and the diagnosis's predictive test."""
    # Samples from a request or a live session are not read from a file: their units and columns are checked here.
    for name, checked in (("samples", samples), ("test", test)):
        if checked is not None:
            source = (sources or {}).get(name) or name
            check_spot_units(checked.spots, robot, source)
            check_spot_columns(robot, checked.q, checked.spots, source)
    made = None  # the outermost folder this call creates, removed again if the estimate writes nothing
    with writing(out_dir):  # a folder that cannot be made: refused before the estimate
        if out_dir:
            refuse_finished(out_dir, "output_dir")
            made = outermost_missing(Path(out_dir).absolute())
            Path(out_dir).mkdir(parents=True, exist_ok=True)
    try:
        calibration = calibrate(robot, samples, options, test, sources=sources, compensator=compensator)
    except BaseException as exc:  # refused, canceled (estimation.cancel), interrupted: no empty folder left
        if made is not None and not any(path.is_file() for path in made.rglob("*")):
            shutil.rmtree(made, ignore_errors=True)
        if not isinstance(exc, ValueError) or isinstance(exc, (InputError, np.linalg.LinAlgError)):
            raise  # LinAlgError: our numerics, not the input
        raise InputError("estimate", str(exc)) from None
    with writing(out_dir):
        if out_dir:
            write_outputs(calibration, out_dir)
        diagnosis = ""
        if diagnose:
            try:
                diagnosis = json.dumps(run_diagnosis(robot, samples, options, Path(out_dir) if out_dir else None,
                                                     test, sources))
            except InputError as exc:
                if calibration.failure is None:
                    raise
                # it starts from that failed fit: its refusal is said beside the estimate's failure, whose
                # files are written (a wrong robot file ended a session as bad input, its failure unsaid)
                diagnosis = json.dumps({"skipped": f"diagnosis skipped: {exc}"})
    return Outcome(calibration, diagnosis)


@contextmanager
def writing(out_dir: str | Path | None):
    """An OSError while out_dir is made or written: an InputError naming output_dir."""
    try:
        yield
    except OSError as exc:
        reason = f"{exc.strerror}: {exc.filename}" if exc.strerror and exc.filename else (exc.strerror or str(exc))
        raise InputError("output_dir", f"cannot write the report into {out_dir} ({reason})") from None


def run_diagnosis(robot: Robot, samples: Samples, options: EstimateOptions, out: Path | None,
                  test: Samples | None = None, sources: dict | None = None) -> dict:
    """laser_calib.diagnosis.engine.diagnose (what `laser-calib diagnose --test` runs) on the same
    samples and test samples (None: none; its predictive test is then not run).

    Its files (diagnosis.json, report.md with plots, robot_calibrated.yaml with
    the effects) go to out/diagnosis/, beside the geometric estimate's, when out
    is given, naming its inputs as ``sources`` does (the estimate's; without, the session's counts).
    The noise as the estimate's options give it: a sigma None is not given (estimated, as `diagnose`
    without --spot-sigma / --joint-sigma), a joint sigma 0 is none (--joint-sigma 0).
    Always LM: the diagnosis runs dozens of fits. Returns the JSON; too few
    poses for it is a data limit, not an error: {"skipped": "diagnosis skipped: ..."}.
    """
    try:
        diagnosis = diagnose(robot, samples, test, options=DiagnoseOptions(
            method="lm", spot_sigma=options.spot_sigma, joint_sigma=options.joint_sigma,
            robust=options.robust), sources=sources)
    except TooFewPoses as exc:
        return {"skipped": f"diagnosis skipped: {exc.n_poses} poses, at least {exc.needed} needed"}
    if out is not None:
        # what the estimate beside it names (its result.json's inputs), but the compensator, which the diagnosis
        # does not apply
        given = sources or {}
        written_from = {"robot": given.get("robot") or robot.name,
                        "samples": given.get("samples") or f"{len(samples)} session samples"}
        if test is not None:
            written_from["test"] = given.get("test") or f"{len(test)} session test samples"
        write_diagnosis(diagnosis, out / "diagnosis", written_from)
    return diagnosis.to_json()


def laser_statistics(stats: dict) -> dict[str, list[float]]:
    """Per-laser mean/std/max in metres and counts from report.statistics.laser_stats (mm)."""
    out = {"mean": [], "std": [], "max": [], "count": []}
    for j in range(2):
        entry = stats.get(f"laser{j + 1}", {})
        for key in ("mean", "std", "max"):
            value = entry.get(f"{key}_mm")
            out[key].append(math.nan if value is None else value * 1e-3)
        out["count"].append(int(entry.get("n", 0)))
    return out
