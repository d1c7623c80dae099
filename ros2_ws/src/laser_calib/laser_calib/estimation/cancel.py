"""Stopping a long estimate or diagnosis at its caller's request.

The caller (the Calibrate action) runs the work inside ``cancellable(requested)``;
every evaluation of the model passes problem.pose_blocks, which calls check(), and
check() raises Cancelled once ``requested()`` is true. The fits need no hook of their
own, and a cancel takes effect within one evaluation (milliseconds), not at the end
of a stage that may run for minutes.

The request lives in a context variable: the service's estimates, run by other
threads of the same node, never see another goal's cancel.
"""

from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from typing import Callable, Iterator

_requested: ContextVar[Callable[[], bool] | None] = ContextVar("cancel_requested", default=None)


class Cancelled(Exception):
    """The caller asked the work to stop; what it was computing is given up."""


@contextmanager
def cancellable(requested: Callable[[], bool]) -> Iterator[None]:
    """Work in this block stops with Cancelled at its next model evaluation once requested() is true."""
    token = _requested.set(requested)
    try:
        yield
    finally:
        _requested.reset(token)


def check() -> None:
    """Raise Cancelled if the enclosing cancellable() block's caller asked to stop."""
    requested = _requested.get()
    if requested is not None and requested():
        raise Cancelled
