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


@pytest.fixture(scope="session")
def small_slides(tmp_path_factory):
    """Bundle paths of 8 small semi-synthetic slides (320 × 256 px, tile 32, Easy levels; a few
    seconds to build), for the sharding and rotation tests."""
    from data_tools.synth import make_dataset

    root = tmp_path_factory.mktemp("small-slides")
    ds = make_dataset(root, n_slides=8, size=(320, 256), seed=0, tile_size=32, level_sets=(3,), progress=False,
                      previews=False)
    return [str(root / s["bundle"]) for s in ds["slides"]]
