"""The speed changes of the reading modes change nothing a user sees: observations, rewards,
``terminated`` / ``truncated`` and the reading figures of ``info`` of auto-resetting, vmapped rollouts
equal, bit for bit, those recorded from histojax before the changes (commit cdcc966: both views
observed every step, the visited map recounted from every finest view, ``seen`` as bools, host
tables from the whole stacked feature bank) in ``tests/data/reading_reference.npz``.

Two small synthetic slides of different sizes (a dataset: padding, slide draws) with the cheap
``colour-stats`` feature grid, 32-px views, 3 levels. The fixture was written by this module with
``HISTOJAX_RECORD_READING_REFERENCE=1`` (same modes, keys and actions); it holds only numbers made
here (no third-party data). One jitted rollout per mode, compiled once for the module.
"""
from __future__ import annotations

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import histojax

TILE, STEPS, ENVS, EPISODE = 32, 40, 4, 9
REFERENCE = Path(__file__).parent / "data" / "reading_reference.npz"
RECORD = os.environ.get("HISTOJAX_RECORD_READING_REFERENCE") == "1"
# (name, make overrides) of the modes whose trajectories must not change
MODES = {
    "discrete": dict(),
    "discrete_memory": dict(action_mode="discrete:memory", obs_mode="features"),
    "discrete_tracked": dict(track_reading=True, read_budget=0.3),
    "zoom_select": dict(action_mode="zoom_select", obs_mode="features", task="classification", read_budget=0.5),
    "glimpse": dict(action_mode="glimpse:1", obs_mode="features", task="classification", read_budget=0.4),
}


@pytest.fixture(scope="module")
def bundles(tmp_path_factory) -> list[Path]:
    import tifffile

    from data_tools.bundle import build_bundle
    from data_tools.features.grid import compute_features

    root = tmp_path_factory.mktemp("equiv")
    out = []
    for name, (h, w), seed in (("a", (768, 1024), 1), ("b", (1024, 640), 2)):
        rng = np.random.default_rng(seed)
        image = np.full((h, w, 3), 245, np.uint8)                          # glass
        image[60:h - 60, 50:w - 70] = [230, 160, 200]                       # pink tissue
        image[h // 4:h // 2, w // 2:w - 150] = [120, 40, 140]               # purple "tumour"
        image = np.clip(image.astype(int) + rng.integers(-8, 9, image.shape), 0, 255).astype(np.uint8)
        tifffile.imwrite(root / f"{name}.tif", image, photometric="rgb")
        path = build_bundle(root / f"{name}.tif", root / name, level_sets=(3,), tile_size=TILE, progress=False)
        compute_features(path, encoder_name="colour-stats", batch=64, progress=False, dtype="float32")
        out.append(path)
    return out


def _rollout(env, params, actions, key):
    """``ENVS`` vmapped auto-resetting envs for ``len(actions)`` steps: (obs, reward, term, trunc, info)."""
    def run(key, actions):
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, ENVS), params)

        def body(carry, a):
            state, key = carry
            key, sub = jax.random.split(key)
            obs, state, r, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(sub, ENVS), state, a, params)
            keep = {k: info[k] for k in ("fraction_read", "fields_of_view") if k in info}
            return (state, key), (obs, r, term, trunc, keep)

        return obs, jax.lax.scan(body, (state, key), actions)[1]
    return jax.jit(run)(key, actions)


def _flatten(name, first, steps) -> dict:
    obs, r, term, trunc, info = steps
    out = {f"{name}/reward": r, f"{name}/terminated": term, f"{name}/truncated": trunc}
    for k, v in info.items():
        out[f"{name}/info/{k}"] = v
    for prefix, o in (("first", first), ("obs", obs)):
        if isinstance(o, dict):
            for k, v in o.items():
                out[f"{name}/{prefix}/{k}"] = v
        else:
            out[f"{name}/{prefix}"] = o
    return {k: np.asarray(v) for k, v in out.items()}


def _record(name, bundles) -> dict:
    env, params = histojax.make("HistoJAX-Easy-v0", slides=bundles, max_steps_in_episode=EPISODE, **MODES[name])
    n = env.num_actions - (2 if env.task == "classification" else 0)
    actions = jax.random.randint(jax.random.key(3), (STEPS, ENVS), 0, n)
    if env.task == "classification":  # now and then a diagnosis, so that episodes also end by declaring
        declare = jax.random.randint(jax.random.key(4), (STEPS, ENVS), 0, 12)
        actions = jnp.where(declare == 0, n + (declare % 2), actions)
    first, steps = _rollout(env, params, actions, jax.random.key(5))
    return _flatten(name, first, steps)


if RECORD:
    def test_record_reference(bundles):
        out = {}
        for name in MODES:
            out.update(_record(name, bundles))
        np.savez_compressed(REFERENCE, **out)


# glimpse (a cell reader) in `make test`; plain discrete, discrete with the reading memory, discrete with tracked
# reading and zoom_select under `make test-all`
DEFAULT_RUN = ("glimpse",)


@pytest.mark.parametrize("name", [n if n in DEFAULT_RUN else pytest.param(n, marks=pytest.mark.slow) for n in MODES])
def test_trajectories_equal_the_recorded_reference(name, bundles):
    want = np.load(REFERENCE)
    got = _record(name, bundles)
    keys = sorted(k for k in want.files if k.startswith(f"{name}/"))
    assert keys, f"no reference recorded for {name}"
    assert sorted(got) == keys
    for k in keys:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    # the episodes do end (by time, budget or a diagnosis) and restart, so the auto-reset path is compared
    assert want[f"{name}/terminated"].any() or want[f"{name}/truncated"].any()
