"""Session bags: a crash-safe rosbag2 MCAP writer and a ROS-free reader.

Why segments. rosbags' MCAP writer keeps the open chunk (up to 1 MiB, with the
schemas and channels) in memory and writes the summary, the footer and
metadata.yaml only in close(). A process killed with SIGKILL therefore leaves
an MCAP file with next to nothing in it (seen: empty after 2000 joint states,
still buffered) and no metadata.yaml: neither `ros2 bag` nor rosbags opens it. (sqlite3 storage would keep the rows
but still lack metadata.yaml, which both readers require.)

So a session bag is a split rosbag2 bag, as `ros2 bag record --max-bag-duration`
makes: one directory with metadata.yaml and the files <name>_0.mcap,
<name>_1.mcap, ... Each message is written to the open segment as it arrives;
the recorder closes the segment at every completed pose (and after
``max_segment_seconds``), moves the finished .mcap file into the bag directory
and rewrites metadata.yaml atomically (write, fsync, rename) to list it. After a
crash the directory is a valid bag holding every closed segment, i.e. every
completed pose; only the open segment (the pose being measured) is lost, and it
is measured again on resume, which appends new segments to the same bag.

Nothing here imports rclpy: the reader serves the offline command line
(`laser-calib estimate --bag`).
"""

from __future__ import annotations

import math
import os
import shutil
from io import StringIO
from pathlib import Path
from typing import Iterator, Mapping, Sequence

import numpy as np
from ruamel.yaml import YAML

from laser_calib.errors import InputError
from laser_calib.samples_file import Samples

from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.metadata import dump_qos_v9
from rosbags.typesys import Stores, get_typestore, get_types_from_msg
from rosbags.typesys.store import Typestore

INTERFACES = "laser_calib_interfaces"
SAMPLES_TOPIC = "/samples"
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
    try:
        from ament_index_python.packages import get_package_share_directory
        path = Path(get_package_share_directory(INTERFACES)) / "msg"
        if path.is_dir():
            return path
    except Exception:  # no ament index (ROS-free use): fall back to the sources
        pass
    path = Path(__file__).resolve().parents[2] / INTERFACES / "msg"
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


def _yaml() -> YAML:
    yaml = YAML(typ="safe")
    yaml.default_flow_style = False
    return yaml


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as handle:
        os.fsync(handle.fileno())


class SegmentedBagWriter:
    """rosbag2 MCAP bag written in closed segments (see the module docstring).

    topics: topic -> (message type 'pkg/msg/Type', offered QoS list). Messages
    are raw CDR bytes with a timestamp in ns. ``work_dir`` holds the open
    segment; put it on the same file system as ``bag_dir``. An existing bag in
    ``bag_dir`` is continued (resume).
    """

    def __init__(self, bag_dir: str | Path, work_dir: str | Path, topics: Mapping[str, tuple[str, Sequence[Qos]]],
                 store: Typestore | None = None, custom_data: Mapping[str, str] | None = None,
                 max_segment_seconds: float = 10.0):
        self.bag_dir = Path(bag_dir)
        self.work_dir = Path(work_dir)
        self.name = self.bag_dir.name
        self.store = store or typestore()
        self.topics = dict(topics)
        self.custom_data = dict(custom_data or {})
        self.max_segment_ns = int(max_segment_seconds * 1e9)
        self.files: list[dict] = []
        self.topic_counts: dict[str, int] = {}
        self.topic_entries: dict[str, dict] = {}
        self.recovered: list[str] = []
        self.discarded: list[str] = []
        self._writer: Writer | None = None
        self._connections: dict[str, object] = {}
        self._segment = 0
        self._seg_count = 0
        self._seg_counts: dict[str, int] = {}
        self._seg_start = 2**63 - 1
        self._seg_end = 0
        self._seg_opened_ns = 0
        self.bag_dir.mkdir(parents=True, exist_ok=True)
        self.work_dir.mkdir(parents=True, exist_ok=True)
        self._load_existing()

    # ---- resume -------------------------------------------------------------
    def _load_existing(self) -> None:
        meta_path = self.bag_dir / METADATA
        if meta_path.exists():
            info = _yaml().load(meta_path.read_text())["rosbag2_bagfile_information"]
            self.files = list(info.get("files") or [])
            self.custom_data = {**(info.get("custom_data") or {}), **self.custom_data}
            for entry in info.get("topics_with_message_count") or []:
                name = entry["topic_metadata"]["name"]
                self.topic_entries[name] = entry["topic_metadata"]
                self.topic_counts[name] = int(entry["message_count"])
        listed = {f["path"] for f in self.files}
        # A segment moved into the bag just before a crash, not yet listed: adopt it.
        for path in sorted(self.bag_dir.glob("*.mcap"), key=_segment_index):
            if path.name not in listed:
                if self._adopt(path):
                    self.recovered.append(path.name)
                else:
                    self.discarded.append(path.name)
        # The open segment of a killed recorder: its data were still in memory.
        for stale in self.work_dir.glob(f"{self.name}_*"):
            self.discarded.append(str(stale))
            shutil.rmtree(stale, ignore_errors=True)
        indices = [_segment_index(Path(f["path"])) for f in self.files] + [-1]
        self._segment = max(indices) + 1
        if self.recovered:
            self._write_metadata()

    def _adopt(self, path: Path) -> bool:
        from rosbags.rosbag2.storage_mcap import McapReader
        try:
            reader = McapReader(path)
            reader.open()
        except Exception:  # unreadable remains of a crash: keep aside, never delete data
            aside = self.bag_dir.parent / (".unreadable-" + path.name)
            os.replace(path, aside)
            return False
        try:
            counts: dict[str, int] = {}
            start, end = 2**63 - 1, 0
            for connection, stamp, _ in reader.messages(reader.connections):
                counts[connection.topic] = counts.get(connection.topic, 0) + 1
                start, end = min(start, stamp), max(end, stamp)
        finally:
            reader.close()
        total = sum(counts.values())
        self.files.append({"path": path.name, "starting_time": {"nanoseconds_since_epoch": start if total else 0},
                           "duration": {"nanoseconds": max(0, end - start) if total else 0},
                           "message_count": total})
        for topic, count in counts.items():
            self._ensure_entry(topic)
            self.topic_counts[topic] = self.topic_counts.get(topic, 0) + count
        return True

    # ---- writing ------------------------------------------------------------
    def _ensure_entry(self, topic: str) -> None:
        if topic in self.topic_entries:
            return
        msgtype, profiles = self.topics[topic]
        self.topic_entries[topic] = {
            "name": topic, "type": msgtype, "serialization_format": "cdr",
            "offered_qos_profiles": dump_qos_v9(list(profiles)),
            "type_description_hash": self.store.hash_rihs01(msgtype),
        }
        self.topic_counts.setdefault(topic, 0)

    def _open_segment(self, now_ns: int) -> None:
        name = f"{self.name}_{self._segment}"
        self._writer = Writer(self.work_dir / name, version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._connections = {}
        for topic, (msgtype, profiles) in self.topics.items():
            self._connections[topic] = self._writer.add_connection(
                topic, msgtype, typestore=self.store, offered_qos_profiles=list(profiles))
        self._seg_count = 0
        self._seg_counts = {}
        self._seg_start, self._seg_end = 2**63 - 1, 0
        self._seg_opened_ns = now_ns

    def write(self, topic: str, timestamp_ns: int, data: bytes | memoryview) -> None:
        if topic not in self.topics:
            raise KeyError(f"topic {topic} is not recorded")
        if self._writer is None:
            self._open_segment(timestamp_ns)
        elif self.max_segment_ns and timestamp_ns - self._seg_opened_ns > self.max_segment_ns:
            self.rotate()
            self._open_segment(timestamp_ns)
        self._writer.write(self._connections[topic], int(timestamp_ns), bytes(data))
        self._seg_count += 1
        self._seg_counts[topic] = self._seg_counts.get(topic, 0) + 1
        self._seg_start = min(self._seg_start, timestamp_ns)
        self._seg_end = max(self._seg_end, timestamp_ns)

    def rotate(self) -> None:
        """Close the open segment (if it holds messages) and make it part of the bag."""
        writer, self._writer = self._writer, None
        if writer is None:
            return
        seg_dir = writer.path
        if self._seg_count == 0:
            writer.abort()
            shutil.rmtree(seg_dir, ignore_errors=True)
            return
        writer.close()
        source = seg_dir / f"{seg_dir.name}.mcap"
        _fsync_file(source)
        target = self.bag_dir / source.name
        os.replace(source, target)
        _fsync_dir(self.bag_dir)
        shutil.rmtree(seg_dir, ignore_errors=True)
        self.files.append({"path": target.name, "starting_time": {"nanoseconds_since_epoch": self._seg_start},
                           "duration": {"nanoseconds": self._seg_end - self._seg_start},
                           "message_count": self._seg_count})
        for topic, count in self._seg_counts.items():
            self._ensure_entry(topic)
            self.topic_counts[topic] += count
        self._segment += 1
        self._write_metadata()

    def close(self) -> None:
        self.rotate()
        if not (self.bag_dir / METADATA).exists():
            self._write_metadata()
        shutil.rmtree(self.work_dir, ignore_errors=True)

    def _write_metadata(self) -> None:
        files = sorted(self.files, key=lambda f: _segment_index(Path(f["path"])))
        counted = [f for f in files if f["message_count"]]
        start = min((f["starting_time"]["nanoseconds_since_epoch"] for f in counted), default=0)
        end = max((f["starting_time"]["nanoseconds_since_epoch"] + f["duration"]["nanoseconds"] for f in counted),
                  default=0)
        info = {
            "version": 9,
            "storage_identifier": "mcap",
            "relative_file_paths": [f["path"] for f in files],
            "duration": {"nanoseconds": max(0, end - start)},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": sum(f["message_count"] for f in files),
            "topics_with_message_count": [
                {"topic_metadata": self.topic_entries[t], "message_count": self.topic_counts[t]}
                for t in self.topic_entries
            ],
            "compression_format": "",
            "compression_mode": "",
            "files": files,
            "custom_data": self.custom_data or None,
            "ros_distro": "rosbags",
        }
        text = StringIO()
        _yaml().dump({"rosbag2_bagfile_information": info}, text)
        tmp = self.bag_dir / (METADATA + ".tmp")
        with open(tmp, "w", encoding="utf8") as handle:
            handle.write(text.getvalue())
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, self.bag_dir / METADATA)
        _fsync_dir(self.bag_dir)


def _segment_index(path: Path) -> int:
    stem = path.name.removesuffix(".mcap")
    tail = stem.rsplit("_", 1)[-1]
    return int(tail) if tail.isdigit() else 0


# ---- reading (ROS-free) ------------------------------------------------------

def stamp_seconds(sec: int, nanosec: int) -> float:
    """A header stamp as float seconds: the one conversion used for every samples stamp."""
    return float(sec) + float(nanosec) * 1e-9


def _reader(path: Path):
    from rosbags.highlevel import AnyReader
    if not path.exists():
        raise InputError(str(path), "no such bag")
    if path.is_dir() and not (path / METADATA).exists():
        raise InputError(str(path), f"not a rosbag2 bag (no {METADATA})")
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY))
        reader.open()
    except InputError:
        raise
    except Exception as exc:  # rosbags raises several types; the user needs one line
        raise InputError(str(path), f"cannot read bag ({exc})") from None
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


def read_samples(path: str | Path, topic: str = SAMPLES_TOPIC) -> Samples:
    """The measured samples of a session bag (its /samples messages, in order), as the core's Samples."""
    path = Path(path)
    reader = _reader(path)
    rows = []
    try:
        connections = [c for c in reader.connections if c.topic == topic]
        if not connections:
            raise InputError(str(path), f"no topic {topic} in the bag (not a calibration session bag?)")
        for index, (connection, _, raw) in enumerate(reader.messages(connections=connections)):
            msg = reader.deserialize(raw, connection.msgtype)
            rows.append(sample_row_from_msg(msg, f"{path}: {topic} message {index + 1}"))
    finally:
        reader.close()
    if not rows:
        raise InputError(str(path), f"topic {topic} holds no samples")
    return samples_from_rows(rows, str(path))


def sample_row_from_msg(msg, where: str) -> tuple[int, float, np.ndarray, np.ndarray]:
    """(pose, stamp, q (N,), spots (2,2) NaN where unseen) from a Sample message
    (rclpy or rosbags object: same field names)."""
    q = np.array(msg.joint_positions, dtype=float)
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
