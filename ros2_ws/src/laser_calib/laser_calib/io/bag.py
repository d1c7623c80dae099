"""Session bags (rosbag2, MCAP), ROS-free through rosbags: the type store with our
interfaces, offered-QoS records, and the reader (`laser-calib estimate --bag`,
replay, resume). The crash-safe writer is bag_writer.py.
"""

from __future__ import annotations

import math
import tempfile
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import yaml
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.typesys import Stores, get_typestore, get_types_from_msg
from rosbags.typesys.store import Typestore

from laser_calib.io.ament import installed
from laser_calib.io.errors import InputError
from laser_calib.io.joint_names import RobotJoints
from laser_calib.io.samples import Samples

INTERFACES = "laser_calib_interfaces"
SAMPLE_TYPE = f"{INTERFACES}/msg/Sample"
# A session's topics as its nodes name them in the root namespace; a session launched in one
# (namespace:=rig2) recorded /rig2/samples: session_topic finds it.
SAMPLES_TOPIC = "/samples"
TEST_SAMPLES_TOPIC = "/test_samples"  # the session's held-out poses: measured, never fitted
METADATA = "metadata.yaml"
_INFINITE = QosTime(9223372036, 854775807)  # RMW_DURATION_INFINITE, as ros2 bag (Jazzy) writes it


def qos(reliable: bool = True, transient_local: bool = False, depth: int = 10) -> Qos:
    """An offered QoS profile as rosbag2 metadata records it."""
    return Qos(QosHistory.KEEP_LAST, depth,
               QosReliability.RELIABLE if reliable else QosReliability.BEST_EFFORT,
               QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE,
               _INFINITE, _INFINITE, QosLiveliness.AUTOMATIC, _INFINITE, False)


def interfaces_msg_dir() -> Path:
    """The .msg files of laser_calib_interfaces: installed share, else the source tree."""
    path = installed(f"share/{INTERFACES}/msg")
    if path is not None and path.is_dir():
        return path
    path = Path(__file__).resolve().parents[3] / INTERFACES / "msg"
    if path.is_dir():
        return path
    raise InputError(INTERFACES, "message definitions not found (build the workspace: scripts/setup)")


def typestore() -> Typestore:
    """ROS 2 Jazzy types plus ours, for writing bags with the exact type hashes rclpy uses."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for path in sorted(interfaces_msg_dir().glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"{INTERFACES}/msg/{path.stem}"))
    store.register(types)
    return store



def segment_index(path: Path) -> int:
    stem = path.name.removesuffix(".mcap")
    tail = stem.rsplit("_", 1)[-1]
    return int(tail) if tail.isdigit() else 0



def stamp_seconds(sec: int, nanosec: int) -> float:
    """A header stamp as float seconds: the one conversion used for every samples stamp."""
    return float(sec) + float(nanosec) * 1e-9


class MissingTopic(InputError):
    """A bag that does not have the topic asked for (not damage: no segment is lost for it)."""


def _one_line(exc: Exception, limit: int = 300) -> str:
    """An exception's text on one line, cut at ``limit`` characters: a YAML parser's message spans
    lines, and rosbags lists every missing segment of a bag (3 kB for 82)."""
    text = " ".join(str(exc).split())
    return text if len(text) <= limit else text[:limit] + " ..."


def _reader(path: Path):
    from rosbags.highlevel import AnyReader
    if not path.exists():
        raise InputError(str(path), "no such bag")
    if path.is_dir() and not (path / METADATA).exists():
        raise InputError(str(path), f"not a rosbag2 bag (no {METADATA})")
    if path.is_file() and (path.parent / METADATA).exists():   # read alone, it was a bag of its few poses
        raise InputError(str(path), f"one file of the bag {path.parent}: give the bag's folder")
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY))
        reader.open()
    except InputError:
        raise
    except Exception as exc:  # rosbags raises several types; the user needs one line
        raise InputError(str(path), f"cannot read bag ({_one_line(exc)})") from None
    return reader


def read_messages(path: str | Path, topics: Sequence[str] | None = None) -> Iterator[tuple[str, str, int, bytes]]:
    """(topic, message type, bag timestamp ns, raw CDR) in recording order."""
    path = Path(path)
    reader = _reader(path)
    try:
        connections = [c for c in reader.connections if topics is None or c.topic in topics]
        if connections:
            for connection, timestamp, raw in reader.messages(connections=connections):
                yield connection.topic, connection.msgtype, timestamp, raw
    finally:
        reader.close()


@contextmanager
def intact_parts(path: str | Path) -> Iterator[tuple[list[Path], list[str]]]:
    """(the parts to read in turn, the damaged segments each as 'file (problem)'): the bag itself when
    it opens whole, else each segment that opens on its own (a one-segment bag in a temporary folder,
    removed on exit), as read_samples_checked keeps the intact segments' samples. InputError, the
    whole bag's, when none opens."""
    path = Path(path)
    try:
        _reader(path).close()
        whole = None
    except InputError as exc:
        whole = exc
    if whole is None:
        yield [path], []
        return
    with tempfile.TemporaryDirectory(prefix="bag-segments-") as root:
        parts, lost = [], []
        for name, single in _segments(path, Path(root)):
            try:
                _reader(single).close()
                parts.append(single)
            except InputError as exc:  # said of the bag's own file, not of the link made to read it alone
                lost.append(f"{name} ({exc.problem.replace(str(single), str(path))})")
        if not parts:
            raise whole
        yield parts, lost


def bag_topics(path: str | Path) -> dict[str, tuple[str, int, list[Qos]]]:
    """topic -> (type, message count, offered QoS profiles)."""
    reader = _reader(Path(path))
    try:
        out: dict[str, tuple[str, int, list[Qos]]] = {}
        for c in reader.connections:
            kind, count, profiles = out.get(c.topic, (c.msgtype, 0, list(c.ext.offered_qos_profiles)))
            out[c.topic] = (kind, count + c.msgcount, profiles)
        return out
    finally:
        reader.close()


def session_topic(path: str | Path, topic: str) -> str:
    """``topic`` (a session's topic as named in the root namespace, /samples) in the namespace of
    the session the bag holds: the namespace of its Sample topic named .../samples, the root
    where it has none. A session launched with namespace:=rig2 recorded /rig2/samples, and its
    bag read as no session at all ('no topic /samples'). A bag with the samples of more than one
    namespace (`ros2 bag record` of two sessions) is refused: their poses are not one session's."""
    names = _typed_topics(Path(path), SAMPLE_TYPE)
    spaces = sorted({name.removesuffix(SAMPLES_TOPIC) for name in names if name.endswith(SAMPLES_TOPIC)})
    if len(spaces) > 1:
        raise InputError(str(path), f"holds the samples of {len(spaces)} sessions ("
                                    f"{', '.join(space + SAMPLES_TOPIC for space in spaces)}): give one session's bag")
    return (spaces[0] if spaces else "") + topic


def _typed_topics(path: Path, msgtype: str) -> list[str]:
    """The names of the bag's topics of ``msgtype``: from its metadata, which a damaged
    segment leaves readable (read_samples_checked reads the others), else from the reader
    (bag_topics), which says what is wrong with the bag."""
    try:
        info = yaml.safe_load((path / METADATA).read_text())["rosbag2_bagfile_information"]
        return [entry["topic_metadata"]["name"] for entry in info["topics_with_message_count"]
                if entry["topic_metadata"]["type"] == msgtype]
    except Exception:  # a file, no metadata, or a torn one
        return [topic for topic, (kind, _, _) in bag_topics(path).items() if kind == msgtype]


def read_samples(path: str | Path, topic: str = SAMPLES_TOPIC, joints: RobotJoints | None = None,
                 required: bool = True) -> Samples | None:
    """The measured samples of a session bag (its /samples messages, in order; ``topic`` in the
    session's namespace, session_topic), as the core's Samples; not ``required``: None for a bag
    without the topic or without a message on it."""
    return read_samples_checked(path, topic, joints, required)[0]


def read_samples_checked(path: str | Path, topic: str = SAMPLES_TOPIC, joints: RobotJoints | None = None,
                         required: bool = True) -> tuple[Samples | None, list[str]]:
    """Samples and the damaged segments lost, one text each. If the bag cannot
    be read whole, each segment is read on its own and the intact ones kept.
    ``joints``: the robot's, each sample's joint_positions put in its order by the
    sample's joint_names; None: the positions as recorded. A bag without the topic,
    or without a message on it: InputError, or None when not ``required`` (a session
    without test poses has no /test_samples). ``topic``: in the session's namespace (session_topic)."""
    path = Path(path)
    topic = session_topic(path, topic)
    try:
        msgs = _sample_msgs(path, topic)
        lost: list[str] = []
    except MissingTopic:
        if required:
            raise
        return None, []
    except InputError as whole:
        with tempfile.TemporaryDirectory(prefix="bag-segments-") as root:
            segments = _segments(path, Path(root))
            if len(segments) < 2:
                raise whole from None
            msgs, lost = [], []
            for name, single in segments:
                try:
                    msgs += _sample_msgs(single, topic, str(path / name))
                except MissingTopic:  # its metadata lists the bag's topics: this one is not among them
                    continue
                except InputError as exc:  # said of the bag's own file, not of the link made to read it alone
                    lost.append(f"{name} ({exc.problem.replace(str(single), str(path))})")
        if len(lost) == len(segments):
            raise whole from None
    if not msgs:
        if not required:
            return None, lost
        raise InputError(str(path), f"topic {topic} holds no samples")
    # a sample that was read but is wrong is bad input, not a damaged segment: it refuses the bag
    rows = [sample_row_from_msg(msg, where, joints) for where, msg in msgs]
    samples = samples_from_rows(rows, f"{path} {topic}")
    said = [f"{path}: segment {segment} is damaged and was skipped; its samples are lost, the other segments "
            "were read" for segment in lost]
    if joints is not None:
        said += joints.naming_warnings([list(msg.joint_names) for _, msg in msgs], f"{path} {topic}")
    return replace(samples, warnings=samples.warnings + tuple(said)), lost


def _sample_msgs(path: Path, topic: str, label: str | None = None) -> list:
    """(where, message) of each sample on ``topic``, ``where`` naming the bag and the message."""
    reader = _reader(path)
    label = label or str(path)
    msgs = []
    try:
        connections = [c for c in reader.connections if c.topic == topic]
        if not connections:
            raise MissingTopic(label, f"no topic {topic} in the bag (not a calibration session bag?)")
        try:
            for index, (connection, _, raw) in enumerate(reader.messages(connections=connections)):
                msgs.append((f"{label}: {topic} message {index + 1}", reader.deserialize(raw, connection.msgtype)))
        except Exception as exc:  # a damaged segment: rosbags raises several types
            raise InputError(label, f"cannot read bag ({_one_line(exc)})") from None
    finally:
        reader.close()
    return msgs


def _segments(path: Path, root: Path) -> list[tuple[str, Path]]:
    """(file name, a one-segment bag of it) per segment listed in the metadata:
    a folder under root with a link to the segment and its own metadata."""
    try:
        meta = yaml.safe_load((path / METADATA).read_text())
        info = meta["rosbag2_bagfile_information"]
        files = [(entry, str(entry["path"])) for entry in info.get("files") or []]
    except Exception:  # no readable metadata (a torn file lists a segment without its path): nothing to split
        return []
    out = []
    for entry, name in files:
        single = root / Path(name).stem
        single.mkdir()
        (single / name).symlink_to((path / name).absolute())
        one = dict(info, relative_file_paths=[name], files=[entry],
                   message_count=entry.get("message_count", 0))
        (single / METADATA).write_text(yaml.safe_dump({**meta, "rosbag2_bagfile_information": one}))
        out.append((name, single))
    return out


def sample_row_from_msg(msg, where: str, joints: RobotJoints | None = None
                        ) -> tuple[int, float, np.ndarray, np.ndarray]:
    """(pose, stamp, q (N,), spots (2,2) NaN where unseen) from a Sample message
    (rclpy or rosbags object: same field names). ``joints``: the robot's, q put in its
    order by the message's joint_names; None: q as the message has it (a message the
    sequencer built itself, in the robot's order)."""
    q = np.array(msg.joint_positions, dtype=float)
    if joints is not None:
        q = joints.sample_positions(msg.joint_names, q, where)
    spots = np.full((2, 2), np.nan)
    if len(msg.spots) != 2:
        raise InputError(where, f"{len(msg.spots)} spots, expected 2")
    for j, spot in enumerate(msg.spots):
        if spot.seen:
            if not (math.isfinite(spot.y) and math.isfinite(spot.z)):
                raise InputError(where, f"laser {j + 1} spot marked seen has a non-finite coordinate")
            spots[j] = (spot.y, spot.z)
    stamp = stamp_seconds(msg.header.stamp.sec, msg.header.stamp.nanosec)
    return int(msg.pose), stamp, q, spots


def samples_from_rows(rows: Sequence[tuple[int, float, np.ndarray, np.ndarray]], where: str) -> Samples:
    """Samples from (pose, stamp, q, spots) rows; one line naming the row for bad ones."""
    if not rows:
        raise InputError(where, "no samples")
    n_joints = len(rows[0][2])
    for index, (pose, _, q, spots) in enumerate(rows):
        label = f"{where}: sample {index + 1} (pose {pose})"
        if len(q) != n_joints:
            raise InputError(label, f"{len(q)} joint positions, the first sample has {n_joints}")
        if len(q) == 0:
            raise InputError(label, "no joint positions")
        bad = [i for i, v in enumerate(q) if not math.isfinite(v)]
        if bad:
            raise InputError(label, f"joint_positions[{bad[0]}] is not finite ({q[bad[0]]})")
    return Samples(np.array([r[0] for r in rows], dtype=int), np.array([r[1] for r in rows], dtype=float),
                   np.array([r[2] for r in rows], dtype=float), np.array([r[3] for r in rows], dtype=float))

