"""Worker processes that die with their parent (``histojax dataset --jobs N``).

A ``ProcessPoolExecutor`` worker blocks on its task queue forever when the parent is killed (``SIGKILL``,
``SIGTERM``, the out-of-memory killer): a pool of slide builders would stay alive, each holding hundreds
of MiB. :func:`die_with_parent` (the pool's ``initializer``) makes the kernel kill the worker when its
parent dies (Linux ``prctl(PR_SET_PDEATHSIG, SIGKILL)``) and, on every system, starts a watchdog thread
that exits the worker within half a second of its parent's death. :func:`stop_workers_on_sigterm`
makes ``SIGTERM`` of the parent terminate the workers before it exits (status 143).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time

PR_SET_PDEATHSIG = 1
WATCH_SECONDS = 0.5


def _parent_gone(parent_pid: int) -> bool:
    return os.getppid() != parent_pid


def die_with_parent(parent_pid: int) -> None:
    """Pool ``initializer``: end this worker process when the process ``parent_pid`` (its parent) dies —
    at once on Linux (``PR_SET_PDEATHSIG``), else within :data:`WATCH_SECONDS` (a daemon watchdog thread
    comparing ``os.getppid()``)."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):
            pass
    if _parent_gone(parent_pid):  # the parent died before the line above: nobody would kill us
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(WATCH_SECONDS)
            if _parent_gone(parent_pid):
                os._exit(1)

    threading.Thread(target=watch, name="histojax-parent-watchdog", daemon=True).start()


@contextlib.contextmanager
def stop_workers_on_sigterm(pool):
    """Within the block, ``SIGTERM`` of this (main-thread) process terminates the worker processes of the
    ``ProcessPoolExecutor`` ``pool``, cancels what is queued and exits with status 143; the previous handler
    is restored after the block. Elsewhere than the main thread the block runs unchanged."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            with contextlib.suppress(Exception):
                proc.terminate()
        with contextlib.suppress(Exception):
            pool.shutdown(wait=False, cancel_futures=True)
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


__all__ = ["die_with_parent", "stop_workers_on_sigterm"]
