"""Session bags: a crash-safe rosbag2 MCAP writer (ROS-free, through rosbags).

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

"""

from __future__ import annotations

import os
import shutil
from io import StringIO
from pathlib import Path
from typing import Mapping, Sequence

from rosbags.interfaces import Qos
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.metadata import dump_qos_v9
from ruamel.yaml import YAML

from laser_calib.io.bag import METADATA, segment_index, typestore


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
        self.missing: list[str] = []  # listed in metadata.yaml, gone from the folder: struck from the list
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
        # A listed segment gone from the folder (deleted by hand, lost with a disk): rosbag2 and rosbags
        # refuse the whole bag for it ("Some database files are missing"), so the list and the counts
        # are made those of the segments there; the poses it held come back from samples.csv on resume.
        self.missing = [f["path"] for f in self.files if not (self.bag_dir / f["path"]).exists()]
        if self.missing:
            self.files = [f for f in self.files if f["path"] not in self.missing]
            self.topic_counts = dict.fromkeys(self.topic_counts, 0)
            for entry in self.files:
                try:
                    counts = self._counts(self.bag_dir / entry["path"])[0]
                except Exception:  # damaged as well: its messages are not counted (readers skip or refuse it)
                    counts = {}
                for topic, count in counts.items():
                    self.topic_counts[topic] = self.topic_counts.get(topic, 0) + count
        listed = {f["path"] for f in self.files}
        # A segment moved into the bag just before a crash, not yet listed: adopt it.
        for path in sorted(self.bag_dir.glob("*.mcap"), key=segment_index):
            if path.name not in listed:
                if self._adopt(path):
                    self.recovered.append(path.name)
                else:
                    self.discarded.append(path.name)
        # The open segment of a killed recorder: its data were still in memory.
        for stale in self.work_dir.glob(f"{self.name}_*"):
            self.discarded.append(str(stale))
            shutil.rmtree(stale, ignore_errors=True)
        indices = [segment_index(Path(f["path"])) for f in self.files] + [-1]
        self._segment = max(indices) + 1
        if self.recovered or self.missing:
            self._write_metadata()

    @staticmethod
    def _counts(path: Path) -> tuple[dict[str, int], int, int]:
        """Messages per topic of one segment file, its first and last stamp (ns); what McapReader
        raises for a file it cannot read."""
        from rosbags.rosbag2.storage_mcap import McapReader
        reader = McapReader(path)
        reader.open()
        try:
            counts: dict[str, int] = {}
            start, end = 2**63 - 1, 0
            for connection, stamp, _ in reader.messages(reader.connections):
                counts[connection.topic] = counts.get(connection.topic, 0) + 1
                start, end = min(start, stamp), max(end, stamp)
        finally:
            reader.close()
        return counts, start, end

    def _adopt(self, path: Path) -> bool:
        try:
            counts, start, end = self._counts(path)
        except Exception:  # unreadable remains of a crash: keep aside, never delete data
            aside = self.bag_dir.parent / (".unreadable-" + path.name)
            os.replace(path, aside)
            return False
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
        files = sorted(self.files, key=lambda f: segment_index(Path(f["path"])))
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


