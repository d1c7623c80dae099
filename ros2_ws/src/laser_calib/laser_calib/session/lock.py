"""One owner per session folder (ROS-free): an advisory lock held while a session runs.

The lock is flock(2) on ``<folder>/.lock``, which also holds the owner's PID. The
kernel drops the lock when its process dies, however it dies (SIGKILL included),
so a crashed session never leaves a stale lock: the next start finds the folder
free and resumes it. A second session on a live folder is refused with one line
naming the owner's PID.

The starters of a session (scripts/run-session, the launch files:
laser_calib_nodes.graph.take_folder) take the lock before any node starts and
hold it for the session; the sequencer they start then finds it held by its
parent, which is its own session's: acquire() lets it through without holding
it. A sequencer started on its own takes it itself. The descriptor is inherited
by no child (Python's descriptors are not inheritable).
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from laser_calib.io.errors import InputError

LOCK_FILE = ".lock"


class SessionBusy(InputError):
    """The folder is the live session of another process, ``owner`` (its PID; None if unreadable)."""

    def __init__(self, folder: Path, owner: int | None):
        super().__init__(str(folder), f"in use by the session of PID {owner if owner else 'unknown'} (one session "
                                      "per folder: stop it first, or choose another output_dir)")
        self.owner = owner


class SessionLock:
    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock (creating the folder), or SessionBusy '<folder>: in use by the session of
        PID <pid>'. When the holder is this process's parent (the launcher of this session) the
        folder is this session's: returns without holding the lock."""
        try:  # an output_dir under a file, on a read-only or full disk: one line, not a traceback
            self.folder.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise InputError(str(self.folder), f"cannot create the session folder or its {LOCK_FILE}: "
                                               f"{exc.strerror} ({exc.filename})") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            text = os.pread(fd, 32, 0).decode(errors="replace").strip()
            os.close(fd)
            owner = int(text) if text.isdigit() else None
            if owner is not None and owner == os.getppid():
                return
            raise SessionBusy(self.folder, owner) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        os.fsync(fd)
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock; the file stays (unlinking would race a new owner)
            self._fd = None
