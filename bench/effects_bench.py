"""Effect diagnosis on both paper arms (issue 4), or on arms of robot files (--robots).

For every library effect on each arm: 80 calibration and 80 test poses over the
whole workspace (effects.truth.effect_session: random geometric errors within
10 mm / 1 deg, test rows interleaved in time with the calibration rows, a
temperature column), spot noise uniform +-0.5 mm, joint disturbance uniform
+-0.02 deg, the effect at its typical size (the truth form's default, see each
effect's docstring) with random signs. laser-calib's diagnose is given the
spot and joint noise standard deviations (half-width / sqrt(3)).

Per case it records the chosen effects, the verdict, the test-set RMS spot
error of the geometric fit, of the final model and of the true effect model
(the geometric errors plus the true effect, at its true place, fitted on the
same calibration set), and the wall time of the whole diagnosis, and checks
the targets: the right effect is chosen (and nothing else), the final test
RMS is within 15 % of the true effect model's, the diagnosis takes < 30 s.
Control cases: no effect (expect "explained", nothing added) and two effects
outside the library, a joint error proportional to q^3 and a sudden step of a
joint offset halfway through the session (expect "structure remains", and no
added effect that worsens the test error).

The foreign family (issue 13): six kinds outside the library the verdict's
tests were designed around (FOREIGN) and two kinds added afterwards that were
not (NEW_KINDS: a third harmonic of a joint's angle, a link offset pulled by a
hose that winds with another joint), each at joints drawn per seed, reported
apart. The summary counts the false alarms too: "structure remains" on a
library case or on effect-free data (and "undetermined" there, apart).

    .venv/bin/python bench/effects_bench.py [--seeds 1 2 3] [--jobs 2]

Seeds 1-3 are the ones the verdict's tests were changed while looking at; a
change is judged again on seeds never looked at (results/effects_heldout.*,
results/effects_seeds89.*):

    .venv/bin/python bench/effects_bench.py --seeds 6 7 --name effects_heldout
    .venv/bin/python bench/effects_bench.py --seeds 8 9 --name effects_seeds89

and on five more kinds written after the diagnosis was built (PROBE_KINDS: the
laser mount tilting with the last joint, a joint error following the product
of two joints' angles, a joint error on one side of its range only, a link
offset growing with the square of the temperature, a link length following
the square of another joint's angle), not in the default run:

    .venv/bin/python bench/effects_bench.py --seeds 10 11 --name effects_probe \
        --kinds p_mount p_product p_one_sided p_heat p_length

and on a second probe written after the first one's results were in, run once
as written and not used to change anything (PROBE2_KINDS: backlash taken up by
the load, a joint error at 1.5 times its angle, a warm-up settling in a tenth of
the session, a link twist following the cube of another angle, a link offset
following |another angle|):

    .venv/bin/python bench/effects_bench.py --seeds 12 13 --name effects_probe2 \
        --kinds s_load_backlash s_ratio s_warmup s_twist s_vee

and on arms it was never tuned on, given as D-H robot files (the effects placed by the rules of
``places``; bench/robots/ur5e_laser.yaml: a UR5e with the paper's laser module):

    .venv/bin/python bench/effects_bench.py --robots bench/robots/ur5e_laser.yaml --seeds 1 2 \
        --jobs 2 --name effects_ur5e
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from typing import Callable

from _common import RESULTS, verdict_cell, warned_worse_on_test, worse_on_test_warned, write_results

import numpy as np
from scipy import stats

from laser_calib.diagnosis.engine import diagnose
from laser_calib.diagnosis.options import DiagnoseOptions
from laser_calib.effects import Backlash, Compliance, Drift, JointScale, Periodic
from laser_calib.effects.catalog import camera_distortion, screen_shape
from laser_calib.effects.effect_model import EffectModel
from laser_calib.effects.joint import gravity_torques
from laser_calib.sim.effect_truth import (TEMPERATURE, ForeignError, ForeignJointError, TrueEffect, Truth, draw_truth,
                                          effect_session, fitted_test_rms, sized, true_offsets_rms)
from laser_calib.estimation.estimate import EstimateOptions
from laser_calib.measurement.spot import SpotModel
from laser_calib.model.robot import Robot
from laser_calib.model.robot_file import load_robot
from laser_calib.io.samples import Samples
from laser_calib.sim.simulation import NoiseSpec, bundled_robot

NOISE = NoiseSpec(spot=0.5e-3, joint=float(np.deg2rad(0.02)))
N_CAL = N_TEST = 80
RMS_MARGIN = 1.15
VISIBILITY = 150.0  # chi^2 excess each simulated effect leaves in the geometric fit (effects.truth.sized)
CUBIC = 8e-3  # rad at the ends of the joint range
COUPLING = 5e-3  # rad per rad
PERIOD = 10.0  # s between rows (effect_session's default)
TIME_LIMIT = 30.0

Maker = Callable[[Robot, Samples], object]

# Where each effect sits on each arm: joints that move over a wide range (scale,
# periodic), that carry a changing gravity load (compliance), any joint
# (backlash); a link length of the upper arm; the screen and the camera.
PLACES: dict[str, dict[str, Maker]] = {
    "paper-7dof": {
        "joint_scale": lambda r, c: JointScale(joint=0),
        "compliance": lambda r, c: Compliance.make(r, c, 1),
        "periodic": lambda r, c: Periodic(joint=4),
        "backlash": lambda r, c: Backlash(joint=3),
        "drift": lambda r, c: Drift.make(r, c, "a2", TEMPERATURE),
        "screen_shape": lambda r, c: screen_shape(r),
        "camera_distortion": lambda r, c: camera_distortion(r),
    },
    "paper-4dof": {
        "joint_scale": lambda r, c: JointScale(joint=3),
        "compliance": lambda r, c: Compliance.make(r, c, 1),
        "periodic": lambda r, c: Periodic(joint=2),
        "backlash": lambda r, c: Backlash(joint=1),
        "drift": lambda r, c: Drift.make(r, c, "slm_x", "stamp"),
        "screen_shape": lambda r, c: screen_shape(r),
        "camera_distortion": lambda r, c: camera_distortion(r),
    },
}
LIBRARY = tuple(PLACES["paper-7dof"])


def places(robot: Robot) -> dict[str, Maker]:
    """Where each effect sits on an arm of a robot file, by rules fixed before any of its results:
    scale on the base joint, compliance on joint 2 (the shoulder: it carries the whole arm),
    periodic on the joint of widest range (over a small part of a turn a harmonic is mostly an
    offset and a scale), backlash on joint 3, drift with the temperature on the longest link
    length beyond link 1 (whose a and d place the arm before the screen)."""
    low, high = robot.pose_range()
    widest = int(np.argmax(high - low))
    lengths = [i for i in range(4, robot.n_link_params) if robot.param_kinds()[i] == "length"]
    longest = robot.param_names[max(lengths, key=lambda i: abs(robot.vector()[i]))]
    return {
        "joint_scale": lambda r, c: JointScale(joint=0),
        "compliance": lambda r, c: Compliance.make(r, c, 1),
        "periodic": lambda r, c: Periodic(joint=widest),
        "backlash": lambda r, c: Backlash(joint=2),
        "drift": lambda r, c: Drift.make(r, c, longest, TEMPERATURE),
        "screen_shape": lambda r, c: screen_shape(r),
        "camera_distortion": lambda r, c: camera_distortion(r),
    }


def cubic(robot: Robot, joint: int) -> ForeignJointError:
    """q^3 about the middle of the joint's range, CUBIC at its ends."""
    middle, half = (robot.q_max[joint] + robot.q_min[joint]) / 2, (robot.q_max[joint] - robot.q_min[joint]) / 2
    return ForeignJointError("joint error ~ q^3", joint, lambda s: CUBIC * ((s.q[:, joint] - middle) / half) ** 3)


def step(robot: Robot, joint: int) -> ForeignJointError:
    """A joint offset that jumps by 3 mrad halfway through the session (a slipped coupling)."""
    return ForeignJointError("joint offset steps in time", joint,
                             lambda s: np.where(s.stamp > N_CAL * PERIOD / 2, 3e-3, 0.0))


def coupling(robot: Robot, joint: int) -> ForeignJointError:
    """The joint's angle follows the next joint's reading, COUPLING rad per rad
    (a cable-driven or differential joint): no library effect of one joint has it."""
    other = (joint + 1) % robot.n_joints
    return ForeignJointError(f"joint error ~ q{other + 1} (coupling)", joint, lambda s: COUPLING * s.q[:, other])


OUTSIDE = {"cubic": cubic, "step": step, "coupling": coupling}
# Joint (0-based) of each outside effect per arm. The 4-DOF arm's joints 3 and 4
# are parallel, so an error of joint 3 following q4 is a scale error of joint 4:
# the coupling sits on joint 2 there.
OUTSIDE_JOINT = {"paper-7dof": {"cubic": 0, "step": 1, "coupling": 3},
                 "paper-4dof": {"cubic": 2, "step": 1, "coupling": 1}}
# On an arm of a robot file: the base joint, whose axis is not parallel to the shoulder's, and
# the shoulder.
FILE_OUTSIDE_JOINT = {"cubic": 0, "step": 1, "coupling": 0}
# q^3 is not outside the library's span: periodic (1st and 2nd harmonic) plus
# joint scale fit it to 0.5 % over any of these joint ranges, so "explained" by
# those effects is the right answer; only its test error is checked.
INSIDE_SPAN = {"cubic"}


# The foreign family (issue 13): six kinds of error outside the library, each at
# joints drawn per seed (never tuned to a place), sized like the library effects
# (VISIBILITY). Each maker takes the nominal robot and the seed's generator and
# returns offsets(true robot, samples) -> (P, n) of the geometric parameters.
def _span(robot: Robot, joint: int, q: np.ndarray) -> np.ndarray:
    """q of the joint mapped to [-1, 1] over its range."""
    middle, half = (robot.q_max[joint] + robot.q_min[joint]) / 2, (robot.q_max[joint] - robot.q_min[joint]) / 2
    return (q[:, joint] - middle) / half


def _on(robot: Robot, column: int, values: np.ndarray) -> np.ndarray:
    out = np.zeros((len(values), robot.n_params))
    out[:, column] = values
    return out


def _two(rng: np.random.Generator, n: int) -> tuple[int, int]:
    first, second = rng.choice(n, 2, replace=False)
    return int(first), int(second)


def foreign_coupling(robot: Robot, rng: np.random.Generator) -> ForeignError:
    i, j = _two(rng, robot.n_joints)
    return ForeignError(f"coupling: dq{i + 1} ~ q{j + 1}",
                        lambda r, s: _on(r, 4 * i + 3, _span(r, j, s.q)))


def foreign_stiffness(robot: Robot, rng: np.random.Generator) -> ForeignError:
    i, k = _two(rng, robot.n_joints)
    return ForeignError(f"stiffness of joint {i + 1} varying with q{k + 1}",
                        lambda r, s: _on(r, 4 * i + 3, gravity_torques(r, s.q)[:, i] * (1 + 0.8 * np.sin(s.q[:, k]))))


def foreign_polynomial(robot: Robot, rng: np.random.Generator) -> ForeignError:
    i, mix = int(rng.integers(robot.n_joints)), float(rng.uniform(-1, 1))
    t4, t5 = np.polynomial.chebyshev.Chebyshev.basis(4), np.polynomial.chebyshev.Chebyshev.basis(5)
    return ForeignError(f"polynomial error of joint {i + 1} (T4 {mix:+.2f} T5)",
                        lambda r, s: _on(r, 4 * i + 3, t4(_span(r, i, s.q)) + mix * t5(_span(r, i, s.q))))


def foreign_step(robot: Robot, rng: np.random.Generator) -> ForeignError:
    i, when = int(rng.integers(robot.n_joints)), float(rng.uniform(0.3, 0.7)) * N_CAL * PERIOD
    return ForeignError(f"offset of joint {i + 1} steps at {when:.0f} s",
                        lambda r, s: _on(r, 4 * i + 3, (s.stamp > when).astype(float)))


def foreign_bending(robot: Robot, rng: np.random.Generator) -> ForeignError:
    i = int(rng.integers(robot.n_joints - 1))
    return ForeignError(f"link {i + 1} bends under the load beyond it (twist)",
                        lambda r, s: _on(r, 4 * i + 2, gravity_torques(r, s.q)[:, i + 1]))


def foreign_two_joint(robot: Robot, rng: np.random.Generator) -> ForeignError:
    i, j = _two(rng, robot.n_joints)
    phase = float(rng.uniform(0, np.pi))
    return ForeignError(f"error of joint {i + 1} ~ sin q{j + 1} sin(q{i + 1} + {phase:.2f})",
                        lambda r, s: _on(r, 4 * i + 3, np.sin(s.q[:, j]) * np.sin(s.q[:, i] + phase)))


def foreign_harmonic(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """A third harmonic of the joint's own angle (a three-lobed wave generator): the library's periodic
    effect has the first and second only."""
    i, phase = int(rng.integers(robot.n_joints)), float(rng.uniform(0, 2 * np.pi))
    return ForeignError(f"error of joint {i + 1} ~ sin(3 q{i + 1} + {phase:.2f})",
                        lambda r, s: _on(r, 4 * i + 3, np.sin(3 * s.q[:, i] + phase)))


def foreign_hose(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """A link offset d_i pulled by a hose that winds with another joint: a length varying with a joint angle."""
    i, j = _two(rng, robot.n_joints)
    phase = float(rng.uniform(0, 2 * np.pi))
    return ForeignError(f"d{i + 1} ~ cos(q{j + 1} + {phase:.2f}) (hose pull)",
                        lambda r, s: _on(r, 4 * i + 1, np.cos(s.q[:, j] + phase)))


def probe_mount(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """The laser module's mount tilts (slm_ry or slm_rz) as the last joint turns (a loose clamp under its cable)."""
    j, name = robot.n_joints - 1, str(rng.choice(["slm_ry", "slm_rz"]))
    phase = float(rng.uniform(0, 2 * np.pi))
    return ForeignError(f"{name} ~ cos(q{j + 1} + {phase:.2f}) (mount tilt)",
                        lambda r, s: _on(r, r.param_names.index(name), np.cos(s.q[:, j] + phase)))


def probe_product(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """A joint error following the product of two (possibly equal) joints' angles."""
    i, j, k = (int(v) for v in rng.integers(robot.n_joints, size=3))
    return ForeignError(f"dq{i + 1} ~ u{j + 1} u{k + 1}",
                        lambda r, s: _on(r, 4 * i + 3, _span(r, j, s.q) * _span(r, k, s.q)))


def probe_one_sided(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """A joint error on one side of its range only, growing as |u|^1.5 (a worn half of a gear)."""
    i = int(rng.integers(robot.n_joints))
    return ForeignError(f"dq{i + 1} ~ max(u{i + 1}, 0)^1.5",
                        lambda r, s: _on(r, 4 * i + 3, np.maximum(_span(r, i, s.q), 0.0) ** 1.5))


def probe_heat(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """A link offset d_i growing with the square of the temperature's departure from its mean."""
    i = int(rng.integers(robot.n_joints))

    def offsets(r: Robot, s: Samples) -> np.ndarray:
        t = np.asarray(s.extra[TEMPERATURE], float)
        u = (t - t.mean()) / max(float(np.ptp(t)), 1e-12)
        return _on(r, 4 * i + 1, u ** 2 - np.mean(u ** 2))
    return ForeignError(f"d{i + 1} ~ temperature^2", offsets)


def probe_length(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """A link length a_i following the square of another joint's angle."""
    i, j = _two(rng, robot.n_joints)
    return ForeignError(f"a{i + 1} ~ u{j + 1}^2", lambda r, s: _on(r, 4 * i, _span(r, j, s.q) ** 2))



# A second probe (PROBE2_KINDS), written after the first probe's results were in and before any run of
# its own: nothing in the diagnosis was changed while looking at it.
def probe2_load_backlash(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """Backlash taken up by the load: a joint's error flips with the sign of its gravity torque (0 where
    the torque is under 1 % of its largest: a joint the load does not turn has nothing to take up)."""
    i = int(rng.integers(1, robot.n_joints))

    def offsets(r: Robot, s: Samples) -> np.ndarray:
        torque = gravity_torques(r, s.q)[:, i]
        return _on(r, 4 * i + 3, np.sign(torque) * (np.abs(torque) > 0.01 * np.abs(torque).max()))
    return ForeignError(f"dq{i + 1} ~ sign(gravity torque {i + 1}) (load-side backlash)", offsets)


def probe2_ratio(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """A belt stage of ratio 3:2 behind a joint: its error follows 1.5 times the joint's angle."""
    i, phase = int(rng.integers(robot.n_joints)), float(rng.uniform(0, 2 * np.pi))
    return ForeignError(f"dq{i + 1} ~ sin(1.5 q{i + 1} + {phase:.2f})",
                        lambda r, s: _on(r, 4 * i + 3, np.sin(1.5 * s.q[:, i] + phase)))


def probe2_warmup(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """A joint offset that settles as the drive warms up: 1 - exp(-t / tau), tau a tenth of the session."""
    i, tau = int(rng.integers(robot.n_joints)), 0.1 * N_CAL * PERIOD
    return ForeignError(f"dq{i + 1} ~ 1 - exp(-t / {tau:.0f} s) (warm-up)",
                        lambda r, s: _on(r, 4 * i + 3, 1 - np.exp(-(s.stamp - s.stamp.min()) / tau)))


def probe2_twist(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """A link's twist alpha_i following the cube of another joint's angle."""
    i, j = _two(rng, robot.n_joints)
    return ForeignError(f"alpha{i + 1} ~ u{j + 1}^3", lambda r, s: _on(r, 4 * i + 2, _span(r, j, s.q) ** 3))


def probe2_vee(robot: Robot, rng: np.random.Generator) -> ForeignError:
    """A link offset d_i following |u_j| (a cam follower on another joint: a kink at mid-range)."""
    i, j = _two(rng, robot.n_joints)
    return ForeignError(f"d{i + 1} ~ |u{j + 1}|", lambda r, s: _on(r, 4 * i + 1, np.abs(_span(r, j, s.q))))


FOREIGN = {"f_coupling": foreign_coupling, "f_stiffness": foreign_stiffness, "f_polynomial": foreign_polynomial,
           "f_step": foreign_step, "f_bending": foreign_bending, "f_two_joint": foreign_two_joint,
           "f_harmonic": foreign_harmonic, "f_hose": foreign_hose,
           "p_mount": probe_mount, "p_product": probe_product, "p_one_sided": probe_one_sided, "p_heat": probe_heat,
           "p_length": probe_length, "s_load_backlash": probe2_load_backlash, "s_ratio": probe2_ratio,
           "s_warmup": probe2_warmup, "s_twist": probe2_twist, "s_vee": probe2_vee}
# Kinds added after the specification test (diagnosis/specification.py) was designed, and not used to
# design it: its Legendre basis of degree 2 is not made for a third harmonic, nor its columns for a
# length following a joint; reported apart from the six it was designed around.
NEW_KINDS = ("f_harmonic", "f_hose")
# Kinds written after the diagnosis was built, to judge it on effects it was not made for (module
# docstring); not in the default run.
PROBE_KINDS = ("p_mount", "p_product", "p_one_sided", "p_heat", "p_length")
PROBE2_KINDS = ("s_load_backlash", "s_ratio", "s_warmup", "s_twist", "s_vee")
COMPENSATED_MARGIN = 1.25
EXPLAINED_MARGIN = 1.3


def not_worse(diagnosis) -> bool:
    """The final model is not significantly worse than the geometric fit on the
    test poses: one-sided Wilcoxon signed-rank test over test poses of the
    squared spot distances, p >= 0.01."""
    first, last = diagnosis.stages[0].test, diagnosis.stages[-1].test
    both = np.isfinite(first) & np.isfinite(last)
    difference = (np.where(both, last, 0.0) ** 2 - np.where(both, first, 0.0) ** 2).sum(axis=1)
    difference = difference[difference != 0]
    return bool(len(difference) < 6 or stats.wilcoxon(difference, alternative="greater").pvalue >= 0.01)


def true_model_rms(session, truth: list[TrueEffect], options: EstimateOptions) -> float:
    """Test RMS (mm) of the geometric errors plus the true effects, fitted on the calibration set."""
    effects = [t.effect for t in truth]
    return fitted_test_rms(session, lambda samples: EffectModel(SpotModel(session.nominal, samples), effects), options)


def case_diagnosis(session, given: str):
    """The diagnosis of a case with the noise given as ``given`` says ('both': spot and joint sigma, 'spot').
    Every case has its own 80 test poses the selection never saw: their RMS is the held-out figure
    here, so the nested selection (the library's default, about 6x the time) is not run; the
    positioner bench and test_diagnosis's CLI test measure it."""
    return diagnose(session.nominal, session.cal, session.test,
                    spot_sigma=NOISE.spot_sigma if given in ("both", "spot") else None,
                    joint_sigma=NOISE.joint_sigma if given == "both" else None,
                    options=DiagnoseOptions(nested=False))


def arm(case: str) -> tuple[Robot, dict[str, Maker], dict[str, int]]:
    """The nominal robot of ``case`` (a paper arm's name or a robot file), where the library
    effects sit on it and the joints of the outside effects."""
    if case in PLACES:
        return bundled_robot(case), PLACES[case], OUTSIDE_JOINT[case]
    robot = load_robot(case)
    return robot, places(robot), FILE_OUTSIDE_JOINT


def run_case(case: str, kind: str, seed: int, visible: float = VISIBILITY, given: str = "both") -> dict:
    options = EstimateOptions(spot_sigma=NOISE.spot_sigma, joint_sigma=NOISE.joint_sigma)
    nominal, place, outside_joint = arm(case)
    robot_joint = outside_joint.get(kind, 0)
    truth_effects: list[Truth] = []

    def make_truth(robot, errors, context, rng):
        if kind in place:
            drawn = draw_truth(place[kind](robot, context), rng)
            truth_effects.append(sized(robot, errors, context, drawn, NOISE, visible))
        elif kind in OUTSIDE:
            truth_effects.append(OUTSIDE[kind](robot, robot_joint))
        elif kind in FOREIGN:
            truth_effects.append(sized(robot, errors, context, FOREIGN[kind](robot, rng), NOISE, visible))
        return list(truth_effects)

    session = effect_session(nominal, seed, make_truth, N_CAL, N_TEST, NOISE, PERIOD)
    start = time.perf_counter()
    diagnosis = case_diagnosis(session, given)
    elapsed = time.perf_counter() - start
    result = diagnosis.to_json()
    stages = result["stages"]
    chosen = [f"{e['name']} ({e['where']}" + (f" with {e['covariate']})" if "covariate" in e else ")")
              for e in result["effects"]]
    row = {"arm": nominal.name if case not in PLACES else case, "effect": kind, "seed": seed, "noise_given": given,
           "visibility": visible if kind in place else None,
           "chosen": chosen, "verdict": result["verdict"], "warned_worse_on_test": warned_worse_on_test(result),
           "geometric_test_rms_mm": stages[0]["test"]["rms_mm"], "final_test_rms_mm": stages[-1]["test"]["rms_mm"],
           "time_s": elapsed, "evidence": result["evidence"],
           "detector_gain": result["detector"]["heldout_gain"], "detector_p": result["detector"]["p"],
           "compensated_test_rms_mm": (result["compensator"]["test"]["rms_mm"] if result["compensator"]
                                       else stages[-1]["test"]["rms_mm"])}
    if kind in place:
        truth = truth_effects[0]
        row["truth"] = truth.effect.label
        row["true_values"] = truth.values.tolist()
        row["size_in_typical"] = float(np.linalg.norm(truth.values / truth.effect.typical) / np.sqrt(truth.values.size))
        row["true_model_test_rms_mm"] = true_model_rms(session, truth_effects, options)
        right = [e for e in diagnosis.final.effects if e.label == truth.effect.label]
        row["checks"] = {"right_effect": len(right) == 1 and len(diagnosis.final.effects) == 1,
                         "rms_within_15pct": row["final_test_rms_mm"] <= RMS_MARGIN * row["true_model_test_rms_mm"],
                         "under_30s": elapsed < TIME_LIMIT}
        if right:
            block = diagnosis.final.model.blocks[0]
            est = diagnosis.final.estimate
            n_geo = diagnosis.final.model.n_geometric
            row["estimated_values"] = est.values[n_geo:][block].tolist()
            row["estimated_std"] = est.std[n_geo:][block].tolist()
    elif kind == "none":
        row["checks"] = {"explained": result["verdict"] == "explained", "nothing_added": not chosen,
                         "under_30s": elapsed < TIME_LIMIT}
    elif kind in FOREIGN:
        row["truth"] = truth_effects[0].name
        true_rms = row["true_model_test_rms_mm"] = true_offsets_rms(session, truth_effects[0], options)
        row["checks"] = {"not_explained": result["verdict"] != "explained",
                         "honest": result["verdict"] != "explained" or row["final_test_rms_mm"] <= EXPLAINED_MARGIN * true_rms,
                         "compensated_within_25pct": row["compensated_test_rms_mm"] <= COMPENSATED_MARGIN * true_rms,
                         "under_30s": elapsed < TIME_LIMIT}
    else:
        row["truth"] = f"{truth_effects[0].name} (joint {robot_joint + 1})"
        row["checks"] = {"structure_remains": result["verdict"] == "structure remains",
                         "no_worse_on_test": not_worse(diagnosis), "under_30s": elapsed < TIME_LIMIT}
        if kind in INSIDE_SPAN:
            del row["checks"]["structure_remains"]
    return row


def summary(rows: list[dict]) -> dict:
    """The targets of issue 13 over the rows: the library set (every check), the
    foreign family (not "explained", never "explained" beyond 1.3x the true
    model's test RMS, compensated within 25 % of it)."""
    library = [r for r in rows if r["effect"] not in FOREIGN]
    out = {}
    if library:
        out["library_all_checks"] = [sum(all(r["checks"].values()) for r in library), len(library)]
    # A false alarm: "structure remains" where the model is the true one; "undetermined" there is
    # counted apart (the selection's rule: effects the data cannot tell apart, selection.ambiguous_verdict).
    clean = [r for r in library if r["effect"] in LIBRARY + ("none",)]
    if clean:
        out["false_alarms"] = [sum(r["verdict"] == "structure remains" for r in clean), len(clean)]
        out["clean_undetermined"] = [sum(r["verdict"] == "undetermined" for r in clean), len(clean)]
    six = [r for r in rows if r["effect"] in FOREIGN and r["effect"] not in NEW_KINDS + PROBE_KINDS + PROBE2_KINDS]
    for prefix, group in (("", six), ("new_kinds_", [r for r in rows if r["effect"] in NEW_KINDS]),
                          ("probe_kinds_", [r for r in rows if r["effect"] in PROBE_KINDS]),
                          ("probe2_kinds_", [r for r in rows if r["effect"] in PROBE2_KINDS])):
        if group:
            out.update({prefix + key: [sum(r["checks"][key] for r in group), len(group)]
                        for key in ("not_explained", "honest", "compensated_within_25pct")})
    # The diagnosis's warning that the effects it chose miss the test poses by more than the geometric model.
    out["worse_on_test_warned"] = list(worse_on_test_warned(rows))
    return out


def table(rows: list[dict]) -> str:
    lines = ["# Effect diagnosis benchmark", "",
             f"{N_CAL} calibration and {N_TEST} test poses over the whole workspace, spot noise uniform "
             f"+-{NOISE.spot * 1e3:g} mm, joint noise uniform +-{np.degrees(NOISE.joint):g} deg; "
             "RMS of the Euclidean spot error on the test poses.", "",
             "Each library effect is sized so that it leaves a chi^2 excess of "
             f"{VISIBILITY:g} in the geometric fit (effects.truth.sized); 'noise given': what diagnose was told "
             "(both: spot and joint sigma; spot: spot sigma only, the joint-reading noise is estimated).", "",
             "| noise given | arm | simulated | seed | chosen | verdict | geometric (mm) | final (mm) | true model (mm) "
             "| time (s) | checks |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        truth = r.get("truth", "none")
        true_rms = f"{r['true_model_test_rms_mm']:.3f}" if "true_model_test_rms_mm" in r else "-"
        checks = ", ".join(("" if ok else "FAIL ") + name for name, ok in r["checks"].items())
        lines.append(f"| {r['noise_given']} | {r['arm']} | {truth} | {r['seed']} | {'; '.join(r['chosen']) or 'nothing'} | "
                     f"{verdict_cell(r)} | "
                     f"{r['geometric_test_rms_mm']:.3f} | {r['final_test_rms_mm']:.3f} | {true_rms} | "
                     f"{r['time_s']:.1f} | {checks} |")
    passed = sum(all(r["checks"].values()) for r in rows)
    lines += ["", f"{passed} of {len(rows)} cases meet every target (under_30s is wall time on a shared, loaded "
                  "machine); slowest diagnosis "
                  f"{max(r['time_s'] for r in rows):.1f} s."]
    lines += [f"- {key}: {n} of {total}" for key, (n, total) in summary(rows).items()]
    return "\n".join(lines) + "\n"


def payload(rows: list[dict], start: float) -> dict:
    return {"noise": {"spot_halfwidth_m": NOISE.spot, "joint_halfwidth_rad": NOISE.joint},
            "poses": {"calibration": N_CAL, "test": N_TEST}, "summary": summary(rows),
            "wall_time_s": time.perf_counter() - start, "cases": rows}


def _case(job: tuple[str, str, str, int]) -> dict:
    given, case, kind, seed = job
    return run_case(case, kind, seed, given=given)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3],
                        help="the seeds of every case (default 1 2 3; e.g. 4 5 for a set never looked at)")
    parser.add_argument("--given", nargs="+", choices=("both", "spot", "none"), default=["both", "spot"],
                        help="noise given to diagnose: spot and joint sigma, spot sigma only, none")
    parser.add_argument("--kinds", nargs="+", help="only these simulated kinds (default: all)")
    parser.add_argument("--jobs", type=int, default=1, help="cases run in parallel (processes)")
    parser.add_argument("--name", default="effects", help="results file name in bench/results (NAME.md, .json)")
    parser.add_argument("--robots", nargs="+", metavar="FILE",
                        help="D-H robot files of the arms to run on, in place of the two paper arms")
    args = parser.parse_args()
    for path in args.robots or []:
        if load_robot(path).chain is not None:
            parser.error(f"{path}: the foreign kinds put their errors on D-H parameters; give a D-H robot file")
    rows = []
    start = time.perf_counter()
    kinds = args.kinds or [k for k in FOREIGN if k not in PROBE_KINDS + PROBE2_KINDS] + ["none"] + list(LIBRARY) + list(OUTSIDE)
    jobs = [(given, case, kind, seed) for given in args.given for case in args.robots or PLACES for kind in kinds
            for seed in args.seeds]
    # Each case is seeded on its own, so the rows do not depend on --jobs (their times do: shared cores).
    with multiprocessing.get_context("spawn").Pool(args.jobs) as pool:
        for (given, case, kind, seed), row in zip(jobs, pool.imap(_case, jobs)):
            print(f"[{given}] {case} {kind} seed {seed}: chose {row['chosen'] or 'nothing'}, "
                  f"{row['verdict']}, {row['time_s']:.1f} s, {row['checks']}", flush=True)
            rows.append(row)
            # Written after every case: a long run interrupted keeps what it measured.
            (RESULTS / f"{args.name}.json").write_text(json.dumps(payload(rows, start), indent=2))
            (RESULTS / f"{args.name}.md").write_text(table(rows))
    write_results(args.name, payload(rows, start), table(rows))


if __name__ == "__main__":
    main()
