"""A block that must not hang: :func:`at_most` fails it with :class:`Blocked` (SIGALRM) instead, for the tests that
hand a reader a FIFO or a lock held elsewhere."""

from __future__ import annotations

import contextlib
import signal


class Blocked(Exception):
    """Raised in a block that blocked too long (not an ``OSError``: no ``except OSError`` swallows it)."""


@contextlib.contextmanager
def at_most(seconds: int):
    """Fail (:class:`Blocked`) instead of hanging when the block blocks longer than ``seconds``."""

    def _raise(*_):
        raise Blocked(f"blocked for more than {seconds} s")

    old = signal.signal(signal.SIGALRM, _raise)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
