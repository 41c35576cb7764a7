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
REFERENCE = Path(__file__).parents[1] / "data" / "reading_reference.npz"
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
        image = np.full((h, w, 3), 245, np.uint8)  # glass
        image[60 : h - 60, 50 : w - 70] = [230, 160, 200]  # pink tissue
        image[h // 4 : h // 2, w // 2 : w - 150] = [120, 40, 140]  # purple "tumour"
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
                jax.random.split(sub, ENVS), state, a, params
            )
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


# ----------------------------------------------------------------------------- the cell-set reader's per-cell layers
# Given observations, the set reader (baselines.cell_set_networks.CellSetActorCritic) runs its per-cell layers over the valid
# cells of the slides in the batch only (CellEncoder.batch_tables, batch_cells=True); before, over those of all
# slides (batch_cells=False, still what the rollout's tables use). Both must give the same outputs and gradients.
SET_SLIDES = ("a", "b", "a", "b", "a")  # 5 slides; a batch of 2 envs leaves at least 3 out


@pytest.fixture(scope="module")
def set_reader(bundles):
    """``(env, params, network, network parameters, observations of 2 envs after 3 reads each)``."""
    from baselines import ppo

    env, params = histojax.make(
        "HistoJAX-Easy-v0",
        slides=[bundles[0 if n == "a" else 1] for n in SET_SLIDES],
        obs_mode="features",
        action_mode="glimpse:1",
        task="classification",
        step_obs=True,
        read_budget=0.5,
        max_steps_in_episode=EPISODE,
    )
    net = ppo.make_network(
        {
            "env_id": "HistoJAX-Easy-v0",
            "action_mode": "glimpse:1",
            "obs_mode": "features",
            "hidden": 16,
            "cell_hidden": 8,
            "obs_norm": None,
        },
        env,
    )
    valid = jnp.asarray(params.mode_data.valid)

    @jax.jit
    def reads(key):  # reset 2 envs, then read cells 1, 4, 7 of each slide's valid cells: one program
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, 2), params)
        for t in range(3):
            action = jax.vmap(lambda i: jnp.nonzero(valid[i], size=valid.shape[1])[0][3 * t + 1])(obs["slide"])
            obs, state, *_ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(jax.random.fold_in(key, t), 2), state, action.astype(jnp.int32), params
            )
        return obs

    obs = reads(jax.random.key(7))
    return env, params, net, jax.jit(net.init)(jax.random.key(8), obs), obs


def test_set_reader_per_cell_layers_run_over_the_batch_slides_only(set_reader, monkeypatch):
    """The batch's tables: the keys and slot rows of the valid cells of the slides present, in flat order, then
    zeros (their count is the work done); the mean keys of those slides equal the all-slides tables', the others are
    zeros. Blocks of 5 rows: several trips of the loop and a partial last block."""
    from baselines import cell_set_networks
    from baselines.cell_set_networks import CellEncoder

    monkeypatch.setattr(cell_set_networks, "CELL_CHUNK", 5)
    env, params, net, p, obs = set_reader
    enc = CellEncoder(net.cell_hidden, net.tables, net.obs_norm)
    v = {"params": p["params"]["CellEncoder_0"]}
    slides = jnp.asarray(obs["slide"], jnp.int32)
    (keys, slot_rows, mean, shift), (all_keys, all_slots, all_mean) = jax.jit(  # the batch's; every slide's (N + 1)
        lambda s: (enc.apply(v, s, method=CellEncoder.batch_tables), enc.apply(v, None))
    )(slides)
    t = net.tables
    present = np.unique(np.asarray(slides))
    assert 1 <= len(present) < len(SET_SLIDES)
    flat_slide = np.asarray(t.flat_slide)
    rows = np.flatnonzero(np.isin(flat_slide, present))  # the present slides' flat rows
    n = len(rows)
    assert 0 < n < t.num_flat and keys.shape[0] > t.num_flat
    np.testing.assert_allclose(keys[:n], all_keys[rows], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(slot_rows[:n], all_slots[rows], rtol=1e-5, atol=1e-6)
    assert not np.asarray(keys[n:]).any() and not np.asarray(slot_rows[n:]).any()
    absent = np.setdiff1d(np.arange(len(SET_SLIDES)), present)
    np.testing.assert_allclose(mean[present], all_mean[present], rtol=1e-5, atol=1e-6)
    assert not np.asarray(mean[absent]).any()
    for i in present:  # flat row f of slide i: row f - shift[i]
        f = np.flatnonzero(flat_slide == i)
        np.testing.assert_allclose(keys[f - int(shift[i])], all_keys[f], rtol=1e-5, atol=1e-6)


def test_set_reader_outputs_and_gradients_equal_the_all_slides_path(set_reader, monkeypatch):
    """The set reader's logits, value and the gradient of a PPO-like loss through them, per-cell layers over the
    batch's slides (blocks of 5 rows) against over all slides (``batch_cells=False``), to float rounding; also
    vmapped over two parameter sets, as PPO runs seeds."""
    from baselines import cell_set_networks

    monkeypatch.setattr(cell_set_networks, "CELL_CHUNK", 5)
    env, params, net, p, obs = set_reader
    old = net.clone(batch_cells=False)
    action = jnp.asarray([np.flatnonzero(np.asarray(params.mode_data.valid)[i])[0] for i in np.asarray(obs["slide"])])

    def loss(q, network):
        logits, value = network.apply(q, obs)
        logp = jax.nn.log_softmax(logits)
        return (
            -jnp.take_along_axis(logp, action[:, None], -1).sum()
            + (value**2).sum()
            - (jnp.exp(logp) * jnp.where(logits > cell_set_networks.NEG, logp, 0.0)).sum()
        )

    @jax.jit
    def run(q):  # one program: outputs, and gradients vmapped over two parameter sets, by both paths
        both = jax.tree.map(lambda a: jnp.stack([a, 1.01 * a]), q)
        grads = [jax.vmap(jax.grad(lambda x, n=n: loss(x, n)))(both) for n in (net, old)]
        return net.apply(q, obs), old.apply(q, obs), grads

    out_new, out_old, (g_new, g_old) = run(p)
    for got, want in zip(out_new, out_old):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    cell = ("cell_in", "cell_mid", "slot_in")
    assert any(np.abs(np.asarray(g_old["params"]["CellEncoder_0"][k]["kernel"])).max() > 0 for k in cell)
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(g_new), jax.tree.leaves(g_old)):
        np.testing.assert_allclose(
            a, b, rtol=2e-5, atol=1e-6 * float(np.abs(np.asarray(b)).max() + 1e-6), err_msg=jax.tree_util.keystr(path)
        )
