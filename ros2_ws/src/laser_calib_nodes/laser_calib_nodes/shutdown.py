"""A bound on the time from the stop signal to the exit of a node's process.

A DDS middleware can hang while its participant is torn down (eProsima/Fast-DDS#235,
ros2/rcl#886), and a stop signal that lands inside a library's critical section can leave
a lock held. Either way Ctrl-C must still end the process: GRACE seconds after the first
stop signal (or after the node's own cleanup, when it ends by itself) the watchdog says so
on stderr and ends the process with os._exit. The node's own cleanup (close(): files
flushed, the bag closed) is never cut: the watchdog waits while it runs. When it had
finished, nothing measured is lost and the exit code is the node's; when it had not begun,
every thread's stack goes to stderr and the code is 1.

The watchdog is a Python thread: it runs only when it can take the GIL. A teardown that
hangs inside a C call that holds it (the node's destruction in rclpy's extension: a session
test's camera and detector, stopped together, were aborted after 30 s there) stops every
Python thread with it. So once the cleanup is done two native backstops are armed as well:
faulthandler's own thread writes every thread's stack to stderr, and a POSIX timer whose
expiry runs _exit(code) on a thread of its own (timer_create with SIGEV_THREAD) ends the
process with the node's code; neither needs the GIL.

A Ctrl-C's KeyboardInterrupt is raised where the main thread happens to be when its Python
handler runs; interruptible() tells whether that place can take it (see there). Where it cannot,
the spin ends because rclpy's signal thread shuts the context; that thread wakes the executors
first and shuts the contexts after, and the shutdown wakes nobody, so the watchdog's first step is
to wake the executor once the context is shut (see _wake_once_shut).
"""

from __future__ import annotations

import ctypes
import faulthandler
import os
import signal
import sys
import threading
import time

GRACE = 15.0  # s: ten times what the nodes need to exit on two loaded cores
BACKSTOP = 1.0  # s after GRACE: the native backstops, when the watchdog thread could not run
WAKE_POLL = 0.005  # s between two looks at the context after a stop: rclpy shuts it microseconds after the wake
PR_SET_PDEATHSIG = 1  # linux/prctl.h


OWN_PACKAGES = ("laser_calib", "laser_calib_nodes")
# The writers of what was measured: stopped between two of their steps they lose it. A bag segment
# interrupted half-rotated kept its name, every later write was refused ("bag_13 exists already")
# and the messages taken at the stop were lost, with exit 0; a message the executor had taken was
# lost when the recorder's callback was interrupted before the bag had it.
WRITERS = ("laser_calib_nodes.recorder", "laser_calib.io.bag_writer", "laser_calib.session.durable")


def interruptible(frame) -> bool:
    """Whether a KeyboardInterrupt raised at ``frame`` (where a stop signal's Python handler runs:
    any line of the main thread) lands where it can be taken: the nodes' own code and what it calls.
    Not inside rclpy: its executor builds a Task for each callback, and one interrupted in
    Future.__init__ lacks the attributes its __del__ reads ("Exception ignored in: <function
    Future.__del__> ... AttributeError: 'Task' object has no attribute '_exception'", seen in
    camera_sim's log when a launch shut down on two loaded cores). Nor inside any __del__: an
    exception there is printed and dropped. Nor inside the WRITERS. In these the stop is left to
    rclpy's signal handler, which has shut the context, and so ends the spin
    (ExternalShutdownException)."""
    while frame is not None:
        if frame.f_code.co_name == "__del__":
            return False
        module = str(frame.f_globals.get("__name__", ""))
        package = module.partition(".")[0]
        if package == "rclpy" or module in WRITERS:
            return False
        if package in OWN_PACKAGES:
            return True
        frame = frame.f_back  # the standard library, numpy, message classes: decided by their caller
    return True


class _Sigevent(ctypes.Structure):
    """struct sigevent (Linux, 64 bytes) for SIGEV_THREAD: sigev_value is the argument the
    notify function is called with."""

    _fields_ = [("value", ctypes.c_void_p), ("signo", ctypes.c_int), ("notify", ctypes.c_int),
                ("function", ctypes.c_void_p), ("attributes", ctypes.c_void_p), ("pad", ctypes.c_int * 8)]


class _Timespec(ctypes.Structure):
    _fields_ = [("seconds", ctypes.c_long), ("nanoseconds", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("interval", _Timespec), ("value", _Timespec)]


SIGEV_THREAD = 2
CLOCK_MONOTONIC = 1


def exit_later(seconds: float, code: int) -> None:
    """_exit(code) after ``seconds`` on a thread the C library starts (no GIL needed); nothing
    where the C library has no POSIX timers (the Python watchdog alone then bounds the exit)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        event = _Sigevent(value=code, notify=SIGEV_THREAD, function=ctypes.cast(libc._exit, ctypes.c_void_p).value)
        timer = ctypes.c_void_p()
        if libc.timer_create(CLOCK_MONOTONIC, ctypes.byref(event), ctypes.byref(timer)) == 0:
            whole = int(seconds)
            spec = _Itimerspec(value=_Timespec(whole, int((seconds - whole) * 1e9)))
            libc.timer_settime(timer, 0, ctypes.byref(spec), None)
    except (OSError, AttributeError):
        pass  # no POSIX timers here


class StopFlag:
    """Whether a stop signal (SIGINT, SIGTERM) came: what a signal handler notes. Not a
    threading.Event: a Python handler runs in the main thread between two bytecodes, inside
    itself too when signals come microseconds apart (GNU timeout's SIGTERM to the process
    group, launch's own, the parent's death: three at once), and Event.set holds a lock the
    nested call then waits on for ever (a camera_sim left on the graph after its launch had
    exited, deaf to SIGINT, its watchdog never armed). An attribute is read and set without a
    lock, and CPython runs no handler between the two (it looks for them at calls and jumps)."""

    def __init__(self):
        self.stopped = False

    def note(self, *_signal) -> bool:
        """Note a stop (also as a handler itself: signal.signal(SIGINT, flag.note)); whether it
        was the first."""
        first = not self.stopped
        self.stopped = True
        return first


class ExitWatchdog:
    def __init__(self, name: str, grace: float = GRACE):
        self.name, self.grace = name, grace
        self.code = 0
        self.closing = threading.Event()
        self.closed = threading.Event()
        self._armed = False
        self._executor = None  # the spinning one, woken once the stop has shut its context
        self._executor_lock = threading.Lock()  # held while it is woken, so that it is not shut down then

    def watch_executor(self, executor) -> None:
        """The executor the node spins in (None once its cleanup shuts it down)."""
        with self._executor_lock:
            self._executor = executor

    def arm(self) -> None:
        """Start the countdown (once; later calls keep the first deadline). Called from a
        signal handler, also inside itself (StopFlag): the flag is claimed before any call."""
        if self._armed:
            return
        self._armed = True
        threading.Thread(target=self._watch, name="exit watchdog", daemon=True).start()

    def cleanup_started(self) -> None:
        self.closing.set()

    def cleanup_done(self, code: int) -> None:
        self.code = code
        self.closed.set()
        self.arm()
        faulthandler.dump_traceback_later(self.grace + BACKSTOP, file=sys.stderr)
        exit_later(self.grace + BACKSTOP + 0.1, code)  # after the stacks are written

    def _wake_once_shut(self, deadline: float) -> None:
        """Wake the executor once the stop has shut its context. rclpy's signal thread triggers the
        executors' guard conditions and only then shuts the contexts (rcl_shutdown, which wakes no
        wait set): an executor that woke between the two found its context still valid and waited
        again, with nothing left to wake it (an idle spot_detector, then an estimator, at the end of
        CI's launched sessions, ended by this watchdog after 15 s; every time with rcl_shutdown
        delayed 0.3 s). rclpy's own Context.shutdown wakes them; the signal's path does not."""
        executor = self._executor
        if executor is None:
            return
        while executor.context.ok() and not self.closing.is_set() and time.monotonic() < deadline:
            time.sleep(WAKE_POLL)
        with self._executor_lock:
            if self._executor is not None and not self.closing.is_set():
                self._executor.wake()

    def _watch(self) -> None:
        deadline = time.monotonic() + self.grace
        self._wake_once_shut(deadline)
        if not self.closed.wait(max(0.0, deadline - time.monotonic())):
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


def die_with_parent() -> None:
    """Ask the kernel to SIGTERM this process when its parent ends (even by SIGKILL), so
    that no node runs on without the launcher that owns the session. Linux only."""
    parent = os.getppid()
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the parent ended before prctl took effect
        os.kill(os.getpid(), signal.SIGTERM)
