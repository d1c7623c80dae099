"""Import of the real two-axis positioner data set (industrial_calibration).

The source (data/real/positioner_2axis/README.md) holds 205 pose measurements
of a target on the positioner's last link, seen by a static sensor, keyed by a
Unix time stamp, and rough guesses of the sensor in the world and the target
in the last link. The import writes the two files of this system:

- a robot file: the nominal standard D-H model (``convention: standard``), no
  SLM and no lasers, and the frame guesses (key ``frames``: sensor, base,
  target; docs/conventions-extended.md);
- a pose-samples CSV: pose,stamp,q1,q2,x,y,z,qw,qx,qy,qz in time order.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from laser_calib.io.errors import InputError
from laser_calib.io.read import finite_number, known_keys, load_yaml, read_text
from laser_calib.io.samples import check_joint_range
from laser_calib.model.robot import STANDARD, Joint, Robot, Slm, plausible_length
from laser_calib.measurement.frames import POSE_KEYS, Pose, with_frames
from laser_calib.measurement.rotations import quaternion_to_matrix
from laser_calib.io.sensor_samples import SensorSamples

MEASUREMENTS = "measurements.yaml"
GUESSES = "pose_initial_guesses.yaml"
# The source's keys, checked strictly: a misspelt one would otherwise drop its value unseen.
GUESS_KEYS = {"camera_mount_to_camera_guess": "sensor", "target_mount_to_target_guess": "target"}
ENTRY_KEYS = ("target_joints", "pose", "camera_joints")
# A Unix time in seconds is below 1e11 until the year 5138; above it, a count of a finer clock.
MAX_STAMP = 1e11
FINER_CLOCKS = (("milliseconds", 1e3), ("microseconds", 1e6), ("nanoseconds", 1e9),
                ("a count finer than nanoseconds", math.inf))

# Facts of the source's nominal model (README): standard D-H, base in world.
NOMINAL_JOINTS = (
    Joint(a=0.0, d=0.0, alpha=-math.pi / 2, theta0=0.0, min=-math.pi, max=math.pi),
    Joint(a=0.0, d=-0.475, alpha=0.0, theta0=-math.pi / 2, min=-2 * math.pi, max=2 * math.pi),
)
BASE_IN_WORLD = Pose(quaternion_to_matrix(np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])),
                     np.array([2.2, 0.0, 1.6]))


def _read_yaml(path: Path) -> Any:
    return load_yaml(read_text(path), str(path))


def _pose(where: str, mapping: Any) -> np.ndarray:
    """(x, y, z, qw, qx, qy, qz) from a mapping with those keys."""
    if not isinstance(mapping, Mapping):
        raise InputError(where, "expected a pose mapping x, y, z, qw, qx, qy, qz")
    known_keys(where, mapping, POSE_KEYS)
    values = [finite_number(mapping.get(key), f"{where}.{key}") for key in POSE_KEYS]
    for key, value in zip("xyz", values):
        plausible_length(f"{where}.{key}", value)
    if abs(np.linalg.norm(values[3:]) - 1.0) > 1e-3:
        raise InputError(where, f"quaternion norm {np.linalg.norm(values[3:]):.6g} is not 1")
    return np.array(values)


def positioner_robot(sensor: Pose, target: Pose) -> Robot:
    """The nominal positioner with its frame guesses (base in world from the source)."""
    # Gravity along -z of the world (REP 103: z up), expressed in the robot's frame {0}.
    gravity = tuple(float(v) + 0.0 for v in np.round(BASE_IN_WORLD.rotation.T @ np.array([0.0, 0.0, -1.0]), 12))
    robot = Robot(name="positioner_2axis", joints=NOMINAL_JOINTS, slm=Slm(0.0, 0.0, 0.0, 0.0), lasers=(),
                  gravity=gravity, convention=STANDARD)
    return with_frames(robot, {"sensor": sensor, "base": BASE_IN_WORLD, "target": target})


def read_positioner(directory: str | Path) -> tuple[Robot, SensorSamples]:
    """The robot (nominal + frame guesses) and the 205 samples in time order."""
    directory = Path(directory)
    guesses_path, measurements_path = directory / GUESSES, directory / MEASUREMENTS
    guesses = _read_yaml(guesses_path)
    if not isinstance(guesses, Mapping):
        raise InputError(str(guesses_path), "expected a mapping of pose guesses")
    known_keys(str(guesses_path), guesses, GUESS_KEYS)
    poses = {}
    for key, frame in GUESS_KEYS.items():
        if key not in guesses:
            raise InputError(str(guesses_path), f"missing key '{key}'")
        poses[frame] = Pose.from_values(_pose(f"{guesses_path}: {key}", guesses[key]))
    robot = positioner_robot(poses["sensor"], poses["target"])

    data = _read_yaml(measurements_path)
    if not isinstance(data, Mapping) or not data:
        raise InputError(str(measurements_path), "expected a non-empty mapping of stamp -> observation")
    rows = []
    for key, entry in data.items():
        where = f"{measurements_path}: {key}"
        try:
            stamp = float(key)
        except (TypeError, ValueError):
            raise InputError(where, "key is not a time stamp in seconds") from None
        if not math.isfinite(stamp):  # 'nan' and 'inf' are floats to Python, and samples.csv refuses them
            raise InputError(where, f"key is not a time stamp in seconds (not finite: {key!r})")
        if abs(stamp) >= MAX_STAMP:  # a finer clock's count: taken as seconds, every drift rate is off by its factor
            unit = next(name for name, factor in FINER_CLOCKS if abs(stamp) / factor < MAX_STAMP)
            raise InputError(where, f"key is not a time stamp in seconds (this looks like {unit} since 1970)")
        if not isinstance(entry, Mapping) or "target_joints" not in entry or "pose" not in entry:
            raise InputError(where, "expected target_joints and pose")
        known_keys(where, entry, ENTRY_KEYS)
        joints = entry["target_joints"]
        if (not isinstance(joints, list) or len(joints) != robot.n_joints
                or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in joints)):
            raise InputError(f"{where}.target_joints", f"expected {robot.n_joints} joint readings")
        if entry.get("camera_joints"):
            raise InputError(f"{where}.camera_joints", "a moving sensor is not supported (expected empty)")
        rows.append((stamp, [finite_number(v, f"{where}.target_joints[{i}]") for i, v in enumerate(joints)],
                     _pose(f"{where}.pose", entry["pose"])))
    rows.sort(key=lambda row: row[0])
    stamp = np.array([row[0] for row in rows])
    if np.any(np.diff(stamp) <= 0):
        raise InputError(str(measurements_path), "two observations share a time stamp")
    values = np.array([row[2] for row in rows])
    samples = SensorSamples(pose=np.arange(len(rows)), stamp=stamp, q=np.array([row[1] for row in rows]),
                            position=values[:, :3], quaternion=values[:, 3:])
    # here, not only when the samples are calibrated: the import writes them as if they were good
    check_joint_range(samples.q, robot, f"{measurements_path} (in time order)", samples.pose)
    return robot, samples
