"""A measurement session on disk (ROS-free): folder, samples files, resume and repair.

Session directory:

    session.yaml        what was started (robot, pose source, parameters) and its state
    robot.yaml          the nominal robot model used (copy)
    poses.csv           the pose sequence (pose,q1..qN[,test]), fixed at the first start
    samples.csv         the samples of the fit poses (conventions.md), one row appended per pose
    test_samples.csv    the samples of the test poses (held out: `laser-calib estimate --test`)
    bag/                rosbag2 MCAP bag in closed segments (io.bag_writer.SegmentedBagWriter)
    .recording/         the segment being written (lost in a crash: the pose in progress)
    .lock               the owner's lock and PID (session.lock)
    report.md, result.json, robot_calibrated.yaml (+ PNGs), truth.json   at the end

Resume: a sample is written to the bag (segment closed), then its CSV row. A crash
can leave the two disagreeing by the pose in flight: the bag one sample ahead
(killed before the row), the CSV one row ahead (the bag segment lost), a torn
last CSV line. ``reconcile`` repairs each: every sample found in either record
is kept, assigned to its step of the pose list by pose id (repeats in order),
the CSV files are rewritten to hold all of them, and the samples only the CSV
had are returned for the node to write back into the bag. The steps with no
sample are measured next, in pose-list order. Only a sample whose pose id the
pose list does not hold (another session's data) is refused.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from laser_calib.io import bag
from laser_calib.io.errors import InputError
from laser_calib.io.joint_names import RobotJoints
from laser_calib.io.samples import Samples, format_samples, load_samples, parse_samples, sample_row
from laser_calib.model.robot import Robot
from laser_calib.model.robot_file import dump_robot, load_robot, save_robot
from laser_calib.session.durable import append_durably, write_durably
from laser_calib.session.poses import PoseSequence, load_poses, save_poses

SESSION_FILE = "session.yaml"
POSES_FILE = "poses.csv"
SAMPLES_FILE = "samples.csv"
TEST_SAMPLES_FILE = "test_samples.csv"
ROBOT_FILE = "robot.yaml"
BAG_DIR = "bag"
WORK_DIR = ".recording"
# The arguments that define a session's pose plan and the sequencer's defaults of them
# (session.yaml's ``plan``; see SessionDir.check_plan).
PLAN_DEFAULTS = {"poses_file": "", "poses": 60, "test_poses": 0, "span": "whole", "seed": 0, "repeats": 0,
                 "margin": 0.02}
_GENERATED = re.compile(r"generated: (\d+) poses, span (\w+), seed (\d+), repeats (\d+)")


def _shown(value) -> str:
    """A plan value in a message: an empty one (no pose file: generated) as 'none', not as nothing."""
    return "none" if value == "" else str(value)


def plan_value(name: str, value):
    """A plan argument as recorded and compared: a pose file by its absolute path."""
    return str(Path(value).resolve()) if name == "poses_file" and value else value


def empty_samples(n_joints: int) -> Samples:
    return Samples(np.zeros(0, int), np.zeros(0), np.zeros((0, n_joints)), np.zeros((0, 2, 2)))


def concat(parts: list[Samples], n_joints: int) -> Samples:
    parts = [p for p in parts if len(p)]
    if not parts:
        return empty_samples(n_joints)
    return Samples(np.concatenate([p.pose for p in parts]), np.concatenate([p.stamp for p in parts]),
                   np.vstack([p.q for p in parts]), np.concatenate([p.spots for p in parts]))


_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def same_model(a, b) -> bool:
    """Two robot files' contents (parsed YAML) the same model: equal up to the rounding a
    save and load leave in the numbers (also those of an embedded URDF text)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same_model(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same_model(x, y) for x, y in zip(a, b))
    if isinstance(a, str) and isinstance(b, str):
        return (_NUMBER.split(a) == _NUMBER.split(b) and
                same_model([float(x) for x in _NUMBER.findall(a)], [float(x) for x in _NUMBER.findall(b)]))
    numbers = all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in (a, b))
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12) if numbers else a == b


@dataclass(frozen=True)
class Reconciled:
    """What a resume found: done (P,) bool per step; fit and test, the samples of the done
    steps in measurement order; to_bag, the samples the bag lacked (rewrite them into it);
    repairs, one line per repair made (for the log)."""

    done: np.ndarray
    fit: Samples
    test: Samples
    to_bag: Samples
    repairs: list[str]


class SessionDir:
    """A session directory being measured (see the module docstring)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    @property
    def bag_dir(self) -> Path:
        return self.path / BAG_DIR

    @property
    def work_dir(self) -> Path:
        return self.path / WORK_DIR

    def state(self) -> str:
        """'new' (nothing there), 'partial' (started, not finished), 'finished'."""
        info = self.info()
        if info is None:
            return "new"
        return "finished" if info.get("state") == "finished" else "partial"

    def info(self) -> dict | None:
        path = self.path / SESSION_FILE
        if not path.exists():
            return None
        try:
            data = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError):
            raise InputError(str(path), "unreadable session file") from None
        return data if isinstance(data, dict) else {}

    def set_info(self, **updates) -> None:
        data = self.info() or {}
        data.update(updates)
        write_durably(self.path / SESSION_FILE, yaml.safe_dump(data, sort_keys=False))

    def start(self, robot: Robot, poses: PoseSequence, info: dict) -> None:
        """A new session: robot copy, pose list, empty samples files."""
        self.path.mkdir(parents=True, exist_ok=True)
        leftovers = [p.name for p in self.path.iterdir() if p.name in (SAMPLES_FILE, BAG_DIR, POSES_FILE)]
        if leftovers:
            raise InputError(str(self.path), f"holds {leftovers[0]} but no {SESSION_FILE}: not a session "
                                             "directory to resume; choose an empty output directory")
        save_robot(robot, self.path / ROBOT_FILE, header="Nominal robot model of this session.")
        save_poses(poses, self.path / POSES_FILE)
        for name in self.sample_files(poses):
            write_durably(self.path / name, format_samples(empty_samples(robot.n_joints)))
        self.set_info(state="running", started=time.strftime("%Y-%m-%dT%H:%M:%S%z"), steps=len(poses),
                      test_steps=int(poses.test.sum()), **info)

    @staticmethod
    def sample_files(poses: PoseSequence) -> tuple[str, ...]:
        return (SAMPLES_FILE, TEST_SAMPLES_FILE) if poses.test.any() else (SAMPLES_FILE,)

    def load_for_resume(self) -> tuple[Robot, PoseSequence]:
        robot = load_robot(self.path / ROBOT_FILE)
        poses = load_poses(self.path / POSES_FILE, robot)
        return robot, poses

    def recorded_plan(self) -> dict:
        """The plan arguments of the session's first start: session.yaml's ``plan``; for a
        session started before it was recorded, what its pose description and test steps say."""
        info = self.info() or {}
        if isinstance(info.get("plan"), dict):
            return info["plan"]
        source = str(info.get("poses", ""))
        generated = _GENERATED.fullmatch(source)
        plan = ({"poses": int(generated[1]), "span": generated[2], "seed": int(generated[3]),
                 "repeats": int(generated[4])} if generated else {"poses_file": source} if source else {})
        return {**plan, "test_poses": int(info.get("test_poses", info.get("test_steps", 0)))}

    def check_plan(self, given: dict) -> None:
        """Refuse (InputError naming the folder, and each argument with its recorded and given
        value) to resume with plan arguments other than the session's: its pose list is fixed by
        what was measured, so another plan would be silently ignored (the held-out poses asked for
        missing, say). A value equal to the recorded one passes (a resume re-runs the same
        command), and so does the default: a launch cannot tell a default from an argument left
        out, and resuming with only output_dir must keep working; the recorded plan is used."""
        recorded = self.recorded_plan()
        changed = [name for name in PLAN_DEFAULTS if name in given and name in recorded and
                   plan_value(name, given[name]) not in (PLAN_DEFAULTS[name], recorded[name])]
        if changed:
            differences = "; ".join(f"{name} recorded {_shown(recorded[name])}, given {_shown(given[name])}"
                                    for name in changed)
            raise InputError(str(self.path), f"holds a partial session whose pose plan is fixed by what was "
                                             f"measured: {differences}; resume with the recorded values (or "
                                             f"leave them out) or choose another output_dir")

    def check_namespace(self, namespace: str) -> None:
        """Refuse (InputError naming the folder and both namespaces) to resume in another ROS
        namespace than the session's (session.yaml's ``namespace``; a session started before it was
        recorded passes): its nodes would record the poses to come on other topics than those
        measured (/rig3/samples beside /rig2/samples), and the bag would hold two sessions' samples."""
        recorded = (self.info() or {}).get("namespace")
        if recorded is not None and recorded != namespace:
            raise InputError(str(self.path), f"holds a partial session recorded in ROS namespace {recorded}, "
                                             f"resumed in {namespace}; resume it in {recorded} (the launch's "
                                             f"namespace:={recorded.strip('/')}) or choose another output_dir")

    def check_robot(self, robot: Robot, label: str) -> None:
        """Refuse (InputError naming the folder and both robots) to resume with a robot
        other than the session's robot.yaml: the models are compared as saved, not their names."""
        path = self.path / ROBOT_FILE
        try:
            saved = yaml.safe_load(path.read_text())
        except (OSError, yaml.YAMLError):
            raise InputError(str(path), "unreadable robot file of the session") from None
        given = yaml.safe_load(dump_robot(robot))
        if same_model(saved, given):
            return
        saved = saved if isinstance(saved, dict) else {}
        key = next(k for k in list(given) + list(saved) if not same_model(given.get(k), saved.get(k)))
        which = (f"is '{robot.name}'" if key == "name" else
                 f"of the same name is another model (its '{key}' differs)")
        raise InputError(str(self.path), f"holds a session of robot '{saved.get('name')}' ({path}), but robot "
                                         f"{label} {which}; resume with the session's robot file or choose "
                                         f"another output_dir")

    def reconcile(self, robot: Robot, poses: PoseSequence, joints: RobotJoints | None = None) -> Reconciled:
        """Bag and CSV files made to agree (see the module docstring); call it after the
        bag writer has opened the bag (it adopts a segment closed just before a crash).
        joints: the robot's joints as the bag's samples name them (default: the robot's names)."""
        joints = joints or RobotJoints(robot)
        done = np.zeros(len(poses), dtype=bool)
        kept, to_bag, repairs = {False: [], True: []}, [], []
        records = ((False, bag.SAMPLES_TOPIC, SAMPLES_FILE), (True, bag.TEST_SAMPLES_TOPIC, TEST_SAMPLES_FILE))
        for test, topic, name in records:
            in_bag = self._bag_samples(topic, robot, joints)
            in_csv, torn = self._csv_samples(self.path / name, robot)
            if torn:
                repairs.append(f"{name}: dropped a torn last line (a crash while appending it)")
            bag_steps = self._assign(in_bag, poses, test, f"{self.bag_dir} {topic}")
            csv_steps = self._assign(in_csv, poses, test, str(self.path / name))
            only_csv = [r for r, step in enumerate(csv_steps) if step not in set(bag_steps)]
            only_bag = [r for r, step in enumerate(bag_steps) if step not in set(csv_steps)]
            for r in only_bag:
                repairs.append(f"{name}: pose {in_bag.pose[r]} restored from the bag (a crash before its row)")
            for r in only_csv:
                repairs.append(f"bag: pose {in_csv.pose[r]} restored from {name} (its bag segment was lost)")
            merged = concat([in_bag, in_csv.subset(np.array(only_csv, dtype=int))], robot.n_joints)
            order = np.argsort(merged.stamp, kind="stable")
            merged = merged.subset(order)
            done[bag_steps] = True
            done[[csv_steps[r] for r in only_csv]] = True
            kept[test].append(merged)
            to_bag.append(in_csv.subset(np.array(only_csv, dtype=int)))
            if (name in self.sample_files(poses)) and (torn or only_bag or only_csv or len(in_csv) != len(merged)):
                write_durably(self.path / name, format_samples(merged))
        return Reconciled(done, concat(kept[False], robot.n_joints), concat(kept[True], robot.n_joints),
                          concat(to_bag, robot.n_joints), repairs)

    def _bag_samples(self, topic: str, robot: Robot, joints: RobotJoints) -> Samples:
        if not (self.bag_dir / bag.METADATA).exists():
            return empty_samples(robot.n_joints)
        samples = bag.read_samples(self.bag_dir, topic, joints, required=False)
        return empty_samples(robot.n_joints) if samples is None else samples

    @staticmethod
    def _csv_samples(path: Path, robot: Robot) -> tuple[Samples, bool]:
        """The rows of a samples file and whether a torn last line was dropped."""
        if not path.exists():
            return empty_samples(robot.n_joints), False
        lines = path.read_text().splitlines()
        torn = False
        for attempt in (lines, lines[:-1]):
            if len(attempt) <= 1:
                return empty_samples(robot.n_joints), torn
            try:
                return parse_samples("\n".join(attempt) + "\n", str(path), robot), torn
            except InputError:
                if torn:
                    raise
                torn = True
        raise AssertionError("unreachable")

    @staticmethod
    def _assign(samples: Samples, poses: PoseSequence, test: bool, where: str) -> list[int]:
        """The step of each sample: the first free step of its pose id (repeats share an id)."""
        taken = np.zeros(len(poses), dtype=bool)
        steps = []
        for r, pose_id in enumerate(samples.pose):
            free = np.flatnonzero((poses.pose == pose_id) & (poses.test == test) & ~taken)
            if len(free) == 0:
                raise InputError(where, f"sample {r + 1} is pose {pose_id}, which the pose list does not hold "
                                        f"(or not that often): not this session's data")
            taken[free[0]] = True
            steps.append(int(free[0]))
        return steps

    def append_sample(self, samples: Samples, test: bool = False) -> None:
        """Append the one row of ``samples`` to samples.csv (test_samples.csv), flushed to disk."""
        path = self.path / (TEST_SAMPLES_FILE if test else SAMPLES_FILE)
        append_durably(path, ",".join(sample_row(samples, 0)) + "\n")

    def samples(self, robot: Robot | None, test: bool = False) -> Samples:
        return load_samples(self.path / (TEST_SAMPLES_FILE if test else SAMPLES_FILE), robot)


class Progress:
    """Pose k of n and the time left, from the mean time per pose measured in this run."""

    def __init__(self, total: int, done: int, clock=time.monotonic):
        self.total = total
        self.done = done
        self.clock = clock
        self.start = clock()
        self.started_at = done

    def step(self) -> None:
        self.done += 1

    def seconds_left(self) -> float:
        measured = self.done - self.started_at
        if measured <= 0:
            return math.nan
        return (self.clock() - self.start) / measured * (self.total - self.done)

    def line(self) -> str:
        left = self.seconds_left()
        eta = "?" if math.isnan(left) else _duration(left)
        return f"{self.done}/{self.total} poses done, about {eta} left"


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    return f"{seconds // 60} min {seconds % 60:02d} s"


def outermost_missing(folder: Path) -> Path | None:
    """The outermost folder that creating ``folder`` makes (None: it exists): what to remove again
    when a run that made it leaves nothing in it."""
    missing = None
    while not folder.exists():
        missing, folder = folder, folder.parent
    return missing


def refuse_finished(folder: str | Path, name: str) -> None:
    """Refuse to write into a finished session's folder (InputError naming the argument
    ``name``): an estimate there replaced the session's report, result.json and calibrated
    robot while its truth, diagnosis and session.yaml stayed, a folder that disagreed with
    itself and had lost the session's own results. The session's own estimate writes there
    while the session is still running."""
    if SessionDir(Path(folder)).state() == "finished":
        raise InputError(name, f"{folder} holds a finished session, whose results this would replace; "
                               "choose another folder")
