"""A bound on the time from the stop signal to the exit of a node's process.

A DDS middleware can hang while its participant is torn down (eProsima/Fast-DDS#235,
ros2/rcl#886), and a stop signal that lands inside a library's critical section can leave
a lock held. Either way Ctrl-C must still end the process: GRACE seconds after the first
stop signal (or after the node's own cleanup, when it ends by itself) the watchdog says so
on stderr and ends the process with os._exit. The node's own cleanup (close(): files
flushed, the bag closed) is never cut: the watchdog waits while it runs. When it had
finished, nothing measured is lost and the exit code is the node's; when it had not begun,
every thread's stack goes to stderr and the code is 1.
"""

from __future__ import annotations

import faulthandler
import os
import sys
import threading
import time

GRACE = 15.0  # s: ten times what the nodes need to exit on two loaded cores


class ExitWatchdog:
    def __init__(self, name: str, grace: float = GRACE):
        self.name, self.grace = name, grace
        self.code = 0
        self.closing = threading.Event()
        self.closed = threading.Event()
        self._thread: threading.Thread | None = None

    def arm(self) -> None:
        """Start the countdown (once; later calls keep the first deadline)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._watch, name="exit watchdog", daemon=True)
            self._thread.start()

    def cleanup_started(self) -> None:
        self.closing.set()

    def cleanup_done(self, code: int) -> None:
        self.code = code
        self.closed.set()
        self.arm()

    def _watch(self) -> None:
        if not self.closed.wait(self.grace):
            if not self.closing.is_set():
                print(f"error: {self.name} did not exit within {self.grace:g} s of the stop signal; its threads:",
                      file=sys.stderr, flush=True)
                faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
                os._exit(1)
            self.closed.wait()  # saving what was measured: never cut
        # the middleware's teardown has its own grace from the end of the cleanup
        time.sleep(self.grace)
        print(f"warning: {self.name}: the middleware's teardown did not finish within {self.grace:g} s; "
              "exiting without it (everything was saved)", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(self.code)
