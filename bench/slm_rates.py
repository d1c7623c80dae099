"""slm-calibrate's outcomes over seeded files (laser_calib/slm.py): how often clean files are refused or
lose a spot, and what becomes of files with wrong spots.

The files are the paper's 4-DOF arm's two lasers on a fixture (as test/core/test_slm.py makes them):
offsets uniform within +-50 mm, Gaussian spot noise of 0.1 mm per coordinate, distances 0.5 .. 1.25 m
(three, four or eight). Wrong spots are laser 1's u moved by +-M mm: two of four at the 2nd and 3rd
distance (+M, -M: the reported file), two of four in random places and signs, or one of four or eight
in a random place and sign. Without --spot-sigma unless the case says it. Each file ends one way:
refused (exit 2; "laser vs laser" when by slm.py's comparison of the lasers), written with exactly its
wrong spots rejected (and perhaps a good one), or written with a wrong spot kept.

Usage: python bench/slm_rates.py [--clean 5000] [--bad 1000]
"""

from __future__ import annotations

import argparse
import collections

from _common import write_results  # first: sets up the import path and BLAS threads

import numpy as np  # noqa: E402

from laser_calib.io.errors import InputError  # noqa: E402
from laser_calib.sim.simulation import bundled_robot  # noqa: E402
from laser_calib.sim.slm_fixture import fixture_spots  # noqa: E402
from laser_calib.slm import Measurements, Spots, calibrate  # noqa: E402

ROBOT = bundled_robot("paper-4dof")
SIGMA = 1e-4
DISTANCES = {3: (0.5, 0.75, 1.0), 4: (0.5, 0.75, 1.0, 1.25), 8: tuple(np.linspace(0.5, 1.25, 8))}
OUTCOMES = ("refused (laser vs laser)", "refused (other rule)", "wrong spots rejected", "a wrong spot kept")


def spots(seed: int, distances: tuple[float, ...]) -> list[list]:
    """[laser, distance, u, v] rows of the robot's two beams, with Gaussian noise SIGMA."""
    return fixture_spots(ROBOT, seed, distances, SIGMA)


def measurements(rows: list[list]) -> Measurements:
    lines = {j: [(k + 2, d, u, v) for k, (laser, d, u, v) in enumerate(rows) if laser == j] for j in (1, 2)}
    return Measurements("slm.csv", {j: Spots(np.array([e[0] for e in es]), np.array([e[1] for e in es]),
                                             np.array([e[2:] for e in es])) for j, es in lines.items()})


def spoiled(seed: int, k: int, n_bad: int, size: float, pattern: str) -> tuple[list[list], set[int]]:
    """A file of k distances with n_bad of laser 1's u moved by size (m); the rows moved."""
    rows, rng = spots(seed, DISTANCES[k]), np.random.default_rng(10_000 + seed)
    if pattern == "reported":
        bad, signs = [1, 2], [1, -1]
    else:
        bad, signs = sorted(rng.choice(k, n_bad, replace=False).tolist()), rng.choice([-1, 1], n_bad)
    for i, sign in zip(bad, signs):
        rows[i][2] += sign * size
    return rows, set(bad)


def outcome(rows: list[list], bad: set[int], sigma: float | None) -> str:
    try:
        result = calibrate(ROBOT, measurements(rows), sigma)
    except InputError as exc:
        return OUTCOMES[0] if "one camera sees both" in exc.problem else OUTCOMES[1]
    rejected = {r.line - 2 for r in result.rejected}
    if not bad:
        return "written, a spot rejected" if rejected else "written clean"
    return OUTCOMES[2] if bad <= rejected else OUTCOMES[3]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--clean", type=int, default=5000, help="clean files per case (seeds 0 ..)")
    parser.add_argument("--bad", type=int, default=1000, help="files with wrong spots per case")
    args = parser.parse_args()
    cases = [(f"clean, {k} distances" + (", --spot-sigma" if sigma else ""), args.clean,
              lambda seed, k=k: (spots(seed, DISTANCES[k]), set()), sigma)
             for k in (3, 4, 8) for sigma in (None, SIGMA)]
    for n_bad, k, size, pattern in [(2, 4, 0.03, "reported"), (2, 4, 0.03, "random"), (2, 4, 0.003, "reported"),
                                    (2, 4, 0.003, "random"), (2, 4, 0.001, "reported"), (1, 4, 0.03, "random"),
                                    (1, 8, 0.03, "random")]:
        for sigma in (None, SIGMA) if size == 0.03 else (None,):
            cases.append((f"{n_bad} of {k} off {size * 1e3:g} mm, {pattern}" + (", --spot-sigma" if sigma else ""),
                          args.bad, lambda seed, a=(k, n_bad, size, pattern): spoiled(seed, *a), sigma))
    rows, lines = [], ["| case | files | outcomes |", "|---|---|---|"]
    for name, n, make, sigma in cases:
        counts = collections.Counter(outcome(*make(seed), sigma) for seed in range(n))
        rows.append({"case": name, "files": n, "outcomes": dict(counts)})
        lines.append(f"| {name} | {n} | " + "; ".join(f"{key} {value} ({100 * value / n:.1f} %)"
                                                       for key, value in sorted(counts.items())) + " |")
    write_results("slm_rates", {"sigma_m": SIGMA, "cases": rows}, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
