"""A third probe of the diagnosis: seven kinds written by a helper who had read only how the
effects bench builds its data, not the diagnosis (2026-12-03), run as written.

    .venv/bin/python bench/effects_probe3.py [--kinds ...] [--arms ...] [--seeds 11 12 13]
        [--given both spot] [--visible 400] [--name effects_probe3]

Same diagnosis call as the effects bench (effects_bench.case_diagnosis: no nested selection; spot and
joint sigma given per --given). "true" is the test RMS of the geometric fit with the true effect
known (effects_bench's true_offsets_rms for parameter-level kinds; for the spot-level ones the
exact displacement is removed from the spots and the geometric model fitted: the same
noise-only figure). A violation: "explained" with the final test RMS above 1.3x the true one.
--csv DIR writes each case's calibration and test CSVs instead (for `laser-calib diagnose`).

Kinds:
  n_thermal_lag  a length (a_i/d_i/slm_x) grows with the temperature passed through a first-order thermal lag
                 (tau = 0.3 of the session): neither linear in the temperature column nor in time
  n_runout2      two-lobed bearing runout of the last joint: slm_ry ~ cos(2 qN + phi), slm_rz ~ sin(2 qN + phi)
  n_sag          gravity sag of the longest link: the chain beyond it is displaced along the gravity component
                 perpendicular to the link and rotated by the tip slope (cantilever, point load: slope 1.5 d / L)
                 -- a bending applied to the true spots (spot level), not a joint compliance
  n_cross_dir    dq_i ~ sign of the last move of ANOTHER joint j (cable/harness drag coupled to j's motion)
  n_cyclic43     dq_i ~ sin(4.3 q_i + phi) (motor-side cyclic error behind a non-integer reduction)
  n_dahl         Dahl hysteresis loop on joint i: z_k = s - (s - z_{k-1}) exp(-|dq| / w), s = sign of the move,
                 w = 15 % of the joint range; dq_i ~ -z (a loop that closes gradually, not a dead band)
  n_screen_lean  the screen leans progressively in time: plane x = th(t) (cos b y + sin b z), th ~ t/T - 1/2
                 (spot level; the screen shape effect is static, drift only moves lengths)
"""

from __future__ import annotations

import argparse
import time
import traceback
import warnings
from dataclasses import dataclass, replace

from _common import write_results

import numpy as np

import effects_bench as B
import laser_calib.sim.effect_truth as ET
from laser_calib.effects.base import move_directions
from laser_calib.effects.effect_model import EffectModel
from laser_calib.estimation.estimate import EstimateOptions
from laser_calib.io.samples import Samples
from laser_calib.measurement.base import NoiseModel, whiten
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.kinematics import forward, intersect, predict
from laser_calib.model.robot import Robot

NOISE, N_CAL, PERIOD = B.NOISE, B.N_CAL, B.PERIOD
DURATION = PERIOD * N_CAL
_on, _span, _two, ForeignError = B._on, B._span, B._two, ET.ForeignError


# ---------------------------------------------------------------- parameter-level kinds
def _lagged_temperature(stamps: np.ndarray, tau: float) -> np.ndarray:
    """The effect_truth.warmup curve (the temperature without its sensor noise) through a first-order lag,
    from t = 0."""
    grid = np.linspace(0, DURATION, 4001)
    t = ET.warmup(grid, DURATION)
    lag = np.empty_like(t)
    lag[0] = t[0]
    dt = grid[1] - grid[0]
    for k in range(1, len(t)):
        lag[k] = lag[k - 1] + (t[k] - lag[k - 1]) * (1 - np.exp(-dt / tau))
    return np.interp(stamps, grid, lag) - lag.mean()


def n_thermal_lag(robot: Robot, rng) -> ForeignError:
    lengths = [n for n in robot.param_names if n[0] in "ad" and n != "alpha" and not n.startswith("alpha")] + ["slm_x"]
    name = str(rng.choice(lengths))
    col = robot.param_names.index(name)
    return ForeignError(f"{name} ~ lag(temperature, tau 240 s)",
                        lambda r, s: _on(r, col, _lagged_temperature(s.stamp, 0.3 * DURATION)))


def n_runout2(robot: Robot, rng) -> ForeignError:
    j, phase = robot.n_joints - 1, float(rng.uniform(0, 2 * np.pi))
    ry, rz = robot.param_names.index("slm_ry"), robot.param_names.index("slm_rz")

    def offsets(r, s):
        out = _on(r, ry, np.cos(2 * s.q[:, j] + phase))
        out[:, rz] = np.sin(2 * s.q[:, j] + phase)
        return out
    return ForeignError(f"slm_ry,slm_rz ~ cos/sin(2 q{j + 1} + {phase:.2f}) (2-lobe runout)", offsets)


def n_cross_dir(robot: Robot, rng) -> ForeignError:
    i, j = _two(rng, robot.n_joints)
    return ForeignError(f"dq{i + 1} ~ sign(last move of q{j + 1})",
                        lambda r, s: _on(r, 4 * i + 3, move_directions(s.q)[:, j]))


def n_cyclic43(robot: Robot, rng) -> ForeignError:
    i, phase = int(rng.integers(robot.n_joints)), float(rng.uniform(0, 2 * np.pi))
    return ForeignError(f"dq{i + 1} ~ sin(4.3 q{i + 1} + {phase:.2f})",
                        lambda r, s: _on(r, 4 * i + 3, np.sin(4.3 * s.q[:, i] + phase)))


def _dahl(q: np.ndarray, width: float) -> np.ndarray:
    prev, z, out = 0.0, 0.0, np.zeros(len(q))
    for k, v in enumerate(q):
        step = v - prev
        if abs(step) > 1e-9:
            s = float(np.sign(step))
            z = s - (s - z) * np.exp(-abs(step) / width)
        out[k], prev = z, v
    return out


def n_dahl(robot: Robot, rng) -> ForeignError:
    i = int(rng.integers(robot.n_joints))
    width = 0.15 * (robot.q_max[i] - robot.q_min[i])
    return ForeignError(f"dq{i + 1} ~ -Dahl loop (w {width:.2f} rad)",
                        lambda r, s: _on(r, 4 * i + 3, -_dahl(s.q[:, i], width)))


# ---------------------------------------------------------------- spot-level kinds
@dataclass(frozen=True)
class SpotForeign:
    """A spot-level truth outside the library: displacement(robot, samples, spots) -> (P,L,2) for unit size."""
    name: str
    displacement: object
    factor: float = 1.0

    def scaled(self, f):
        return SpotForeign(self.name, self.displacement, self.factor * f)

    def apply(self, robot, context, spots):
        return spots + self.factor * self.displacement(robot, context, spots)


def _reintersect(origin, beams, n_vec_fn):
    """Spots (P,L,2) where beams from origin (P,3) meet the plane x = n . (y, z) (small tilt;
    kinematics.intersect for x = 0)."""
    p = origin[:, None, :]
    z = beams
    k = -p[..., 0] / z[..., 0]
    s = p + k[..., None] * z
    for _ in range(4):  # fixed point on x = g(y, z)
        g = n_vec_fn(s[..., 1:])
        k = (g - p[..., 0]) / z[..., 0]
        s = p + k[..., None] * z
    return s[..., 1:]


def n_screen_lean(robot: Robot, rng) -> SpotForeign:
    beta = float(rng.uniform(0, 2 * np.pi))

    def disp(r, c, spots):
        st = forward(r, c.q)
        theta = (c.stamp / DURATION - 0.5)[:, None]
        flat = intersect(r, st).yz
        lean = _reintersect(st.origin, st.beams, lambda yz: theta * (np.cos(beta) * yz[..., 0] + np.sin(beta) * yz[..., 1]))
        return lean - flat
    return SpotForeign(f"screen leans in time along {np.degrees(beta):.0f} deg", disp)


def n_sag(robot: Robot, rng) -> SpotForeign:
    st0 = forward(robot, np.zeros((1, robot.n_joints)))
    pts = np.concatenate([st0.joint_origin[0], st0.origin[:1]], axis=0)
    lengths = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    i = int(np.argmax(lengths))  # link between joint i+1 and the next joint (or the SLM)
    g = np.asarray(robot.gravity, float)

    def disp(r, c, spots):
        st = forward(r, c.q)
        pts = np.concatenate([st.joint_origin, st.origin[:, None]], axis=1)
        a, b = pts[:, i], pts[:, i + 1]
        link = b - a
        length = np.linalg.norm(link, axis=1, keepdims=True)
        u = link / length
        gperp = g - (u @ g)[:, None] * u
        delta = gperp * (length / length.mean())  # tip deflection direction/size ~ |g_perp| (per unit)
        omega = 1.5 / length * np.cross(u, gperp) * (length / length.mean())
        p2 = st.origin + delta + np.cross(omega, st.origin - b)
        z2 = st.beams + np.cross(omega[:, None, :], st.beams)
        z2 = z2 / np.linalg.norm(z2, axis=-1, keepdims=True)
        return intersect(r, replace(st, origin=p2, beams=z2)).yz - intersect(r, st).yz
    return SpotForeign(f"sag of link {i + 1} (after joint {i + 1}, L {lengths[i]:.2f} m)", disp)


KINDS = {"n_thermal_lag": n_thermal_lag, "n_runout2": n_runout2, "n_sag": n_sag, "n_cross_dir": n_cross_dir,
         "n_cyclic43": n_cyclic43, "n_dahl": n_dahl, "n_screen_lean": n_screen_lean}

# effect_session builds hooks with effect_truth.hooks: wrap it to apply the spot-level truths too.
_hooks = ET.hooks


def _patched_hooks(truth):
    mine = [t for t in truth if isinstance(t, SpotForeign)]
    offsets, transform = _hooks([t for t in truth if not isinstance(t, SpotForeign)])
    if not mine:
        return offsets, transform

    def spot_transform(robot, context, spots):
        out = spots if transform is None else transform(robot, context, spots)
        for t in mine:
            out = t.apply(robot, context, out)
        # a camera sees no spot the effect moved off the screen
        off = (np.abs(out[..., 0]) > robot.screen.half_y) | (np.abs(out[..., 1]) > robot.screen.half_z)
        return np.where(off[..., None], np.nan, out)
    return offsets, spot_transform


ET.hooks = _patched_hooks

# Per-kind factor on --visible, so the geometric fit's test RMS is ~1.3x-4x the true model's (the screen
# lean's displacement is heavy-tailed at grazing beams: at the common size it left 6x).
SIZE = {"n_screen_lean": 0.15, "n_sag": 2.0}


def spot_visibility(robot, errors, context, truth: SpotForeign, noise) -> float:
    """effect_truth.visibility for a spot displacement."""
    spots = predict(robot.with_errors(errors), context.q).spots
    seen = Samples(context.pose, context.stamp, context.q, spots, context.extra)
    model = EffectModel(SpotModel(robot, seen), [])
    res = model.residuals(errors, True)
    whitener = NoiseModel(noise.spot_sigma, noise.joint_sigma).whitener(res)
    _, jac = whiten(res, whitener)
    d = truth.factor * truth.displacement(robot.with_errors(errors), seen, spots)
    d = np.where(np.isfinite(d) & res.valid[..., None], d, 0.0)
    motion = np.einsum("pij,pj->pi", whitener, d.reshape(len(d), -1)).ravel()
    u, s, _ = np.linalg.svd(jac, full_matrices=False)
    u = u[:, s > 1e-9 * s[0]]
    return float(np.sum((motion - u @ (u.T @ motion)) ** 2))


def spot_true_rms(session, truth: SpotForeign, options) -> float:
    def corrected(s):
        d = truth.factor * truth.displacement(session.true, s, s.spots)
        return Samples(s.pose, s.stamp, s.q, s.spots - d, s.extra)

    class S:
        cal, test = corrected(session.cal), corrected(session.test)
    return ET.fitted_test_rms(S, lambda samples: EffectModel(SpotModel(session.nominal, samples), []), options)


def make_session(arm, kind, seed, visible):
    holder = []
    visible = visible * SIZE.get(kind, 1.0)

    def make_truth(robot, errors, context, rng):
        t = KINDS[kind](robot, rng)
        if isinstance(t, SpotForeign):
            t = t.scaled(float(np.sqrt(visible / spot_visibility(robot, errors, context, t, NOISE))))
        else:
            t = ET.sized(robot, errors, context, t, NOISE, visible)
        holder.append(t)
        return [t]
    session = ET.effect_session(arm, seed, make_truth, N_CAL, B.N_TEST, NOISE, PERIOD)
    return session, holder[0]


def run_case(arm, kind, seed, given, visible):
    options = EstimateOptions(spot_sigma=NOISE.spot_sigma, joint_sigma=NOISE.joint_sigma)
    session, truth = make_session(arm, kind, seed, visible)
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        d = B.case_diagnosis(session, given)
    elapsed = time.perf_counter() - start
    res = d.to_json()
    st = res["stages"]
    true_rms = (spot_true_rms(session, truth, options) if isinstance(truth, SpotForeign)
                else ET.true_offsets_rms(session, truth, options))
    geo, fin = st[0]["test"]["rms_mm"], st[-1]["test"]["rms_mm"]
    comp = res["compensator"]["test"]["rms_mm"] if res["compensator"] else fin
    chosen = [f"{e['name']}({e['where']}" + (f" w {e['covariate']})" if "covariate" in e else ")") for e in res["effects"]]
    return {"kind": kind, "arm": arm, "seed": seed, "given": given, "visible": visible, "truth": truth.name,
            "chosen": chosen, "verdict": res["verdict"], "evidence": res["evidence"], "geo": geo, "final": fin,
            "comp": comp, "true": true_rms, "det_gain": res["detector"]["heldout_gain"] if res["detector"] else None,
            "det_p": res["detector"]["p"] if res["detector"] else None, "notes": res["notes"],
            "py_warnings": [str(w.message) for w in caught], "failure": res["failure"], "time": elapsed,
            "test_n": st[-1]["test"]["n"], "final_p95": st[-1]["test"]["p95_mm"], "final_max": st[-1]["test"]["max_mm"],
            "violation": res["verdict"] == "explained" and fin > 1.3 * true_rms}


def table(rows: list[dict], summary: dict) -> str:
    lines = ["# Probe 3: seven kinds written outside the diagnosis", "",
             "| noise given | arm | kind | seed | chosen | verdict | geometric / true | final / true | "
             "compensated / true | detector gain, p | s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "verdict" not in r:
            lines.append(f"| {r['given']} | {r['arm']} | {r['kind']} | {r['seed']} | traceback | | | | | | |")
            continue
        gain = "-" if r["det_gain"] is None else f"{r['det_gain']:.3f}, {r['det_p']:.2g}"
        lines.append(f"| {r['given']} | {r['arm']} | {r['truth']} | {r['seed']} | {'; '.join(r['chosen']) or 'nothing'} "
                     f"| {r['verdict']}{' (VIOLATION)' if r['violation'] else ''} | {r['geo'] / r['true']:.2f} | "
                     f"{r['final'] / r['true']:.2f} | {r['comp'] / r['true']:.2f} | {gain} | {r['time']:.1f} |")
    lines += [""] + [f"- {key}: {value[0]} of {value[1]}" for key, value in summary.items()]
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--kinds", nargs="+", default=list(KINDS))
    ap.add_argument("--arms", nargs="+", default=["paper-7dof", "paper-4dof"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[11, 12, 13])
    ap.add_argument("--given", nargs="+", default=["both", "spot"])
    ap.add_argument("--visible", type=float, default=400.0)
    ap.add_argument("--name", default="effects_probe3")
    ap.add_argument("--csv", help="write cal/test CSVs of each case into this folder (no diagnosis)")
    a = ap.parse_args()
    if a.csv:
        from pathlib import Path
        from laser_calib.io.samples import save_samples
        for arm in a.arms:
            for kind in a.kinds:
                for seed in a.seeds:
                    session, truth = make_session(arm, kind, seed, a.visible)
                    base = Path(a.csv) / f"{arm}_{kind}_{seed}"
                    save_samples(session.cal, f"{base}_cal.csv")
                    save_samples(session.test, f"{base}_test.csv")
                    print(base, truth.name)
        return
    start = time.perf_counter()
    rows = []
    for given in a.given:
        for arm in a.arms:
            for kind in a.kinds:
                for seed in a.seeds:
                    try:
                        r = run_case(arm, kind, seed, given, a.visible)
                    except Exception:
                        r = {"kind": kind, "arm": arm, "seed": seed, "given": given, "traceback": traceback.format_exc()}
                        print(r["traceback"], flush=True)
                    rows.append(r)
                    if "verdict" in r:
                        print(f"{kind:13s} {arm:10s} {seed} {given:4s} | {'; '.join(r['chosen']) or '-':40s} | "
                              f"{r['verdict']:17s} | geo {r['geo'] / r['true']:.2f} fin {r['final'] / r['true']:.2f} "
                              f"| {r['time']:.1f}s" + ("  VIOLATION" if r["violation"] else ""), flush=True)
    ok = [r for r in rows if "verdict" in r]
    summary = {"not_explained": [sum(r["verdict"] != "explained" for r in ok), len(ok)],
               "honest": [sum(not r["violation"] for r in ok), len(ok)],
               "compensated_within_25pct": [sum(r["comp"] <= 1.25 * r["true"] for r in ok), len(ok)],
               "no_traceback": [len(ok), len(rows)]}
    write_results(a.name, {"visible": a.visible, "summary": summary, "wall_time_s": time.perf_counter() - start,
                           "cases": rows}, table(rows, summary))


if __name__ == "__main__":
    main()
