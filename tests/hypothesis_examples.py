"""How many examples a hypothesis test draws: a few in ``make test`` (the default run stays under 10 minutes on
2 CPU cores), the full count under ``make test-all``, which sets ``HISTOJAX_TEST_ALL=1``."""

from __future__ import annotations

import os

FULL = os.environ.get("HISTOJAX_TEST_ALL", "") not in ("", "0")


def examples(full: int, quick: int) -> int:
    """``max_examples`` for a hypothesis test: ``full`` under ``make test-all``, else ``min(quick, full)``."""
    return full if FULL else min(quick, full)
