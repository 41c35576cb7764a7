"""DQN in pure JAX: many vectorised actors feed one replay buffer; double-Q, n-step returns and a
target network. ``make_train`` returns a :class:`~baselines.harness.trainer.Trainer` whose update is one log
block (a ``lax.scan`` of iterations); the harness runs the updates and the seeds in one jitted program.

    python -m baselines.dqn --env HistoJAX-Easy-v0 --with-position --seeds 2 --total-steps 200000 --out runs/dqn-easy

Outputs as :mod:`baselines.ppo` (``log.csv``, ``log.json``, ``curve.png``, ``params.msgpack``,
``config.json``). Discrete actions only.

**Replay buffer**: a circular buffer in a pytree, time-major: ``rows × num_envs`` transitions
(observation pooled to 32 px uint8 by :func:`networks.preprocess_obs`, action, reward, done),
each observation stored once — the next observation of row ``t`` is row ``t + 1`` of the same
env. A sample is a (row, env) pair whose ``n`` following rows are written; its n-step return
stops at the first episode end (auto-reset puts the next episode's first observation after it,
which the zero discount then ignores). Time limits count as episode ends, as in PPO.
"""

from __future__ import annotations

import dataclasses
import sys

import jax
import jax.numpy as jnp
import optax
from flax import struct

from baselines.common.config import EnvConfig
from baselines.common.env import episode_stats, make_env, params_initialiser, reset_envs
from baselines.harness.cli import trainer_command
from baselines.harness.logs import Progress, report
from baselines.harness.trainer import EPISODE_METRICS, Trainer
from baselines.networks import QNetwork, preprocess_obs
from histojax import compile_cache
from histojax.adapters.jax import LogWrapper


@dataclasses.dataclass(frozen=True)
class DQNConfig(EnvConfig):
    """DQN's settings, typed (``config.json`` records them, :meth:`as_dict`; ``--set KEY=VALUE`` changes any;
    :meth:`from_dict` refuses an unknown entry or a wrong type in one line; discrete actions only). Steps are env
    steps, ``buffer_size`` counts transitions of all envs, ``hidden`` is the network's width."""

    algo: str = "dqn"  # the trainer (recorded in config.json)
    num_envs: int = 32  # parallel envs per seed
    total_timesteps: int = 200_000  # env steps per seed
    buffer_size: int = 32_768  # replay rows (transitions of all envs)
    batch_size: int = 128
    n_step: int = 3  # n-step returns
    gamma: float = 0.99  # discount
    lr: float = 2.5e-4  # Adam learning rate
    max_grad_norm: float = 10.0
    learning_starts: int = 2_048  # env steps before the first update
    train_every: int = 1  # iterations per gradient step
    target_update_every: int = 250  # gradient steps per target-network copy
    eps_start: float = 1.0  # epsilon-greedy schedule
    eps_end: float = 0.05
    eps_fraction: float = 0.4  # fraction of the run the schedule takes
    double_q: bool = True
    hidden: int = 256  # network width
    num_seeds: int = 1
    vmap_seeds: bool = True  # all seeds in one vmapped program
    iterations_per_log: int = 50
    log_every: int = 2  # log blocks per progress line
    print_progress: bool = True
    checkpoint_every: int = 25  # log blocks between checkpoints of the whole training state, replay
    # buffer included (0: only the end)


DEFAULTS = DQNConfig.defaults()  # the record of the default config (config.json's entries)


# ----------------------------------------------------------------------------- targets
def n_step_return(rewards, dones, gamma: float, bootstrap):
    """n-step return ``Σ_k γ^k r_k Π_{j<k}(1 − d_j) + γ^n Π_j(1 − d_j) · bootstrap``.

    ``rewards, dones``: ``(n, ...)`` (the reward of step ``k`` and whether the episode ended at
    it); ``bootstrap``: ``(...)`` the value of the state after the n-th step. Returns ``(G,
    discount)`` where ``discount = γ^n Π(1 − d)`` is the weight the bootstrap got."""

    def body(carry, x):
        g, disc = carry
        r, d = x
        return (g + disc * r, disc * gamma * (1.0 - d)), None

    ones = jnp.ones_like(bootstrap, jnp.float32)
    (g, disc), _ = jax.lax.scan(
        body, (jnp.zeros_like(ones), ones), (jnp.asarray(rewards, jnp.float32), jnp.asarray(dones, jnp.float32))
    )
    return g + disc * bootstrap, disc


def double_q_value(q_online_next, q_target_next):
    """Double-Q bootstrap: the target network's value of the online network's greedy action."""
    a = jnp.argmax(q_online_next, axis=-1)
    return jnp.take_along_axis(q_target_next, a[..., None], axis=-1)[..., 0]


def td_targets(rewards, dones, q_online_next, q_target_next, gamma: float, double_q: bool = True):
    """n-step (double-)Q targets for a batch: ``rewards, dones (n, B)``, ``q_* (B, A)``."""
    boot = double_q_value(q_online_next, q_target_next) if double_q else q_target_next.max(-1)
    return n_step_return(rewards, dones, gamma, boot)[0]


# ----------------------------------------------------------------------------- buffer
@struct.dataclass
class Buffer:
    obs: object  # (rows, envs, ...) preprocessed observations
    action: jnp.ndarray  # (rows, envs)
    reward: jnp.ndarray  # (rows, envs)
    done: jnp.ndarray  # (rows, envs)
    pointer: jnp.ndarray  # next row to write
    filled: jnp.ndarray  # rows written so far (≤ rows)


def buffer_init(obs_example, rows: int, num_envs: int) -> Buffer:
    obs = jax.tree.map(lambda a: jnp.zeros((rows, *a.shape), a.dtype), obs_example)
    z = jnp.zeros((rows, num_envs))
    return Buffer(obs, z.astype(jnp.int32), z, z, jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32))


def buffer_add(buf: Buffer, obs, action, reward, done) -> Buffer:
    rows = buf.reward.shape[0]
    p = buf.pointer
    put = lambda store, x: store.at[p].set(x.astype(store.dtype))  # noqa: E731
    return Buffer(
        jax.tree.map(put, buf.obs, obs),
        put(buf.action, action),
        put(buf.reward, reward),
        put(buf.done, done),
        (p + 1) % rows,
        jnp.minimum(buf.filled + 1, rows),
    )


def buffer_sample(buf: Buffer, key, batch_size: int, n: int):
    """``(obs_t, action_t, rewards (n, B), dones (n, B), obs_{t+n})`` for ``batch_size`` random
    (row, env) pairs whose next ``n`` rows are written (needs ``filled > n``)."""
    rows, num_envs = buf.reward.shape
    k1, k2 = jax.random.split(key)
    logical = jax.random.randint(k1, (batch_size,), 0, jnp.maximum(buf.filled - n, 1))
    env = jax.random.randint(k2, (batch_size,), 0, num_envs)
    start = buf.pointer - buf.filled  # logical 0 = the oldest row
    row = lambda k: (start + logical + k) % rows  # noqa: E731
    steps = jnp.stack([row(k) for k in range(n)])  # (n, B)
    obs_t = jax.tree.map(lambda a: a[row(0), env], buf.obs)
    obs_n = jax.tree.map(lambda a: a[row(n), env], buf.obs)
    return obs_t, buf.action[row(0), env], buf.reward[steps, env], buf.done[steps, env], obs_n


# ----------------------------------------------------------------------------- training
METRIC_KEYS = (*EPISODE_METRICS, "loss", "q", "epsilon")  # a log block's metrics


def make_train(config) -> Trainer:
    """DQN's :class:`~baselines.harness.trainer.Trainer` (as :func:`baselines.ppo.make_train`'s; one update is one
    log block of ``iterations_per_log`` iterations, runner state ``(params, target params, optimizer state,
    replay buffer, env states, observations, key, gradient steps)``), run by the harness
    (:func:`baselines.harness.runner.run_seeds`, :func:`~baselines.harness.runner.run_chunked`). ``config``: a
    :class:`DQNConfig`, or a dict made into one (:meth:`DQNConfig.from_dict`); ``trainer.train_config`` is it,
    ``trainer.config`` its record (``config.json``)."""
    if isinstance(config, dict) and config.get("devices") is not None:
        raise ValueError("DQN does not shard over devices (devices / --devices is PPO only)")
    config = DQNConfig.coerce(config, where="dqn.make_train")
    if config.action_mode != "discrete":
        raise ValueError("DQN needs action_mode='discrete'")
    env, env_params = make_env(config)
    env = LogWrapper(env)
    num_actions = env.action_space().n
    network = QNetwork(num_actions, hidden=config.hidden)
    num_envs = config.num_envs
    rows = max(config.buffer_size // num_envs, config.n_step + 2)
    per_log = config.iterations_per_log
    num_logs = max(1, config.total_timesteps // (num_envs * per_log))
    total_iters = num_logs * per_log
    progress = Progress(config.num_seeds, num_logs, per_log * num_envs, config.log_every, name=f"dqn {config.env_id}")
    n, gamma = config.n_step, config.gamma
    tx = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(config.lr))

    def epsilon(it):
        frac = jnp.clip(it / (config.eps_fraction * total_iters), 0.0, 1.0)
        return config.eps_start + frac * (config.eps_end - config.eps_start)

    def loss_fn(params, target_params, batch):
        obs_t, a_t, rewards, dones, obs_n = batch
        q = network.apply(params, obs_t)
        q_sa = jnp.take_along_axis(q, a_t[:, None], axis=-1)[:, 0]
        q_next_online = network.apply(params, obs_n)
        q_next_target = network.apply(target_params, obs_n)
        target = jax.lax.stop_gradient(td_targets(rewards, dones, q_next_online, q_next_target, gamma, config.double_q))
        return optax.huber_loss(q_sa, target).mean(), q_sa.mean()

    init_params = params_initialiser(env, network, num_envs)

    def init_runner(key, env_params, params):
        """One seed's runner state before the first iteration: ``(params, target params, optimizer state,
        replay buffer, env states, observations, key, gradient steps)`` with the envs freshly reset."""
        key, _, obs, env_state = reset_envs(env, key, env_params, num_envs)
        return (
            params,
            params,
            tx.init(params),
            buffer_init(obs, rows, num_envs),
            env_state,
            obs,
            key,
            jnp.zeros((), jnp.int32),
        )

    def update(carry, block, env_params):
        """One log block (``iterations_per_log`` iterations) of a runner state ``carry``
        (:func:`init_runner`): ``(carry, metrics)``."""
        zero = jnp.zeros((), jnp.float32)

        def iteration(carry, it):
            params, target_params, opt_state, buf, env_state, obs, key, grad_steps = carry
            key, k_eps, k_rand, k_step, k_sample = jax.random.split(key, 5)
            q = network.apply(params, obs)
            explore = jax.random.uniform(k_eps, (num_envs,)) < epsilon(it)
            action = jnp.where(explore, jax.random.randint(k_rand, (num_envs,), 0, num_actions), q.argmax(-1))
            next_obs, env_state, reward, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(k_step, num_envs), env_state, action, env_params
            )
            done = jnp.logical_or(term, trunc)
            buf = buffer_add(buf, obs, action, reward, done)
            next_obs = preprocess_obs(next_obs)

            def learn(args):
                params, target_params, opt_state, grad_steps = args
                batch = buffer_sample(buf, k_sample, config.batch_size, n)
                (loss, q_mean), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, target_params, batch)
                updates, opt_state = tx.update(grads, opt_state, params)
                params = optax.apply_updates(params, updates)
                grad_steps = grad_steps + 1
                refresh = grad_steps % config.target_update_every == 0
                target_params = jax.tree.map(lambda t, p: jnp.where(refresh, p, t), target_params, params)
                return (params, target_params, opt_state, grad_steps), (loss, q_mean)

            can_learn = (
                (buf.filled * num_envs >= config.learning_starts) & (buf.filled > n) & (it % config.train_every == 0)
            )
            (params, target_params, opt_state, grad_steps), (loss, q_mean) = jax.lax.cond(
                can_learn, learn, lambda a: (a, (zero, zero)), (params, target_params, opt_state, grad_steps)
            )
            keep = {
                k: info[k]
                for k in (
                    "returned_episode",
                    "returned_episode_returns",
                    "returned_episode_lengths",
                    "returned_episode_success",
                )
            }
            out = {"info": keep, "loss": loss, "q": q_mean, "learned": can_learn.astype(jnp.float32)}
            return (params, target_params, opt_state, buf, env_state, next_obs, key, grad_steps), out

        its = block * per_log + jnp.arange(per_log)
        carry, out = jax.lax.scan(iteration, carry, its)
        learned = jnp.maximum(out["learned"].sum(), 1.0)
        metrics = {
            **episode_stats(out["info"]),
            "loss": out["loss"].sum() / learned,
            "q": out["q"].sum() / learned,
            "epsilon": epsilon(its[-1]),
        }
        if config.print_progress:
            ack = report(progress, block, metrics)
            metrics = {**metrics, "episodes": metrics["episodes"] + ack}
        return carry, metrics

    return Trainer(
        init_params=init_params,
        init_runner=init_runner,
        update=update,
        runner_params=lambda runner: runner[0],
        env=env,
        env_params=env_params,
        network=network,
        num_updates=num_logs,
        steps_per_update=per_log * num_envs,
        train_config=config,
        config=config.as_dict(),
        progress=progress,
        metric_keys=METRIC_KEYS,
    )


# python -m baselines.dqn and histojax train --algo dqn: options, command, entry point
add_arguments, run, main = trainer_command("dqn", make_train, DQNConfig, "log blocks", __doc__)


if __name__ == "__main__":
    raise SystemExit(main(compile_cache.setup(sys.argv[1:])))  # the persistent compilation cache, --no-compile-cache
