"""Baselines: a tiny PPO run end to end, DQN targets against a hand calculation, the replay
buffer's sampling, checkpoint round trip, the evaluation's scripted policy."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from ppo_configs import TINY

from baselines import dqn, networks, ppo
from baselines.episodes import policies
from baselines.evaluate import cli, scoring
from baselines.harness.logs import load_checkpoint, save_checkpoint
from baselines.harness.runner import run_seeds

TINY_PPO = {**TINY, "hidden": 32, "num_seeds": 2}


# the default (seeds vmapped) in `make test`; seeds one after another (lax.map) under `make test-all`, whose
# runner path tests/training/test_resume.py::test_driver_killed_and_resumed_equals_the_uninterrupted_run[False] covers
@pytest.mark.parametrize("vmap_seeds", [pytest.param(False, marks=pytest.mark.slow), True])
def test_tiny_ppo_runs_jitted_with_finite_losses(vmap_seeds):
    train = ppo.make_train({**TINY_PPO, "vmap_seeds": vmap_seeds})
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    out = jax.block_until_ready(run_seeds(train, keys))
    m = out["metrics"]
    assert train.num_updates == 2
    for k in ("return", "success", "length", "steps_to_success", "pg_loss", "v_loss", "entropy", "approx_kl"):
        assert m[k].shape == (2, 2), k
    for k in ("pg_loss", "v_loss", "entropy", "approx_kl"):
        assert np.isfinite(np.asarray(m[k])).all(), k
    leaves = jax.tree.leaves(out["params"])
    assert all(leaf.shape[0] == 2 for leaf in leaves)  # seeds stacked
    assert all(np.isfinite(np.asarray(leaf)).all() for leaf in leaves)


def test_a_rollout_too_big_for_the_device_is_refused_before_compiling(monkeypatch):
    """glimpse:2 on the full C16 set compiled for 10 minutes and then died allocating 35 GB; now the trainers
    refuse such a run at once, with the figures and what to lower."""
    from baselines import ppo_rnn
    from baselines.common import devices

    obs = 128 * 128 * 3 + 3 * 4  # a pixel view (uint8) and the position (3 float32), bytes
    need = 2 * obs * TINY_PPO["num_steps"] * TINY_PPO["num_envs"] * 2
    monkeypatch.setattr(devices, "device_memory_bytes", lambda: need - 1)
    for trainer in (ppo, ppo_rnn):
        with pytest.raises(ValueError, match=r"rollouts of this run need .* lower num_envs / num_steps"):
            trainer.make_train({**TINY_PPO, "num_seeds": 2})
    monkeypatch.setattr(devices, "device_memory_bytes", lambda: need)
    assert ppo.make_train({**TINY_PPO, "num_seeds": 2, "vmap_seeds": True}).num_updates == 2


# `make test-all` (two network compiles, over a minute on 2 loaded cores): in `make test` the discrete ActorCritic
# on pooled pixels and the position runs in test_tiny_ppo_runs_jitted_with_finite_losses[True]
@pytest.mark.slow
def test_networks_shapes_pixels_dict_and_continuous():
    key = jax.random.PRNGKey(0)
    px = jnp.zeros((3, 128, 128, 3), jnp.uint8)
    pooled = networks.preprocess_obs(px)
    obs = {"pixels": pooled, "position": jnp.zeros((3, 3))}
    net = networks.ActorCritic(7, hidden=32)
    logits, value = jax.jit(lambda o: net.apply(net.init(key, o), o))(obs)
    assert logits.shape == (3, 7) and value.shape == (3,)
    cont = networks.ActorCritic(3, "continuous", hidden=32)
    (mean, log_std), value = jax.jit(lambda o: cont.apply(cont.init(key, o), o))(px)  # 128 px pooled inside
    assert mean.shape == (3, 3) and log_std.shape == (3,)


def test_networks_shapes_pooling_vector_and_patch_convolution():
    key = jax.random.PRNGKey(0)
    px = jnp.zeros((3, 128, 128, 3), jnp.uint8)
    pooled = networks.preprocess_obs(px)
    assert pooled.shape == (3, 32, 32, 3) and pooled.dtype == jnp.uint8
    q = networks.QNetwork(7, hidden=32)
    vec = jnp.zeros((3, 10))
    assert jax.jit(lambda o: q.apply(q.init(key, o), o))(vec).shape == (3, 7)
    # the 2x2 patch "convolution" equals nn.Conv with kernel 2, stride 2
    x = jax.random.normal(key, (2, 8, 8, 3))
    w = jax.random.normal(key, (2, 2, 3, 5))
    conv = jax.lax.conv_general_dilated(x, w, (2, 2), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    np.testing.assert_allclose(networks.space_to_depth(x) @ w.reshape(12, 5), conv, rtol=1e-4, atol=1e-4)


def test_n_step_double_q_target_matches_hand_calculation():
    gamma = 0.9
    # batch of 3, n = 3: no episode end; an end at step 1; an end at step 0
    rewards = jnp.array([[1.0, 1.0, 2.0], [2.0, 5.0, 7.0], [3.0, 9.0, 9.0]])  # (n, B)
    dones = jnp.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    q_online_next = jnp.array([[0.0, 3.0, 1.0], [5.0, 0.0, 0.0], [0.0, 0.0, 4.0]])  # argmax 1, 0, 2
    q_target_next = jnp.array([[10.0, 20.0, 30.0], [40.0, 50.0, 60.0], [70.0, 80.0, 90.0]])
    target = dqn.td_targets(rewards, dones, q_online_next, q_target_next, gamma, double_q=True)
    hand = [
        1 + 0.9 * 2 + 0.81 * 3 + 0.729 * 20,  # full 3-step return + γ³ Q_target(s', argmax Q_online) = 20
        1 + 0.9 * 5,  # ends at step 1: no bootstrap
        2.0,  # ends at step 0
    ]
    np.testing.assert_allclose(target, hand, rtol=1e-6)
    # plain (not double) DQN bootstraps from max Q_target = 30 for the first
    plain = dqn.td_targets(rewards, dones, q_online_next, q_target_next, gamma, double_q=False)
    np.testing.assert_allclose(plain[0], 1 + 0.9 * 2 + 0.81 * 3 + 0.729 * 30, rtol=1e-6)
    g, disc = dqn.n_step_return(rewards, dones, gamma, jnp.zeros(3))
    np.testing.assert_allclose(disc, [0.729, 0.0, 0.0], atol=1e-7)


def test_replay_buffer_samples_consecutive_rows_across_the_wrap():
    rows, envs, n = 5, 2, 2
    buf = dqn.buffer_init(jnp.zeros((envs, 1)), rows, envs)
    for t in range(8):  # wraps: rows hold t = 3..7
        obs = jnp.full((envs, 1), float(t)) + jnp.arange(envs)[:, None] * 100
        buf = dqn.buffer_add(buf, obs, jnp.full(envs, t), jnp.full(envs, float(t)), jnp.zeros(envs))
    obs_t, a_t, r, d, obs_n = dqn.buffer_sample(buf, jax.random.PRNGKey(0), 64, n)
    t = np.asarray(a_t)
    assert t.min() >= 3 and t.max() <= 7 - n  # oldest kept row .. last row with n rows after it
    np.testing.assert_array_equal(np.asarray(r), np.stack([t, t + 1]).astype(np.float32))
    np.testing.assert_array_equal(np.asarray(obs_n[:, 0]) % 100, t + n)
    np.testing.assert_array_equal(np.asarray(obs_t[:, 0]) // 100, np.asarray(obs_n[:, 0]) // 100)  # same env


def test_checkpoint_round_trip(tmp_path):
    net = networks.ActorCritic(7, hidden=16)
    obs = {"pixels": jnp.zeros((1, 32, 32, 3), jnp.uint8), "position": jnp.zeros((1, 3))}
    params = jax.jit(lambda ks: jax.lax.map(lambda k: net.init(k, obs), ks))(jax.random.split(jax.random.PRNGKey(3), 2))
    config = {**ppo.DEFAULTS, "hidden": 16}
    save_checkpoint(tmp_path, params, config)
    loaded, cfg = load_checkpoint(tmp_path)
    assert cfg["hidden"] == 16
    assert jax.tree.structure(loaded) == jax.tree.structure(params)
    for a, b in zip(jax.tree.leaves(loaded), jax.tree.leaves(params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    apply = jax.jit(lambda p: net.apply(jax.tree.map(lambda a: a[1], p), obs)[0])
    out1, out2 = apply(loaded), apply(params)
    np.testing.assert_array_equal(out1, out2)


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_scripted_policy_runs_and_moves_toward_dark_stain():
    # a view whose dark stain is on the right: the policy (without exploration) moves RIGHT
    px = jnp.full((128, 128, 3), 240, jnp.uint8).at[:, 96:, :].set(60)
    obs = {"pixels": px, "position": jnp.array([0.5, 0.5, 0.0])}
    a = policies.scripted_policy(jax.random.PRNGKey(0), obs, epsilon=0.0)
    assert int(a) == 3  # RIGHT
    centred = jnp.full((128, 128, 3), 240, jnp.uint8).at[48:80, 48:80, :].set(60)
    assert int(policies.scripted_policy(jax.random.PRNGKey(0), {**obs, "pixels": centred}, epsilon=0.0)) == 4
    config = {**ppo.DEFAULTS, "with_position": True, "max_steps_in_episode": 20}
    rows = scoring.evaluate(config, None, num_episodes=8)
    assert set(rows) == {"random", "scripted"}
    for r in rows.values():
        assert r["episodes"] == 8 and 0.0 <= r["success_rate"] <= 1.0 and r["mean_length"] <= 20


def test_scripted_features_policy_reads_the_view_logit_not_the_noisy_cell():
    # pcam-cnn's embedding: entry 62 is the view's tumour logit (mean l), 63 its most tumour-like cell
    from histojax.core import actions

    feats = jnp.zeros(64).at[62].set(3.0).at[63].set(-5.0)
    obs = {"features": feats, "position": jnp.array([0.5, 0.5, 0.0])}
    assert int(policies.scripted_features_policy(jax.random.PRNGKey(0), obs, epsilon=0.0)) == actions.ZOOM_IN
    at_finest = {**obs, "position": jnp.array([0.5, 0.5, 1.0])}
    assert int(policies.scripted_features_policy(jax.random.PRNGKey(0), at_finest, epsilon=0.0)) == actions.STAY
    # a hot cell in a cold view (63 high, 62 low) is not a reason to zoom in
    cold = {**obs, "features": jnp.zeros(64).at[62].set(-3.0).at[63].set(5.0)}
    moves = {int(policies.scripted_features_policy(jax.random.PRNGKey(k), cold, epsilon=0.0)) for k in range(20)}
    assert actions.ZOOM_IN not in moves and moves <= {0, 1, 2, 3}


@pytest.mark.slow
def test_tiny_dqn_and_evaluate_cli(tmp_path):
    config = dict(
        env_id="HistoJAX-Easy-v0",
        with_position=True,
        num_envs=4,
        total_timesteps=256,
        buffer_size=128,
        batch_size=8,
        learning_starts=32,
        iterations_per_log=16,
        hidden=32,
        num_seeds=1,
        print_progress=False,
    )
    train = dqn.make_train(config)
    out = jax.block_until_ready(run_seeds(train, jax.random.split(jax.random.PRNGKey(0), 1)))
    loss = np.asarray(out["metrics"]["loss"])
    assert loss.shape == (1, 4) and np.isfinite(loss).all() and loss[0, -1] > 0
    save_checkpoint(tmp_path, out["params"], train.config)
    assert cli.main([str(tmp_path), "--episodes", "4", "--out", str(tmp_path / "eval")]) == 0
    assert (tmp_path / "eval" / "eval.json").is_file() and (tmp_path / "eval" / "trajectory.gif").is_file()


@pytest.mark.slow
def test_tiny_ppo_continuous_actions():
    train = ppo.make_train({**TINY_PPO, "action_mode": "continuous", "num_seeds": 1})
    out = jax.block_until_ready(run_seeds(train, jax.random.split(jax.random.PRNGKey(1), 1)))
    assert np.isfinite(np.asarray(out["metrics"]["pg_loss"])).all()
    assert out["params"]["params"]["log_std"].shape == (1, 3)


def test_random_agent_reference_row():
    """The random-agent reference drawn on every learning curve (uses histojax.demo's rollout)."""
    from baselines.common.env import random_agent_reference

    ref = random_agent_reference({"env_id": "HistoJAX-Easy-v0", "with_position": True}, num_envs=8, num_steps=50)
    assert 0.0 <= ref["success"] <= 1.0 and np.isfinite(ref["return"])


def test_evaluate_resolves_held_out_slides_from_the_training_dataset(tmp_path):
    import json as _json

    from baselines.evaluate.cli import resolve_slides

    (tmp_path / "dataset.json").write_text(_json.dumps({"train": ["bundles/a"], "test": ["bundles/b", "bundles/c"]}))
    config = {"env_kwargs": {"dataset": str(tmp_path), "split": "train", "augment": True}}
    assert resolve_slides(["held-out"], config) == [str(tmp_path / "bundles/b"), str(tmp_path / "bundles/c")]
    assert resolve_slides(["x", "y"], config) == ["x", "y"]
    with pytest.raises(SystemExit, match="not trained on a dataset"):
        resolve_slides(["held-out"], {"env_kwargs": None})
    (tmp_path / "dataset.json").write_text("{")
    with pytest.raises(SystemExit, match="cannot read the test split"):
        resolve_slides(["held-out"], config)
