"""The sequencer's session folder opened: one owner (its lock), a new session started with
its pose plan, or a partial one resumed under the rules that keep its poses one data set
(the same robot, plan, namespace and spot frames per pose; other settings said where they
changed)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from laser_calib.planning import values_and_determined
from laser_calib.session.folder import POSES_FILE, PLAN_DEFAULTS, Reconciled, SessionDir, plan_value, refuse_finished
from laser_calib.session.lock import SessionLock
from laser_calib.session.poses import generate_poses, load_poses, with_test_poses

from laser_calib_nodes import common, parameters

FRAMES = 3   # the frames parameter's default: spot frames averaged per pose

PLAN_HELP = {   # the parameters of the pose plan (defaults: folder.PLAN_DEFAULTS)
    "poses_file": "Pose list (YAML or CSV, rad); empty: generate 'poses' poses.",
    "poses": "Number of poses to generate when poses_file is empty.",
    "span": "Generated poses: 'whole' (joint ranges) or 'small' (+-10 deg around zero).",
    "seed": "Seed of the pose generator.",
    "repeats": "Generated poses measured a second time at the end (same pose id).",
    "test_poses": "Held-out poses over the whole workspace, measured after the others and never fitted "
                  "(test_samples.csv, the report's held-out figures).",
    "margin": "Generated poses keep both spots this far inside the screen edge, m.",
}


def open_session(node):
    """(session, lock, robot, poses, state) from the session parameters; the lock is held.
    A partial session is resumed on its own pose plan and in its own ROS namespace: other plan
    arguments and another namespace are refused (SessionDir.check_plan, check_namespace), other
    settings are used with a warning (warn_settings)."""
    d = lambda *a, **k: parameters.declare(node, *a, **k)  # noqa: E731
    robot_source = common.robot_source(node)
    output_dir = d("output_dir", "", "Session directory: samples.csv, bag/, report (created; resumed "
                                     "when it holds a partial session).")
    plan = {name: d(name, PLAN_DEFAULTS[name], text) for name, text in PLAN_HELP.items()}
    resume = d("resume", "auto", "'auto': resume a partial session in output_dir, else start one; "
                                 "'yes': resume (error if none); 'no': never (error if output_dir holds a session).")
    if not output_dir:
        raise parameters.NodeError("parameter output_dir is empty: give the session directory", 2)
    if resume not in ("auto", "yes", "no"):
        raise parameters.NodeError(f"parameter resume: expected 'auto', 'yes' or 'no', got {resume!r}", 2)
    session = SessionDir(Path(output_dir).resolve())
    lock = SessionLock(session.path)
    lock.acquire()
    refuse_finished(session.path, "output_dir")
    state = session.state()
    if state == "partial" and resume == "no":
        raise parameters.NodeError(f"{session.path} holds a partial session and resume is 'no'", 2)
    if state == "new" and resume == "yes":
        raise parameters.NodeError(f"{session.path}: no session to resume", 2)
    if state == "partial":
        if robot_source.path:  # a robot given must be the session's (its poses, samples, report are of it)
            session.check_robot(*robot_source.load(node, lasers=True))
        session.check_plan(plan)
        session.check_namespace(node.get_namespace())
        check_frames(node, session)
        warn_settings(node, session)
        robot, poses = session.load_for_resume()
        return session, lock, robot, poses, state
    robot, robot_label = robot_source.load(node, lasers=True)
    poses = (load_poses(plan["poses_file"], robot) if plan["poses_file"] else
             generate_poses(robot, plan["poses"], plan["span"], plan["seed"], plan["repeats"], plan["margin"]))
    poses = with_test_poses(poses, robot, plan["test_poses"], plan["seed"], plan["margin"])
    if node.end.mode != "none" and not node.end.prior:
        enough_poses(robot, poses.q[~poses.test])
    source = plan["poses_file"] or (f"generated: {plan['poses']} poses, span {plan['span']}, seed {plan['seed']}, "
                                   f"repeats {plan['repeats']}")
    session.start(robot, poses, {"robot": robot_label, "poses": source, "test_poses": plan["test_poses"],
                                 "plan": {name: plan_value(name, value) for name, value in plan.items()},
                                 "namespace": node.get_namespace(), "frames": node.frames,
                                 "settings": settings(node)})
    return session, lock, robot, poses, state


def enough_poses(robot, q: np.ndarray) -> None:
    """NodeError (exit 2) when the calibration poses q (P,N) give no more spot values than the
    errors they determine at the nominal model: the estimate after the last pose would refuse
    them (a session measured in full, then failed, and its plan, fixed by what was measured,
    could not grow on a resume)."""
    values, determined = values_and_determined(robot, q)
    if values <= determined:
        raise parameters.NodeError(f"the plan's {len(q)} poses give {values} spot values for the {determined} errors "
                                   "they determine: as many fit exactly, and the estimate after the last pose would "
                                   f"refuse them; plan more poses (poses:={robot.n_params // 4 + 1} or more), or "
                                   "estimate.prior:=true, or estimate.mode:=none", 2)


def settings(node) -> dict:
    """The session's parameters that do not change its pose plan, recorded to say on a resume
    which differ (a resume may change them): the sigmas as declared, so "not given" (0, -1)
    compares equal to itself."""
    end = node.end
    return {"estimate.method": end.method, "estimate.spot_sigma": end.spot_sigma,
            "estimate.joint_sigma": end.joint_sigma, "move.joint_speed": node.joint_speed,
            "settle.hold_time": node.settle_rule.hold_time}


def check_frames(node, session: SessionDir) -> None:
    """A resume averages as many spot frames per pose as the session's poses did: a pose of 1 frame
    has sqrt(3) times the spot noise of one of 3, and the estimate gives every pose one spot sigma
    (mixed, as a resume with frames:=1 did unsaid, the noise is no longer the model's). As the plan:
    refused when given anew and different, the recorded value used when left at its default."""
    recorded = (session.info() or {}).get("frames")
    if recorded is None or recorded == node.frames:
        return
    if node.frames != FRAMES:
        raise parameters.NodeError(f"{session.path} holds a partial session whose poses average {recorded} spot "
                                   f"frames each, given frames:={node.frames}: the poses left would carry another "
                                   "noise than those measured, which the estimate cannot tell apart; resume with "
                                   f"frames:={recorded} (or leave it out) or choose another output_dir", 2)
    node.get_logger().info(f"resume: {recorded} spot frames per pose, as the session's poses were measured")
    node.frames = recorded


def warn_settings(node, session: SessionDir) -> None:
    """One WARN line per setting that differs from the session's record (which then holds
    this run's value): the user sees which value this run uses."""
    recorded, current = (session.info() or {}).get("settings") or {}, settings(node)
    changed = [name for name, value in current.items() if name in recorded and recorded[name] != value]
    for name in changed:
        node.get_logger().warning(f"resume: {name} is {current[name]}, the session's previous run used "
                                  f"{recorded[name]}: this run uses {current[name]}")
    if changed:
        session.set_info(settings=current)


def say_resume(node, found: Reconciled, state: str) -> None:
    """The resume line and each repair the folder needed (found by reconcile, and by the recorder in
    the bag), logged and kept in session.yaml's ``resumes``: the report says in how many runs the
    session was measured and what was mended (said only in the log, a resumed or repaired session's
    report read as one run's)."""
    for line in found.repairs:
        node.get_logger().warning(f"resume repaired: {line}")
    if state != "partial":
        return
    session = node.session
    plan = ", ".join(f"{name} {value}" for name, value in session.recorded_plan().items() if value != "")
    measured = int(found.done.sum())
    node.get_logger().info(f"resuming {session.path}: {measured} of {len(node.poses)} poses already measured "
                           f"(pose list from {POSES_FILE}; plan: {plan})")
    resumes = (session.info() or {}).get("resumes") or []
    session.set_info(resumes=resumes + [{"at": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "measured": measured,
                                         "repairs": node.recorder.repairs + found.repairs}])


def history_lines(session: SessionDir, poses: int) -> list[str]:
    """report.md's section on how the session was measured, when it was resumed: each run's start,
    the poses measured before it, and the repairs it made."""
    info = session.info() or {}
    resumes = info.get("resumes") or []
    if not resumes:
        return []
    lines = ["", "## Session history", "", f"Measured in {len(resumes) + 1} runs (session.yaml `resumes`):",
             f"- started {info.get('started', '(unrecorded)')}"]
    for resume in resumes:
        repairs = resume.get("repairs") or []
        lines.append(f"- resumed {resume['at']} with {resume['measured']} of {poses} poses measured"
                     + (f"; repaired: {'; '.join(repairs)}" if repairs else ""))
    return lines + [""]
