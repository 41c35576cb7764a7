"""The peak resident memory of one piece of work in this process (a bundle build), not the process's lifetime peak.

``resource.getrusage(...).ru_maxrss`` is the highest resident set the process ever reached: in a long process (a
pytest worker, a notebook, a dataset job that built other slides first) it reports earlier work, not the build's.
:class:`PeakRSS` measures from its start instead:

* Linux: writes ``5`` to ``/proc/self/clear_refs`` (reset the peak resident set to the current one, Linux ≥ 4.0),
  then reads ``VmHWM`` from ``/proc/self/status``: exact, every page counted (``method`` ``"VmHWM"``);
* where that file cannot be written: a thread samples the resident set (``/proc/self/statm``, else ``ru_maxrss``)
  every 20 ms (``method`` ``"sampled"``; a spike shorter than that may be missed);
* neither: the lifetime peak, named as such (``method`` ``"ru_maxrss (process lifetime)"``).

Resetting ``VmHWM`` also resets what ``ru_maxrss`` reports afterwards in this process. Bytes throughout.
"""

from __future__ import annotations

import os
import resource
import sys
import threading

__all__ = ["PeakRSS"]

_SAMPLE_S = 0.02


def _hwm_bytes() -> int | None:
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm", encoding="ascii") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return _lifetime_bytes()


def _lifetime_bytes() -> int:
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)  # macOS reports bytes, Linux KiB


class PeakRSS:
    """Peak resident memory from :meth:`start` to :meth:`stop` (bytes), by the best means the system offers (see the
    module doc; ``method`` names it). Use ``with PeakRSS() as peak: ...; peak.bytes``, or ``start()`` / ``stop()``."""

    def __init__(self):
        self.method: str | None = None
        self.bytes: int | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sampled = 0

    def start(self) -> "PeakRSS":
        """Reset the peak (or start sampling); returns self."""
        try:
            with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
                f.write("5")
            if _hwm_bytes() is not None:
                self.method = "VmHWM"
                return self
        except OSError:
            pass
        if os.path.exists("/proc/self/statm"):
            self.method = "sampled"
            self._sampled = _rss_bytes()
            self._thread = threading.Thread(target=self._sample, name="peak-rss", daemon=True)
            self._thread.start()
        else:
            self.method = "ru_maxrss (process lifetime)"
        return self

    def _sample(self) -> None:
        while not self._stop.wait(_SAMPLE_S):
            self._sampled = max(self._sampled, _rss_bytes())

    def stop(self) -> int:
        """The peak since :meth:`start`, in bytes (also kept as ``bytes``); a second call returns the first's."""
        if self.bytes is not None:
            return self.bytes
        if self.method == "VmHWM":
            self.bytes = _hwm_bytes() or _lifetime_bytes()
        elif self.method == "sampled":
            self._stop.set()
            self._thread.join()
            self.bytes = max(self._sampled, _rss_bytes())
        else:
            self.bytes = _lifetime_bytes()
        return self.bytes

    def __enter__(self) -> "PeakRSS":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
