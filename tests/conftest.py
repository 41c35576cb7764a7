"""Shared fixtures. Bundles built during the tests go to a per-session cache folder."""
from __future__ import annotations

import os
import tempfile

# Before histojax is imported anywhere: keep the user's ~/.cache untouched and start clean.
os.environ.setdefault("HISTOJAX_CACHE", tempfile.mkdtemp(prefix="histojax-test-cache-"))

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def sample_envs():
    """``{env_id: (env, params)}`` for the three built-in scenarios on the embedded slide."""
    import histojax

    return {env_id: histojax.make(env_id) for env_id in
            ("HistoJAX-Easy-v0", "HistoJAX-Medium-v0", "HistoJAX-Hard-v0")}
