"""The documentation says what the code and the bench results say: the README's synopses
name every flag of the commands they give in full, its figures are bench/results/'s."""

import json
import re
from pathlib import Path

import pytest

from laser_calib.cli.main import build_parser

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()


def _synopses() -> dict[str, str]:
    """The README's command-line block: each command's synopsis, continuation lines joined."""
    block = README[README.index("    laser-calib simulate"):README.index("`estimate --bag` and")]
    found, command = {}, None
    for line in block.splitlines():
        start = re.match(r"\s+laser-calib ([\w-]+)", line)
        command = start[1] if start else command
        if command:
            found[command] = found.get(command, "") + " " + line.split("#")[0]
    return found


# Commands whose synopsis is the whole command line (the others name the usual flags; --help has all).
COMPLETE = ("estimate", "identify", "slm-calibrate", "replay", "screen-calibrate", "import-positioner")


@pytest.mark.parametrize("command", COMPLETE)
def test_the_readme_synopsis_names_every_flag(command):
    """identify's left out --spot-sigma and --joint-sigma, replay's --exclude, --wait-timeout and --quiet."""
    commands = next(a for a in build_parser()._actions if a.dest == "command").choices
    synopsis = _synopses()[command]
    flags = [flag for action in commands[command]._actions for flag in action.option_strings
             if flag.startswith("--") and flag != "--help"]
    # --robust / --no-robust (a default on): the synopsis gives the one that changes something
    missing = [flag for flag in flags if flag not in synopsis and f"--no-{flag[2:]}" not in synopsis]
    assert not missing, f"{command}: {missing}"


def _row(text: str, start: str) -> list[str]:
    line = next(line for line in text.splitlines() if line.startswith(start))
    return [cell.strip() for cell in line.strip("|").split("|")]


def test_the_measured_figures_are_the_bench_results():
    """The README's UR10e nominal figures said 3.88 / 4.12 / 6.72 mm (the bench: 3.890 / 4.132 /
    6.714), docs/real-data.md's positioner nominal held-out 0.420 (the bench: 0.421)."""
    bench = (ROOT / "bench" / "results" / "ur10e.md").read_text()
    figures = {name: [float(v) for v in _row(bench, f"| {label}")[1:4]]
               for name, label in (("nominal", "nominal URDF"), ("calibrated", "calibrated"))}
    said = _row(README, "| Real UR10e from its own URDF")[1]
    for name, values in figures.items():
        assert f"{' / '.join(f'{v:.2f}' for v in values)} mm {name}" in said, (said, figures)
    positioner = json.loads((ROOT / "bench" / "results" / "positioner.json").read_text())
    row = _row((ROOT / "docs" / "real-data.md").read_text(), "| ours: nominal D-H (frames fitted)")
    assert row[1:] == [f"{positioner['nominal_mean_mm']:.3f}", f"{positioner['heldout_nominal_mean_mm']:.3f}"]
