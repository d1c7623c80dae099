"""The batch estimate as the nodes run it (ROS-free): the command line's code path.

Both the estimator's Estimate service and the sequencer's local mode call
run_and_collect, which calls laser_calib.report.files.run_estimate (what
`laser-calib estimate` calls) and gathers what a ROS answer carries: the
result dictionary, the text of the files it wrote, the calibrated model.
"""

from __future__ import annotations

import json
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.estimation.estimate import METHODS, EstimateOptions
from laser_calib.model.robot import Robot
from laser_calib.report.files import run_estimate
from laser_calib.model.robot_file import load_robot
from laser_calib.io.samples import Samples

FILES = ("report.md", "result.json", "robot_calibrated.yaml")


def estimate_options(method: str, spot_sigma: float, prior: bool, robust: bool) -> EstimateOptions:
    """EstimateOptions from ROS-style values (method '' = 'lm', spot_sigma 0 = estimate it)."""
    method = method or "lm"
    if method not in METHODS:
        raise InputError("method", f"expected one of {', '.join(METHODS)}, got {method!r}")
    if not (math.isfinite(spot_sigma) and spot_sigma >= 0):
        raise InputError("spot_sigma", f"expected a non-negative number of metres, got {spot_sigma}")
    return EstimateOptions(method=method, spot_sigma=spot_sigma or None, prior=bool(prior), robust=bool(robust))


def online_options(spot_sigma: float) -> EstimateOptions:
    """The estimator node's online EKF options for its spot_sigma parameter (0: the core's default)."""
    return estimate_options("ekf", spot_sigma, False, False)


@dataclass(frozen=True)
class Outcome:
    result: dict
    files: dict[str, str]
    calibrated: Robot
    diagnosis_json: str
    message: str


def run_and_collect(robot: Robot, samples: Samples, options: EstimateOptions, out_dir: str | Path | None,
                    diagnose: bool = False, sources: dict | None = None) -> Outcome:
    """run_estimate into out_dir (a temporary directory when None); ValueError from
    the estimate (too few spots, ...) becomes an InputError."""
    with tempfile.TemporaryDirectory(prefix="laser_calib_estimate_") as tmp:
        target = Path(out_dir) if out_dir else Path(tmp)
        try:
            result = run_estimate(robot, samples, options, target, sources=sources)
        except ValueError as exc:
            if isinstance(exc, InputError):
                raise
            raise InputError("estimate", str(exc)) from None
        files = {name: (target / name).read_text() for name in FILES}
        calibrated = load_robot(target / "robot_calibrated.yaml")
        diagnosis = ""
        if diagnose:
            diagnosis = json.dumps(run_diagnosis(robot, samples, options, result, target))
    return Outcome(result, files, calibrated, diagnosis, summary(result, len(samples)))


def run_diagnosis(robot: Robot, samples: Samples, options: EstimateOptions, result: dict, out: Path) -> dict:
    """laser_calib.diagnosis.engine.diagnose (what `laser-calib diagnose` runs) on the same samples.

    Its files (diagnosis.json, report.md with plots, robot_calibrated.yaml with
    the effects) go to out/diagnosis/, beside the geometric estimate's. Always
    LM: the diagnosis runs dozens of fits. Returns the JSON.
    """
    from laser_calib.diagnosis.engine import DiagnoseOptions, diagnose, write_outputs
    diagnosis = diagnose(robot, samples, options=DiagnoseOptions(
        method="lm", spot_sigma=options.spot_sigma, joint_sigma=options.joint_sigma or None))
    write_outputs(diagnosis, out / "diagnosis", {"robot": robot.name, "samples": f"{len(samples)} session samples"})
    return diagnosis.to_json()


def summary(result: dict, n_samples: int) -> str:
    """One line: the spot error before and after, as the command line prints it."""
    by_model = result["spot_error"]["calibration"]
    before, after = by_model["before"]["all"], by_model["after"]["all"]

    def mm(value):
        return "n/a" if value is None else f"{value:.3f}"

    return (f"{result['method']} on {n_samples} poses: mean spot error {mm(before['mean_mm'])} mm -> "
            f"{mm(after['mean_mm'])} mm (max {mm(before['max_mm'])} -> {mm(after['max_mm'])}; {after['n']} spots)"
            + ("; " + "; ".join(result["warnings"]) if result.get("warnings") else ""))


def laser_statistics(stats: dict) -> dict[str, list[float]]:
    """Per-laser mean/std/max in metres and counts from pipeline's laser_stats (mm)."""
    out = {"mean": [], "std": [], "max": [], "count": []}
    for j in range(2):
        entry = stats.get(f"laser{j + 1}", {})
        for key in ("mean", "std", "max"):
            value = entry.get(f"{key}_mm")
            out[key].append(math.nan if value is None else value * 1e-3)
        out["count"].append(int(entry.get("n", 0)))
    return out


def parameter_arrays(result: dict) -> tuple[list[str], np.ndarray, np.ndarray, list[bool]]:
    names = [e["name"] for e in result["errors"]]
    errors = np.array([math.nan if e["value"] is None else e["value"] for e in result["errors"]])
    std = np.array([math.nan if e["std"] is None else e["std"] for e in result["errors"]])
    identifiable = [bool(e["identifiable"]) for e in result["errors"]]
    return names, errors, std, identifiable
