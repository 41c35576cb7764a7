"""Shared fixtures. Bundles built during the tests go to a per-session cache folder.

The tests live in folders by subject (``env/``, ``reading/``, ``data_pipeline/``, ``training/``, ``adapters/``,
``hostile_inputs/``, ``project/``); the builders beside this file (``slide_helpers``, ``learned_fixture``, …) and the
builders one test module lends another (``test_head.make_dataset``, ``test_budget_curve.planted_head``, …) are
imported by module name, so this folder and every subject folder are on ``sys.path`` before any test module loads.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

_HERE = Path(__file__).resolve().parent
for _folder in [_HERE, *sorted(p for p in _HERE.iterdir() if p.is_dir() and any(p.glob("test_*.py")))]:
    if str(_folder) not in sys.path:
        sys.path.insert(0, str(_folder))

# Before histojax is imported anywhere: keep the user's ~/.cache untouched and start clean.
os.environ.setdefault("HISTOJAX_CACHE", tempfile.mkdtemp(prefix="histojax-test-cache-"))
# Commands run by the tests (in process or as subprocesses) leave ~/.cache/histojax/jax alone: JAX's persistent
# compilation cache is off unless a test turns it on in its own folder (tests/env/test_compile_cache.py).
os.environ.setdefault("HISTOJAX_NO_COMPILE_CACHE", "1")

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def sample_envs():
    """``{env_id: (env, params)}`` for the three built-in scenarios on the embedded slide."""
    import histojax

    return {env_id: histojax.make(env_id) for env_id in ("HistoJAX-Easy-v0", "HistoJAX-Medium-v0", "HistoJAX-Hard-v0")}


@pytest.fixture(scope="session")
def small_slides(tmp_path_factory):
    """Bundle paths of 8 small semi-synthetic slides (320 × 256 px, tile 32, Easy levels; a few
    seconds to build), for the sharding and rotation tests."""
    from data_tools.datasets.synth.dataset import make_dataset

    root = tmp_path_factory.mktemp("small-slides")
    ds = make_dataset(
        root, n_slides=8, size=(320, 256), seed=0, tile_size=32, level_sets=(3,), progress=False, previews=False
    )
    return [str(root / s["bundle"]) for s in ds["slides"]]


def _colour_feature_grid(src, dest=None):
    """Copy the bundle ``src`` to ``dest`` (None: change ``src`` in place) and give it a cheap 6-d
    feature grid (mean and std of each view's RGB in [0, 1], one cell per tile) through
    ``data_tools.features.store``, so ``obs_mode="features"`` can be tested without running the
    EfficientNet encoder."""
    import shutil
    from pathlib import Path

    import numpy as np

    from data_tools.bundle import load_bundle, read_metadata
    from data_tools.features.store import level_grids, save_array, update_metadata

    dest = Path(src if dest is None else dest)
    if dest != Path(src):
        shutil.copytree(src, dest)
    meta = read_metadata(dest)
    tile = int(meta["tile_size"])
    bundle = load_bundle(dest, verify=False)
    written, levels = [], []
    for k, (gh, gw) in enumerate(level_grids(meta, tile)):
        views = np.asarray(bundle.pixels[k][: gh * tile, : gw * tile], np.float32).reshape(gh, tile, gw, tile, 3) / 255
        grid = np.concatenate([views.mean(axis=(1, 3)), views.std(axis=(1, 3))], -1).astype(np.float32)
        save_array(dest / f"features_{k:02d}.npy", grid)
        written.append(f"features_{k:02d}.npy")
        levels.append({"file": f"features_{k:02d}.npy", "grid": [gh, gw]})
    update_metadata(
        dest,
        {
            "encoder": "mean-std-rgb (tests)",
            "dim": 6,
            "stride": tile,
            "dtype": "float32",
            "projection": None,
            "levels": levels,
        },
        written,
    )
    return dest


@pytest.fixture(scope="session")
def colour_feature_grid():
    """``f(src_bundle, dest=None) -> dest``: a copy of a bundle (or the bundle itself) with a 6-d
    mean/std-RGB feature grid."""
    return _colour_feature_grid


@pytest.fixture(scope="session")
def c16_small(tmp_path_factory):
    """``(folder, id version)`` of the small C16 variant without pixels: pcam-cnn features and the
    ``-v1`` ids when the encoder's weights ship, else colour-stats features and ``-v0`` (seconds); with 2 folds of
    its train side (``--folds 2``)."""
    import subprocess
    import sys

    from data_tools.features import pcam_cnn

    v1 = pcam_cnn.WEIGHTS.is_file()
    folder = tmp_path_factory.mktemp("c16small") / "ds"
    cmd = [sys.executable, "-m", "data_tools", "c16", "--small", "--out", str(folder), "--no-pixels", "--folds", "2"]
    subprocess.run(cmd + ([] if v1 else ["--encoder", "colour-stats"]), check=True, capture_output=True)
    return folder, "v1" if v1 else "v0"
