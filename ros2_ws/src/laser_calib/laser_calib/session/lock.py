"""One owner per session folder (ROS-free): an advisory lock held while a session runs.

The lock is flock(2) on ``<folder>/.lock``, which also holds the owner's PID. The
kernel drops the lock when its process dies, however it dies (SIGKILL included),
so a crashed session never leaves a stale lock: the next start finds the folder
free and resumes it. A second session on a live folder is refused with one line
naming the owner's PID.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from laser_calib.io.errors import InputError

LOCK_FILE = ".lock"


class SessionLock:
    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        self.path = self.folder / LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock, or InputError '<folder>: in use by the session of PID <pid>'."""
        self.folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise InputError(str(self.folder), f"in use by the session of PID {owner} (one session per folder: "
                                               "stop it first, or choose another output_dir)") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        os.fsync(fd)
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock; the file stays (unlinking would race a new owner)
            self._fd = None
