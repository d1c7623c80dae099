"""Shared helpers of the benchmarks: import path, results folder, markdown tables."""

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
CORE = ROOT / "ros2_ws" / "src" / "laser_calib"
if str(CORE) not in sys.path:
    sys.path.insert(0, str(CORE))

import laser_calib  # noqa: E402,F401  (first: it pins BLAS to one thread before numpy loads)


def write_results(name: str, data: dict, table: str) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(data, indent=2))
    (RESULTS / f"{name}.md").write_text(table)
    print(table)
    print(f"wrote {RESULTS / name}.json and .md")


def warned_worse_on_test(diagnosis_json: dict) -> bool:
    """Whether a diagnosis warned that its final model misses the test poses by more than the
    geometric one (diagnosis.verdict.worse_on_test)."""
    from laser_calib.diagnosis.verdict import WORSE_ON_TEST
    return any(w.startswith(WORSE_ON_TEST) for w in diagnosis_json["warnings"])


def worse_on_test_warned(rows: list[dict]) -> tuple[int, int]:
    """Of the rows whose final model's test RMS is above the geometric fit's: how many warned so, and how many."""
    worse = [r for r in rows if r["final_test_rms_mm"] > r["geometric_test_rms_mm"]]
    return sum(r["warned_worse_on_test"] for r in worse), len(worse)


def verdict_cell(row: dict) -> str:
    """A table's verdict, marked when the diagnosis warned that its test figure got worse."""
    return row["verdict"] + (" (warned: worse on test)" if row["warned_worse_on_test"] else "")
