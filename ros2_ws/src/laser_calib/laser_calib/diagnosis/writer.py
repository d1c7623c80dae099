"""The files of a diagnosis."""

from __future__ import annotations

import json
from pathlib import Path

from laser_calib import __version__
from laser_calib.diagnosis.report import write_report
from laser_calib.diagnosis.result import Diagnosis
from laser_calib.estimation.failures import undetermined_note
from laser_calib.model.robot_file import save_robot


def write_outputs(diagnosis: Diagnosis, out_dir: str | Path, sources: dict[str, str | None] | None = None) -> dict:
    """diagnosis.json, robot_calibrated.yaml (geometric corrections and the
    ``effects:`` key, docs/effects.md), compensator.json when the learned
    compensator was kept (diagnosis.compensator.load_compensator) and
    report.md with its plots into out_dir; returns the JSON dictionary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = diagnosis.to_json()
    result["inputs"] = sources or {}
    (out / "diagnosis.json").write_text(json.dumps(result, indent=2))
    save_robot(diagnosis.calibrated_robot(), out / "robot_calibrated.yaml", header=robot_header(diagnosis, result))
    if diagnosis.compensator is not None:
        diagnosis.compensator.save(out / "compensator.json")
    write_report(diagnosis, result, out)
    return result


def robot_header(diagnosis: Diagnosis, result: dict) -> str:
    """The header of robot_calibrated.yaml: what the model is, the verdict, and what its numbers
    do not say (parameters held or not separable, an effect that is one of a group the data
    cannot tell apart) from the diagnosis and its JSON (result)."""
    unseparated = [f"{e['name']} ({e['where']}) {p['name']}: {p['note']}" for e in result["effects"]
                   for p in e["parameters"] if p["value"] is None]
    merged = "; ".join(f"{k}: {v}" for k, v in diagnosis.merged.items())
    return (f"Calibrated by laser_calib {__version__} diagnose from {len(diagnosis.samples)} poses: "
            f"{diagnosis.final.label}. Verdict: {diagnosis.verdict}."
            + (f"\nNO CALIBRATION: {diagnosis.failure}" if diagnosis.failure else "")
            + (f"\nNot identifiable, held at nominal: {merged}" if merged else "")
            + undetermined_note(diagnosis.final.estimate.undetermined)
            + "".join(f"\nEffect parameter not separable from the geometric errors (the model uses the "
                      f"value, which has no meaning alone): {u}" for u in unseparated)
            + "".join(f"\nNot one cause: {e['group']}; this file uses {e['name']} ({e['where']}), the lowest "
                      "BIC, which predicts as well held out: it is not named the cause"
                      for e in result["effects"] if not e["determined"]))
