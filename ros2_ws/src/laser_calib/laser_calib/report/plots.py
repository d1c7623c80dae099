"""Plots and the markdown report of a geometric calibration (matplotlib, no display)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from laser_calib.model.robot import Screen

# Most poses a scatter plot draws (drawn_poses).
MAX_DRAWN = 3000
PANELS = (("link length a", "a"), ("link offset d", "d"), ("link twist alpha", "alpha"),
          ("joint angle theta", "theta"))


def pyplot():
    """matplotlib.pyplot without a display, imported when a plot is drawn (a second or more)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_figure(fig, path: Path, dpi: int = 90) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)


def display_units(kinds: np.ndarray) -> np.ndarray:
    """Factor from SI to report units per error of the given kinds (Robot.param_kinds()):
    mm for lengths, deg for angles."""
    return np.where(np.asarray(kinds) == "length", 1e3, np.degrees(1.0))


def _panels(names: tuple[str, ...]) -> list[tuple[str, Callable[[str], bool], str]]:
    """(title, member(name), unit) of each convergence panel: the D-H groups, or a URDF
    robot's joint placements (joint_chain.py: <joint>.offset, .x ... .rz); the SLM last."""
    if any("." in name for name in names):
        def suffix(name: str) -> str:
            return name.rpartition(".")[2] if "." in name else ""
        groups = [("joint offset", lambda n: suffix(n) == "offset", "deg (mm: prismatic)"),
                  ("placement x, y, z", lambda n: suffix(n) in ("x", "y", "z"), "mm"),
                  ("placement rx, ry, rz", lambda n: suffix(n) in ("rx", "ry", "rz"), "deg")]
    else:
        groups = [(title, lambda n, p=prefix: n.rstrip("0123456789") == p, "mm" if prefix in ("a", "d") else "deg")
                  for title, prefix in PANELS]
    return groups + [("SLM", lambda n: n.startswith("slm"), "mm / deg")]


def plot_convergence(history: np.ndarray, names: tuple[str, ...], kinds: np.ndarray, path: Path,
                     truth: np.ndarray | None = None) -> None:
    """Every error against the iteration, grouped like the paper's Fig. 4."""
    units = display_units(kinds)
    scaled = history * units
    panels = _panels(names)
    fig, axes = pyplot().subplots(1, len(panels), figsize=(4 * len(panels), 3.4))
    for ax, (title, member, unit) in zip(axes, panels):
        idx = [i for i, name in enumerate(names) if member(name)]
        for i in idx:
            line, = ax.plot(scaled[:, i], label=names[i])
            if truth is not None:
                ax.axhline(truth[i] * units[i], color=line.get_color(), ls=":", lw=0.8)
        ax.set_title(title)
        ax.set_xlabel("iteration")
        ax.set_ylabel(unit)
        if idx:
            ax.legend(fontsize=6, ncol=2)
        if len(scaled) > 50:
            ax.set_xscale("symlog")
    save_figure(fig, path)


def drawn_poses(n_poses: int, limit: int = MAX_DRAWN) -> np.ndarray:
    """Indices of the poses a scatter plot draws: all up to ``limit``, else
    ``limit`` evenly spread over the session (markers beyond a few thousand
    only hide each other and cost seconds). Statistics never use this."""
    if n_poses <= limit:
        return np.arange(n_poses)
    return np.unique(np.linspace(0, n_poses - 1, limit).round().astype(int))


def plot_screen(screen: Screen, measured: np.ndarray, before: np.ndarray, after: np.ndarray, path: Path) -> None:
    """Measured spots and the spots predicted before/after calibration on the screen;
    measured, before, after (P,2,2) screen (y, z) in m (at most MAX_DRAWN poses drawn)."""
    n_poses = len(measured)
    drawn = drawn_poses(n_poses)
    measured, before, after = measured[drawn], before[drawn], after[drawn]
    fig, ax = pyplot().subplots(figsize=(6, 6))
    for j, marker in enumerate(("o", "s")):
        ax.plot(measured[:, j, 0], measured[:, j, 1], marker, mfc="none", color="k", ms=6,
                label=f"laser {j + 1} measured")
        ax.plot(before[:, j, 0], before[:, j, 1], "x", color="tab:red", ms=4,
                label=f"laser {j + 1} nominal model")
        ax.plot(after[:, j, 0], after[:, j, 1], "+", color="tab:green", ms=6,
                label=f"laser {j + 1} calibrated model")
    if len(drawn) < n_poses:
        ax.set_title(f"{len(drawn)} of {n_poses} poses drawn, evenly spread", fontsize=8)
    ax.set_xlim(-screen.half_y, screen.half_y)
    ax.set_ylim(-screen.half_z, screen.half_z)
    ax.set_xlabel("screen y (m)")
    ax.set_ylabel("screen z (m)")
    ax.set_aspect("equal")
    ax.legend(fontsize=6)
    save_figure(fig, path)


def plot_histogram(groups: dict[str, np.ndarray], path: Path) -> None:
    """Histogram of spot distances (mm) per group, log-spaced bins."""
    fig, ax = pyplot().subplots(figsize=(6, 3.5))
    values = [v[np.isfinite(v)] * 1e3 for v in groups.values()]
    positive = np.concatenate([v[v > 0] for v in values] + [np.empty(0)])
    # From the smallest distance, however small: a model checked on noise-free data leaves
    # distances of nanometres (a floor above them made the bins run backwards); none at all, one decade.
    low, high = (positive.min(), positive.max() * 1.01) if positive.size else (1e-3, 1e-2)
    bins = np.logspace(np.log10(low), np.log10(high), 40)
    for label, v in zip(groups, values):
        ax.hist(v, bins=bins, alpha=0.5, label=label)
    ax.set_xscale("log")
    ax.set_xlabel("spot distance (mm)")
    ax.set_ylabel("spots")
    ax.legend(fontsize=7)
    save_figure(fig, path)


def stats_table(spot_error: dict) -> list[str]:
    lines = ["| set | model | laser | n | mean (mm) | RMS (mm) | P95 (mm) | max (mm) | std (mm) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for set_name, by_model in spot_error.items():
        for model_name, by_laser in by_model.items():
            for laser in ("laser1", "laser2"):
                s = by_laser[laser]
                if s["n"]:
                    figures = " | ".join(f"{s[key + '_mm']:.3f}" for key in ("mean", "rms", "p95", "max", "std"))
                    lines.append(f"| {set_name} | {model_name} | {laser[-1]} | {s['n']} | {figures} |")
    return lines
