"""Recurrent PPO (baselines.ppo_rnn): the GRU's reset at episode starts, the network step jitted
and not, the loss replaying the rollout's log-probabilities, and a short run that beats the random
agent on Easy (features of the sample slide) evaluated from its checkpoint by baselines.evaluate."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from baselines import networks, ppo_rnn
from baselines.common.env import make_env, params_initialiser, reset_envs
from baselines.evaluate import scoring
from baselines.harness.logs import load_checkpoint, save_checkpoint
from baselines.harness.runner import run_seeds


def _scaled(params, factor):
    """Parameters with every kernel multiplied by ``factor``: a policy far from uniform, so the
    checks below see the hidden state in the action probabilities."""
    return jax.tree_util.tree_map_with_path(
        lambda path, a: a * factor if "kernel" in jax.tree_util.keystr(path) else a, params
    )


@pytest.fixture(scope="module")
def vector_net():
    net = networks.RecurrentActorCritic(action_dim=7, hidden=16)
    t, b = 6, 3
    obs = jax.random.normal(jax.random.PRNGKey(1), (t, b, 5))
    params = jax.jit(net.init)(
        jax.random.PRNGKey(0), networks.ScannedGRU.initial_state(b, 16), obs, jnp.zeros((t, b), bool)
    )
    return net, _scaled(params, 3.0), obs, jax.jit(net.apply)


def test_gru_hidden_state_resets_where_an_episode_starts(vector_net):
    _, params, obs, apply = vector_net
    t, b = obs.shape[:2]
    h0 = jax.random.normal(jax.random.PRNGKey(2), (b, 16))  # a state left over from earlier steps
    resets = jnp.zeros((t, b), bool).at[3, 0].set(True).at[0, 2].set(True)
    _, logits, value = apply(params, h0, obs, resets)
    _, logits_noreset, _ = apply(params, h0, obs, jnp.zeros((t, b), bool))
    # env 0 after its reset at t = 3 behaves as a fresh episode that starts at obs[3]
    zeros = networks.ScannedGRU.initial_state(1, 16)
    _, fresh, fresh_v = apply(params, zeros, obs[3:, :1], jnp.zeros((t - 3, 1), bool))
    np.testing.assert_allclose(logits[3:, 0], fresh[:, 0], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(value[3:, 0], fresh_v[:, 0], rtol=1e-5, atol=1e-5)
    # before the reset, and in env 1 (never reset), the carried state is used
    np.testing.assert_allclose(logits[:3, 0], logits_noreset[:3, 0], rtol=1e-6)
    np.testing.assert_allclose(logits[:, 1], logits_noreset[:, 1], rtol=1e-6)
    assert np.abs(np.asarray(logits[3:, 0] - logits_noreset[3:, 0])).max() > 1e-3  # the reset mattered
    # env 2 reset at t = 0: the leftover state is ignored entirely
    _, from_zero, _ = apply(params, networks.ScannedGRU.initial_state(b, 16), obs, jnp.zeros((t, b), bool))
    np.testing.assert_allclose(logits[:, 2], from_zero[:, 2], rtol=1e-5, atol=1e-5)


def test_network_step_jit_equals_no_jit_and_equals_the_scanned_sequence(vector_net):
    net, params, obs, apply = vector_net
    t, b = obs.shape[:2]
    first = jnp.zeros((t, b), bool).at[2, 1].set(True)
    step = lambda h, o, f: networks.network_step(net, params, h, o, f)  # noqa: E731
    jitted = jax.jit(step)
    h_eager = h_jit = networks.ScannedGRU.initial_state(b, 16)
    for i in range(t):
        h_eager, pi_eager, v_eager = step(h_eager, obs[i], first[i])
        h_jit, pi_jit, v_jit = jitted(h_jit, obs[i], first[i])
        np.testing.assert_allclose(pi_eager, pi_jit, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(v_eager, v_jit, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(h_eager, h_jit, rtol=1e-5, atol=1e-6)
    h_seq, pi_seq, _ = apply(params, networks.ScannedGRU.initial_state(b, 16), obs, first)
    np.testing.assert_allclose(pi_seq[-1], pi_eager, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(h_seq, h_eager, rtol=1e-5, atol=1e-5)


def test_loss_replays_the_rollouts_log_probs_across_episode_ends():
    """Pixels + position, episodes of 4 steps inside a 12-step rollout: replaying the stored
    sequence with ``first`` reproduces the rollout's log-probabilities; resetting on ``done`` of
    the same step instead (as PureJaxRL's ppo_rnn loss does) would not."""
    config = {**ppo_rnn.DEFAULTS, "with_position": True, "max_steps_in_episode": 4, "hidden": 16}
    env, env_params = make_env(config)
    from histojax.adapters.jax import LogWrapper

    env = LogWrapper(env)
    net = ppo_rnn.make_network(config, env)
    n = 2
    init = params_initialiser(
        env,
        net,
        n,
        inputs=lambda o: (
            networks.ScannedGRU.initial_state(n, 16),
            jax.tree.map(lambda a: a[None], o),
            jnp.ones((1, n), bool),
        ),
    )

    @jax.jit
    def go(key):
        params = _scaled(init(key, env_params), 2.0)
        key, _, obs, env_state = reset_envs(env, key, env_params, n)
        h0 = jax.random.normal(key, (n, 16))  # a state carried over from an earlier rollout
        carry = (env_state, obs, jnp.zeros(n, bool), h0, key)
        _, traj = ppo_rnn.rollout(net, env, params, env_params, carry, 12, "discrete")
        replayed, _ = ppo_rnn.replay(net, params, h0, traj)
        wrong, _ = ppo_rnn.replay(net, params, h0, traj._replace(first=traj.done.astype(bool)))
        logp = lambda pi: networks.policy_log_prob(pi, traj.action, "discrete")  # noqa: E731
        return traj, logp(replayed), logp(wrong)

    traj, replayed, wrong = go(jax.random.PRNGKey(0))
    assert np.asarray(traj.done).sum() == 3 * n  # episodes end at steps 4, 8, 12
    np.testing.assert_array_equal(np.asarray(traj.first[1:]), np.asarray(traj.done[:-1]).astype(bool))
    np.testing.assert_allclose(replayed, traj.log_prob, rtol=1e-4, atol=1e-4)
    assert np.abs(np.asarray(wrong - traj.log_prob)).max() > 1e-3


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_short_run_beats_the_random_agent_and_evaluates_from_its_checkpoint(tmp_path, colour_feature_grid):
    from histojax.sample import sample_bundle

    slide = colour_feature_grid(sample_bundle(), tmp_path / "slide")
    config = dict(
        env_id="HistoJAX-Easy-v0",
        slide=str(slide),
        obs="features",
        with_position=True,
        num_envs=16,
        num_steps=32,
        total_timesteps=4096,
        hidden=64,
        lr=1e-3,
        update_epochs=4,
        num_minibatches=4,
        num_seeds=1,
        print_progress=False,
    )
    train = ppo_rnn.make_train(config)
    out = jax.block_until_ready(run_seeds(train, jax.random.split(jax.random.PRNGKey(0), 1)))
    assert np.isfinite(np.asarray(out["metrics"]["pg_loss"])).all()
    save_checkpoint(tmp_path / "run", out["params"], train.config)
    params, loaded = load_checkpoint(tmp_path / "run")
    assert loaded["algo"] == "ppo_rnn"
    rows = scoring.evaluate(loaded, params, num_episodes=64, label="ppo_rnn")
    learned, rand = rows["ppo_rnn (sampled)"], rows["random"]
    assert learned["success_rate"] >= rand["success_rate"] + 0.2, rows
    assert learned["mean_steps_to_success"] < rand["mean_steps_to_success"], rows
