"""Progress of a long step on the console, by the terminal conventions.

On a terminal: a tqdm bar with the count, rate and time left, shown only once
the step has run for ``delay`` seconds (short runs stay quiet). Elsewhere (a
log file, a pipe, a service): one plain line every ``interval`` seconds, no
carriage returns. The core calls a callback ``progress(done, total, note)``
(estimation.lm.ProgressCallback); this module is what the command line passes.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

from tqdm import tqdm


class Progress:
    """Callable progress(done, total, note) for one step; close() when it ends
    (or use it as a context manager). header: a line saying what the step does,
    written at its first call (the work has begun), or when the context ends
    without an error if no call came: input the step refuses before any work
    (too few poses, a name it does not know) gives its error line alone."""

    def __init__(self, desc: str, unit: str = "it", stream: TextIO | None = None,
                 interval: float = 10.0, delay: float = 2.0, header: str | None = None):
        self.desc, self.unit = desc, unit
        self.header = header
        self.stream = sys.stderr if stream is None else stream
        self.interval, self.delay = interval, delay
        self.terminal = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._bar: tqdm | None = None
        self._first: float | None = None  # the step's first call
        self._start: float | None = None  # the run's first call: the rate counts from there
        self._last_line: float | None = None  # when the last plain line was written
        self._done = 0

    def __call__(self, done: int, total: int | None = None, note: str = "") -> None:
        self._say_header()
        # a count that falls back is the next run of the step (another fit): rate and time from there
        restart = done < self._done
        self._done = done
        if self.terminal:
            if self._bar is None:
                self._bar = tqdm(total=total, desc=self.desc, unit=self.unit, file=self.stream,
                                 delay=self.delay, dynamic_ncols=True, leave=True)
            if restart:
                self._bar.reset(total)
            self._bar.total = total
            if note:
                self._bar.set_postfix_str(note, refresh=False)
            self._bar.update(done - self._bar.n)  # update, not refresh: it keeps tqdm's delay and rate
            return
        now = time.monotonic()
        if self._first is None:
            self._first = now
        if self._start is None or restart:
            self._start = now
        # The clock of the lines is the whole step's, not the run's: a step of many
        # short runs (the diagnosis's fits, each restarting the count) still gets a
        # line every interval.
        since, wait = (self._first, self.delay) if self._last_line is None else (self._last_line, self.interval)
        if now - since >= wait:
            self._last_line = now
            self.stream.write(self.line(done, total, now - self._start, note) + "\n")
            self.stream.flush()

    def line(self, done: int, total: int | None, elapsed: float, note: str = "") -> str:
        """'desc: done/total unit, rate/s, elapsed, ~left' (the plain form)."""
        rate = done / elapsed if elapsed > 0 else 0.0
        text = f"{self.desc}: {done}" + (f"/{total}" if total else "") + f" {self.unit}, {rate:.3g} {self.unit}/s, "
        text += f"{elapsed:.0f} s elapsed"
        if total and rate > 0:
            text += f", ~{max(total - done, 0) / rate:.0f} s left"
        return text + (f"; {note}" if note else "")

    def _say_header(self) -> None:
        if self.header is not None:
            self.stream.write(self.header + "\n")
            self.stream.flush()
            self.header = None

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __deepcopy__(self, memo) -> "Progress":
        # A handle on the console, not data: options holding it (dataclasses.asdict) share it.
        return self

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self._say_header()
        self.close()
