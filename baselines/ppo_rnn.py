"""Recurrent PPO in the PureJaxRL ``ppo_rnn`` style: a GRU policy
(:class:`baselines.networks.RecurrentActorCritic`) whose hidden state is carried through the
rollout and reset at episode starts; the whole run — rollouts, GAE, minibatch epochs over whole
env sequences — is one jitted program, vmapped over seeds, run by the harness from the
:class:`~baselines.harness.trainer.Trainer` ``make_train`` returns (as :mod:`baselines.ppo`).

    python -m baselines.ppo_rnn --env HistoJAX-Easy-v0 --with-position --seeds 2 --total-steps 500000 --out runs/ppo-rnn-easy

Writes the same files as ``baselines.ppo`` (``log.csv``, ``log.json``, ``curve.png``,
``params.msgpack``, ``config.json`` with ``"algo": "ppo_rnn"``); ``python -m baselines.evaluate
runs/ppo-rnn-easy`` evaluates it, carrying the hidden state through each episode.

Memory: each step the network reads ``(h, obs_t, first_t)`` where ``first_t`` says that ``obs_t`` is
the first observation of an episode (the previous step ended one; with auto-reset the env has
already started the next). The GRU sets ``h`` to zeros where ``first_t`` is true, before reading
``obs_t``. The rollout stores ``first`` apart from ``done`` (the end of *this* step's episode, used by
GAE), and the loss replays every env's sequence from the hidden state it had at the start of the
rollout with the same ``first`` flags, so the replayed log-probabilities equal the rollout's (PPO's
ratio is 1 before the first gradient step). Minibatches are sets of whole env sequences
(``num_envs`` must divide by ``num_minibatches``). ``--devices`` is not supported here.
"""

from __future__ import annotations

import dataclasses
import sys

import jax
import jax.numpy as jnp
from flax.training.train_state import TrainState

from baselines import ppo
from baselines.common.devices import check_rollout_memory
from baselines.common.env import make_env, params_initialiser, pin_env_shapes, reset_envs
from baselines.harness.cli import trainer_command
from baselines.harness.logs import Progress
from baselines.harness.trainer import Trainer
from baselines.networks import (
    RecurrentActorCritic,
    ScannedGRU,
    network_step,
    policy_log_prob,
    preprocess_obs,
    rollout_sampler,
    rollout_step,
)
from histojax import compile_cache
from histojax.adapters.jax import LogWrapper


@dataclasses.dataclass(frozen=True)
class PPORNNConfig(ppo.PPOConfig):
    """Recurrent PPO's settings: :class:`baselines.ppo.PPOConfig`'s with its own defaults (``hidden``: the GRU's
    width; ``num_minibatches`` splits the ``num_envs`` env sequences). ``devices`` is refused (one device) and not
    recorded in ``config.json``; ``minibatch_by`` is always ``"env"`` and not recorded."""

    algo: str = "ppo_rnn"  # the trainer (recorded in config.json)
    num_minibatches: int = 4  # minibatches of whole env sequences (num_envs must divide by it)
    minibatch_by: str = "env"  # always whole env sequences (the GRU replays them); not recorded
    hidden: int = 128  # GRU and dense width

    RECORDED_WITHOUT = ("devices", "minibatch_by")


DEFAULTS = PPORNNConfig.defaults()  # the record of the default config (config.json's entries)


def make_network(config, env) -> RecurrentActorCritic:
    """The GRU actor-critic for ``env``'s action space (discrete: ``n`` logits; continuous: Box size)."""
    return ppo.make_network(config, env, RecurrentActorCritic)


def rollout(network, env, params, env_params, carry, num_steps: int, action_mode: str):
    """``num_steps`` steps of the sampled recurrent policy in ``B`` vmapped, auto-resetting envs
    (``env`` wrapped in :class:`~histojax.adapters.jax.LogWrapper`). ``carry = (env_state, obs (pooled,
    :func:`~baselines.networks.preprocess_obs`), first (B,) bool, h (B, H), key)`` → ``(carry,
    traj)`` with ``traj`` a :class:`baselines.ppo.Transition` (``first`` set) of time-major
    ``(num_steps, B, ...)`` arrays; ``first`` of step ``t + 1`` is ``done`` of step ``t``."""
    num_envs = carry[2].shape[0]
    policy = rollout_step(network, params)  # the params are fixed during the rollout
    sample = rollout_sampler(network, action_mode)

    def env_step(carry, _):
        env_state, obs, first, h, key = carry
        key, k_act, k_step = jax.random.split(key, 3)
        h, pi, value = policy(h, obs, first)
        action = sample(k_act, pi)
        log_prob = policy_log_prob(pi, action, action_mode)
        next_obs, env_state, reward, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(k_step, num_envs), env_state, action, env_params
        )
        done = jnp.logical_or(term, trunc)
        t = ppo.Transition(
            done.astype(jnp.float32), action, value, reward, log_prob, obs, {k: info[k] for k in ppo.LOG_KEYS}, first
        )
        return (env_state, preprocess_obs(next_obs), done, h, key), t

    return jax.lax.scan(env_step, carry, None, num_steps)


def replay(network, params, h_start, traj: ppo.Transition):
    """The policy and values ``(pi (T, B, ...), value (T, B))`` of ``params`` along a stored
    rollout, from the hidden states ``h_start (B, H)`` it started with, resetting where
    ``traj.first``: with the rollout's own parameters this reproduces its log-probabilities."""
    _, pi, value = network.apply(params, h_start, traj.obs, traj.first)
    return pi, value


def make_train(config) -> Trainer:
    """Recurrent PPO's :class:`~baselines.harness.trainer.Trainer` (as :func:`baselines.ppo.make_train`'s; runner
    state ``(train state, env states, observations, first flags, GRU states, key)``), run by the harness
    (:func:`baselines.harness.runner.run_seeds`, :func:`~baselines.harness.runner.run_chunked`).
    ``config``: a :class:`PPORNNConfig`, or a dict made into one (:meth:`~PPORNNConfig.from_dict`)."""
    config = PPORNNConfig.coerce(config, where="ppo_rnn.make_train")
    if config.devices is not None:
        raise ValueError("ppo_rnn does not shard over devices; drop devices (use baselines.ppo for that)")
    if config.minibatch_by != "env":
        raise ValueError(f"ppo_rnn's minibatches are whole env sequences; minibatch_by={config.minibatch_by!r} is not")
    env, env_params = make_env(config)
    config = pin_env_shapes(ppo.resolve_obs_norm(config, env_params), env_params)
    check_rollout_memory(env, env_params, config)
    env = LogWrapper(env)
    network = make_network(config, env)
    mode, hidden = config.action_mode, config.hidden
    num_envs, num_steps, n_mb = config.num_envs, config.num_steps, config.num_minibatches
    if num_envs % n_mb:
        raise ValueError(
            f"num_envs={num_envs} must divide by num_minibatches={n_mb} (minibatches are whole env sequences)"
        )
    num_updates = max(1, config.total_timesteps // (num_envs * num_steps))
    batch = num_envs * num_steps
    progress = Progress(config.num_seeds, num_updates, batch, config.log_every, name=f"ppo_rnn {config.env_id}")

    init_params = params_initialiser(
        env,
        network,
        num_envs,
        inputs=lambda obs: (
            ScannedGRU.initial_state(num_envs, hidden),
            jax.tree.map(lambda a: a[None], obs),
            jnp.ones((1, num_envs), bool),
        ),
    )

    tx = ppo.make_optimizer(config, num_updates)

    def init_runner(key, env_params, params):
        """One seed's runner state before the first update: ``(train state, env states, observations,
        first flags, GRU states, key)`` with the envs freshly reset."""
        key, _, obs0, env_state = reset_envs(env, key, env_params, num_envs)
        state = TrainState.create(apply_fn=network.apply, params=params, tx=tx)
        return state, env_state, obs0, jnp.ones(num_envs, bool), ScannedGRU.initial_state(num_envs, hidden), key

    def update(carry, update_index, env_params):
        """One recurrent PPO update of a runner state ``carry`` (:func:`init_runner`): ``(carry, metrics)``."""
        state, env_state, obs, first, h0, key = carry
        (env_state, obs, first, h, key), traj = rollout(
            network, env, state.params, env_params, (env_state, obs, first, h0, key), num_steps, mode
        )
        _, _, last_value = network_step(network, state.params, h, obs, first)
        advantages, targets = ppo.gae(traj, last_value, config.gamma, config.gae_lambda)

        def loss_fn(params, mb):
            h_start, traj, adv, target = mb
            pi, value = replay(network, params, h_start, traj)
            return ppo.clipped_loss(
                pi, value, traj, adv, target, config, ppo.entropy_coef(config, update_index, num_updates)
            )

        def minibatches(k_perm):  # whole env sequences: shuffle and split the env axis
            perm = jax.random.permutation(k_perm, num_envs)
            # env axis: 0 for the start states, 1 for the time-major rollout
            split = lambda a, axis: jnp.stack(jnp.split(jnp.take(a, perm, axis=axis), n_mb, axis=axis))  # noqa: E731
            return (
                jax.tree.map(lambda a: split(a, 0), h0),
                *jax.tree.map(lambda a: split(a, 1), (traj, advantages, targets)),
            )

        state, key, aux = ppo.run_epochs(state, key, loss_fn, minibatches, config.update_epochs)
        metrics = ppo.update_metrics(traj.info, aux, progress, update_index, config)
        return (state, env_state, obs, first, h, key), metrics

    return Trainer(
        init_params=init_params,
        init_runner=init_runner,
        update=update,
        runner_params=lambda runner: runner[0].params,
        env=env,
        env_params=env_params,
        network=network,
        num_updates=num_updates,
        steps_per_update=batch,
        train_config=config,
        config=config.as_dict(),
        progress=progress,
        metric_keys=ppo.METRIC_KEYS,
    )


# python -m baselines.ppo_rnn and histojax train --algo ppo_rnn: options, command, entry point
add_arguments, run, main = trainer_command("ppo_rnn", make_train, PPORNNConfig, "updates", __doc__)


if __name__ == "__main__":
    raise SystemExit(main(compile_cache.setup(sys.argv[1:])))  # the persistent compilation cache, --no-compile-cache
