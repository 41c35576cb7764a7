"""Reader policies over a set of cells (``baselines.cell_set_networks.CellSetActorCritic`` and its recurrent
twin) for ``glimpse`` with ``step_obs=True``: parameters made on one dataset run on a dataset whose
slide is wider and taller than any of its slides, the pointer masks what cannot be picked, and the
trainers no longer pin the cell grid.

Two tiny synthetic datasets (made here, no third-party data): training slides of 640 × 800 and
800 × 560 px (height × width), and one 1000 × 2000 px slide; 32-px views, 3 levels (downsamples 16, 4, 1),
``colour-stats`` features.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import histojax
from baselines import ppo, ppo_rnn
from baselines.cell_set_networks import NEG
from baselines.common.env import pin_env_shapes
from baselines.harness.runner import run_seeds
from baselines.networks import ScannedGRU, network_step

TILE, ENVS, STEPS = 32, 4, 6
CONFIG = {
    "env_id": "HistoJAX-Easy-v0",
    "action_mode": "glimpse:1",
    "obs_mode": "features",
    "hidden": 32,
    "cell_hidden": 16,
    "obs_norm": None,
}


@pytest.fixture(scope="module")
def slides(tmp_path_factory) -> dict:
    import tifffile

    from data_tools.bundle import build_bundle
    from data_tools.features.grid import compute_features

    root = tmp_path_factory.mktemp("sets")
    out = {}
    for name, (h, w), seed in (("a", (640, 800), 1), ("b", (800, 560), 2), ("big", (1000, 2000), 3)):
        rng = np.random.default_rng(seed)
        image = np.full((h, w, 3), 245, np.uint8)
        image[60 : h - 60, 50 : w - 70] = [230, 160, 200]
        image[h // 4 : h // 2, w // 2 : w - 150] = [120, 40, 140]
        image = np.clip(image.astype(int) + rng.integers(-8, 9, image.shape), 0, 255).astype(np.uint8)
        tifffile.imwrite(root / f"{name}.tif", image, photometric="rgb")
        out[name] = build_bundle(root / f"{name}.tif", root / name, level_sets=(3,), tile_size=TILE, progress=False)
        compute_features(out[name], encoder_name="colour-stats", batch=64, progress=False, dtype="float32")
    return out


def _make(paths):
    return histojax.make(
        "HistoJAX-Easy-v0",
        slides=[str(p) for p in paths],
        obs_mode="features",
        action_mode="glimpse:1",
        task="classification",
        step_obs=True,
        read_budget=0.3,
        max_steps_in_episode=STEPS,
    )


@pytest.fixture(scope="module")
def envs(slides):
    return _make([slides["a"], slides["b"]]), _make([slides["big"]])


@functools.lru_cache(maxsize=None)
def _vreset(env):
    """``env.reset`` vmapped over keys, jitted once per env for the module (not run op by op in each test)."""
    return jax.jit(jax.vmap(env.reset, in_axes=(0, None)))


@functools.lru_cache(maxsize=None)
def _vstep(env):
    """``env.step`` vmapped over envs (params shared), jitted once per env for the module."""
    return jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))


def _batch_reset(env, params, key):
    return _vreset(env)(jax.random.split(key, ENVS), params)


def _reader_for_the_wider_slide(envs, recurrent: bool):
    """``(network built with the wider slide's tables, parameters made on the training dataset)``."""
    (env_a, pa), (env_b, _) = envs
    make = ppo_rnn.make_network if recurrent else ppo.make_network
    net_a, net_b = make(CONFIG, env_a), make(CONFIG, env_b)
    obs_a, _ = _batch_reset(env_a, pa, jax.random.key(0))
    if recurrent:
        h0 = ScannedGRU.initial_state(ENVS, CONFIG["hidden"])
        params = net_a.init(jax.random.key(1), h0, jax.tree.map(lambda a: a[None], obs_a), jnp.ones((1, ENVS), bool))
    else:
        params = net_a.init(jax.random.key(1), obs_a)
    return net_b, params


def test_the_other_slide_is_wider_and_taller(envs):
    (_, train), (_, other) = envs
    grids = np.asarray(train.mode_data.slide_grid)
    big = np.asarray(other.mode_data.slide_grid)[0]
    assert big[0] > grids[:, 0].max() and big[1] > grids[:, 1].max()
    assert other.mode_data.valid.shape[-1] > train.mode_data.valid.shape[-1]


@pytest.mark.parametrize("recurrent", [False, pytest.param(True, marks=pytest.mark.slow)])  # recurrent: make test-all
def test_parameters_from_one_dataset_read_another(envs, recurrent):
    env_b, pb = envs[1]
    net_b, params = _reader_for_the_wider_slide(envs, recurrent)
    c_b = int(pb.mode_data.valid.shape[-1])

    def policy(h, obs, first):
        if recurrent:
            return network_step(net_b, params, h, obs, first)
        return (h, *net_b.apply(params, obs))

    @jax.jit
    def rollout(key):
        obs, state = _batch_reset(env_b, pb, key)

        def body(carry, k):
            obs, state, h, first = carry
            h, logits, value = policy(h, obs, first)
            action = jax.random.categorical(k, logits)
            obs2, state, r, term, trunc, info = jax.vmap(env_b.step, in_axes=(0, 0, 0, None))(
                jax.random.split(k, ENVS), state, action, pb
            )
            return (obs2, state, h, term | trunc), (logits, value, action, obs, info["fraction_read"])

        h = ScannedGRU.initial_state(ENVS, CONFIG["hidden"])
        return jax.lax.scan(body, (obs, state, h, jnp.ones(ENVS, bool)), jax.random.split(key, STEPS - 1))[1]

    logits, value, action, obs, fraction = rollout(jax.random.key(2))
    assert logits.shape == (STEPS - 1, ENVS, c_b + 2) and np.isfinite(np.asarray(value)).all()
    valid = np.asarray(env_b.episode_tables(pb)["valid"])[np.asarray(obs["slide"])] > 0
    from histojax.reading.modes.glimpse import unpack_bits

    read = np.asarray(unpack_bits(obs["read_bits"], c_b))
    cell_logits = np.asarray(logits)[..., :c_b]
    assert (cell_logits[~valid | read] == NEG).all() and (cell_logits[valid & ~read] > NEG / 2).all()
    assert (np.asarray(action) < c_b + 2).all() and float(np.asarray(fraction).max()) > 0  # it reads


def test_trainers_do_not_pin_the_cell_grid(envs):
    (_, pa), _ = envs
    assert pin_env_shapes({"env_kwargs": {}}, pa) == {"env_kwargs": {}}


@pytest.mark.slow
def test_ppo_trains_on_one_dataset_and_reads_another(slides, envs):
    """A few PPO updates on the small slides; the trained parameters then act on the large one."""
    config = {
        **CONFIG,
        "env_kwargs": {
            "slides": [str(slides["a"]), str(slides["b"])],
            "task": "classification",
            "step_obs": True,
            "read_budget": 0.3,
        },
        "num_envs": 8,
        "num_steps": 8,
        "total_timesteps": 128,
        "num_minibatches": 2,
        "print_progress": False,
    }
    train = ppo.make_train(config)
    params = jax.tree.map(lambda a: a[0], run_seeds(train, jax.random.split(jax.random.key(0), 1))["params"])
    assert "glimpse_grid" not in train.config["env_kwargs"]
    _, (env_b, pb) = envs
    net_b = ppo.make_network(train.config, env_b)
    obs, _ = _batch_reset(env_b, pb, jax.random.key(3))
    logits, value = jax.jit(net_b.apply)(params, obs)
    assert logits.shape == (ENVS, int(pb.mode_data.valid.shape[-1]) + 2) and np.isfinite(np.asarray(value)).all()


def test_rollout_apply_computes_the_cell_keys_once_with_the_same_outputs(envs):
    """A rollout's policy (:func:`baselines.networks.rollout_apply`: the per-slide cell keys computed once
    for fixed parameters) gives the outputs of ``network.apply`` on every observation."""
    from baselines.networks import rollout_apply

    (env_a, pa), _ = envs
    net = ppo.make_network(CONFIG, env_a)
    obs, state = _batch_reset(env_a, pa, jax.random.key(4))
    params = net.init(jax.random.key(5), obs)
    policy = jax.jit(rollout_apply(net, params))
    plain = jax.jit(lambda o: net.apply(params, o))
    keys, slot_rows, mean = net.apply(params, None)
    valid = np.asarray(pa.mode_data.valid) > 0  # every valid cell of every slide once (and an empty row), packed
    assert keys.shape[0] == slot_rows.shape[0] == valid.sum() + 1 and mean.shape == (valid.shape[0], keys.shape[-1])
    c = int(pa.mode_data.valid.shape[-1])
    for t in range(STEPS):
        for a, b in zip(policy(obs), plain(obs)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)
        action = jax.random.randint(jax.random.key(10 + t), (ENVS,), 0, c + 2)
        obs, state, *_ = _vstep(env_a)(jax.random.split(jax.random.key(20 + t), ENVS), state, action, pa)


def test_pointer_logits_are_every_pickable_cells_key_against_the_query(envs):
    """The packed keys (valid cells only) scatter back to the right cells: each pickable cell's logit is
    its key, computed by hand from the per-cell layers on the dense ``(S, C)`` tables, against the query."""
    (env_a, pa), _ = envs
    net = ppo.make_network(CONFIG, env_a)
    obs, _ = _batch_reset(env_a, pa, jax.random.key(6))
    params = net.init(jax.random.key(7), obs)
    (logits, _), inter = net.apply(
        params, obs, capture_intermediates=lambda m, _: m.name == "query", mutable=["intermediates"]
    )
    query = np.asarray(jax.tree.leaves(inter["intermediates"])[0])  # (B, Hc)
    t = env_a.episode_tables(pa)
    enc = params["params"]["CellEncoder_0"]
    fixed = np.concatenate(
        [
            np.asarray(t["cells"]),
            np.asarray(t["valid"])[..., None],
            np.asarray(t["cost"])[..., None] * 10.0,
            np.asarray(t["position"]),
        ],
        -1,
    )
    relu = lambda x: np.maximum(x, 0.0)  # noqa: E731
    keys = relu(fixed @ np.asarray(enc["cell_in"]["kernel"]) + np.asarray(enc["cell_in"]["bias"]))
    keys = relu(keys @ np.asarray(enc["cell_mid"]["kernel"]) + np.asarray(enc["cell_mid"]["bias"]))  # (S, C, Hc)
    slide = np.asarray(obs["slide"])
    by_hand = np.einsum("bch,bh->bc", keys[slide], query) / np.sqrt(keys.shape[-1])
    c = keys.shape[1]
    pickable = np.asarray(t["valid"])[slide] > 0  # nothing read yet at a reset
    got = np.asarray(logits)[:, :c]
    assert pickable.sum() > 0
    np.testing.assert_allclose(got[pickable], by_hand[pickable], rtol=1e-4, atol=1e-5)
    assert (got[~pickable] == NEG).all()


def test_read_slots_are_the_dense_layer_over_the_observed_summaries_and_keys(envs):
    """The encoder computes each read slot from per-cell rows (its summary and key through ``slot_in``, once
    per valid cell): the same as ``slot_in`` over the observation's own ``read_summaries`` ‖ the cell's key,
    pooled (mean, max) over the filled slots, computed by hand on the dense ``(S, C)`` tables after a few reads."""
    from baselines.cell_set_networks import CellEncoder

    (env_a, pa), _ = envs
    net = ppo.make_network(CONFIG, env_a)
    obs, state = _batch_reset(env_a, pa, jax.random.key(11))
    params = net.init(jax.random.key(12), obs)
    valid = np.asarray(pa.mode_data.valid)
    for t in range(3):  # read three valid cells a slide (the first valid cells, by index)
        slide = np.asarray(obs["slide"])
        action = jnp.asarray([np.flatnonzero(valid[i])[t] for i in slide], jnp.int32)
        obs, state, *_ = _vstep(env_a)(jax.random.split(jax.random.key(50 + t), ENVS), state, action, pa)
    _, inter = net.apply(
        params, obs, capture_intermediates=lambda m, _: isinstance(m, CellEncoder), mutable=["intermediates"]
    )
    context_in = np.asarray(inter["intermediates"]["CellEncoder_0"]["__call__"][0][1])
    enc = jax.tree.map(np.asarray, params["params"]["CellEncoder_0"])
    t = env_a.episode_tables(pa)
    fixed = np.concatenate(
        [
            np.asarray(t["cells"]),
            np.asarray(t["valid"])[..., None],
            np.asarray(t["cost"])[..., None] * 10.0,
            np.asarray(t["position"]),
        ],
        -1,
    )
    relu = lambda x: np.maximum(x, 0.0)  # noqa: E731
    keys = relu(fixed @ enc["cell_in"]["kernel"] + enc["cell_in"]["bias"])
    keys = relu(keys @ enc["cell_mid"]["kernel"] + enc["cell_mid"]["bias"])  # (S, C, Hc)
    slide, where = np.asarray(obs["slide"]), np.asarray(obs["read_cells"])
    filled = where < valid.shape[1]
    assert (filled.sum(1) == 3).all()
    slot_in = np.concatenate(
        [np.asarray(obs["read_summaries"], np.float32), keys[slide[:, None], np.minimum(where, valid.shape[1] - 1)]], -1
    )
    slots = relu(slot_in @ enc["slot_in"]["kernel"] + enc["slot_in"]["bias"])  # (B, K, Hc)
    mean = (slots * filled[..., None]).sum(1) / filled.sum(1, keepdims=True)
    top = np.where(filled[..., None], slots, 0.0).max(1)
    hc = keys.shape[-1]
    np.testing.assert_allclose(context_in[:, hc : 2 * hc], mean, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(context_in[:, 2 * hc : 3 * hc], top, rtol=1e-4, atol=1e-5)
    on = valid[slide] > 0
    slide_mean = (keys[slide] * on[..., None]).sum(1) / on.sum(1, keepdims=True)
    np.testing.assert_allclose(context_in[:, :hc], slide_mean, rtol=1e-4, atol=1e-5)


def test_inverse_cdf_sampling_draws_the_softmax_distribution():
    """The set readers' rollout sampler (one uniform per row) draws each action as often as
    ``softmax(logits)`` says, never a masked one (``NEG``), on a row length that is not a multiple of its block,
    and on a row whose mass lies in its last entry."""
    from baselines.networks import inverse_cdf_sample

    rng = np.random.default_rng(0)
    logits = rng.normal(size=(3, 77)).astype(np.float32)
    logits[0, ::3] = NEG
    logits[1, :70] = NEG
    logits[2, :] = NEG
    logits[2, -1] = 0.0
    draws = np.asarray(
        jax.jit(jax.vmap(lambda k: inverse_cdf_sample(k, jnp.asarray(logits))))(
            jax.random.split(jax.random.key(0), 40_000)
        )
    )  # (draws, 3)
    p = np.asarray(jax.nn.softmax(jnp.asarray(logits), -1))
    for row in range(3):
        freq = np.bincount(draws[:, row], minlength=77) / draws.shape[0]
        assert freq[p[row] == 0].sum() == 0
        assert np.abs(freq - p[row]).max() < 5 * np.sqrt(p[row].max() / draws.shape[0]) + 1e-3
    assert (draws[:, 2] == 76).all()


def test_recurrent_rollout_step_computes_the_cell_keys_once_with_the_same_outputs(envs):
    """:func:`baselines.networks.rollout_step` (the recurrent reader's keys once per rollout) gives
    ``network_step``'s outputs, GRU state included."""
    from baselines.networks import network_step, rollout_step

    (env_a, pa), _ = envs
    net = ppo_rnn.make_network(CONFIG, env_a)
    obs, state = _batch_reset(env_a, pa, jax.random.key(8))
    h = ScannedGRU.initial_state(ENVS, CONFIG["hidden"])
    params = net.init(jax.random.key(9), h, jax.tree.map(lambda a: a[None], obs), jnp.ones((1, ENVS), bool))
    once = jax.jit(rollout_step(net, params))
    plain = jax.jit(lambda h, o, f: network_step(net, params, h, o, f))
    c = int(pa.mode_data.valid.shape[-1])
    first = jnp.ones(ENVS, bool)
    for t in range(STEPS):
        a, b = once(h, obs, first), plain(h, obs, first)
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-6, atol=1e-6)
        h = a[0]
        action = jax.random.randint(jax.random.key(30 + t), (ENVS,), 0, c + 2)
        obs, state, _, term, trunc, _ = _vstep(env_a)(jax.random.split(jax.random.key(40 + t), ENVS), state, action, pa)
        first = term | trunc


@pytest.mark.parametrize("recurrent", [False, True])
def test_evaluate_runs_a_set_reader_on_a_wider_slide(envs, recurrent):
    """``baselines.episodes.policies.learned_policy`` (cell keys once per rollout) runs a feed-forward or recurrent
    set reader made on one dataset on the wider slide (sampled: an untrained reader), and it reads."""
    from baselines.episodes.policies import learned_policy
    from baselines.episodes.rollout import run_episodes

    env_b, pb = envs[1]
    net_b, params = _reader_for_the_wider_slide(envs, recurrent)
    policy = learned_policy(net_b, params, CONFIG["action_mode"], greedy=False)
    assert hasattr(policy, "initial_memory") == recurrent
    ep = run_episodes(env_b, pb, policy, jax.random.key(3), 4)
    assert np.all(ep["length"] >= 1) and np.all(np.isfinite(ep["return"]))
    assert float(np.nanmax(ep["fraction_read"])) > 0  # it reads
