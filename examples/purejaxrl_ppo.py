"""PPO on histojax in one file, in PureJaxRL's shape: ``make_train(config)`` returns ``train(rng)``,
one jittable function holding the whole run (``lax.scan`` over updates; each update a ``lax.scan``
rollout of vmapped envs, GAE, minibatch epochs). Nothing here comes from ``baselines``: only
``histojax.make`` and histojax's ``LogWrapper`` (``histojax.adapters.jax``).

    python examples/purejaxrl_ppo.py                       # Easy on the sample slide, 1 seed, 163,840 env steps
    python examples/purejaxrl_ppo.py --seeds 3 --total-timesteps 163840 --out ppo.json

Observations: ``HistoJAX-Easy-v0`` with ``with_position=True`` gives ``{"pixels": (128, 128, 3) uint8,
"position": (3,) float32}``. :func:`flatten_obs` average-pools the pixels to 16 × 16, scales them
to [0, 1] and concatenates the position: one ``(771,)`` float vector, which the two-layer tanh MLPs
of :class:`ActorCritic` read (PureJaxRL's network for flat observations).

Seeds run one after another through the same compiled ``train`` (``jax.jit(train)`` once, called per
key); PureJaxRL's ``jax.vmap(train)`` over keys also works in principle, but a vmapped orthogonal
initialiser (a batched QR) compiles very slowly on XLA's CPU backend.

Prints, per seed, the success rate of the last update's finished training episodes and an evaluation
of the trained policy on fresh episodes (sampled actions): success rate, mean return, mean length.
Figures against ``baselines.ppo``: docs/results/examples.md.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.linen.initializers import constant, orthogonal
from flax.training.train_state import TrainState

import histojax
from histojax.adapters.jax import LogWrapper

POOL = 8  # 128 px views -> 16 x 16 x 3 pooled pixels

CONFIG = {
    "ENV_ID": "HistoJAX-Easy-v0",
    "ENV_KWARGS": {"with_position": True},
    "LR": 3e-4,
    "NUM_ENVS": 64,
    "NUM_STEPS": 64,
    "TOTAL_TIMESTEPS": 163_840,
    "UPDATE_EPOCHS": 2,
    "NUM_MINIBATCHES": 8,
    "GAMMA": 0.99,
    "GAE_LAMBDA": 0.95,
    "CLIP_EPS": 0.2,
    "ENT_COEF": 0.01,
    "VF_COEF": 0.5,
    "MAX_GRAD_NORM": 0.5,
    "HIDDEN": 256,
    "ANNEAL_LR": True,
}


def flatten_obs(obs) -> jax.Array:
    """A histojax observation → one float vector per env: ``{"pixels": (..., H, W, 3) uint8,
    "position": (..., 3)}`` (or pixels alone) → ``(..., (H/8)·(W/8)·3 [+ 3])`` float32, the pixels
    average-pooled over 8 × 8 blocks and scaled to [0, 1]."""
    pixels = obs["pixels"] if isinstance(obs, dict) else obs
    *batch, h, w, c = pixels.shape
    x = pixels.astype(jnp.float32).reshape(*batch, h // POOL, POOL, w // POOL, POOL, c).mean(axis=(-4, -2)) / 255.0
    parts = [x.reshape(*batch, -1)]
    if isinstance(obs, dict) and "position" in obs:
        parts.append(obs["position"].astype(jnp.float32))
    return jnp.concatenate(parts, axis=-1)


class ActorCritic(nn.Module):
    """Separate actor and critic MLPs (two tanh layers each): flat obs ``(B, D)`` →
    ``(logits (B, action_dim), value (B,))``."""

    action_dim: int
    hidden: int = 256

    @nn.compact
    def __call__(self, x):
        a = x
        for _ in range(2):
            a = nn.tanh(nn.Dense(self.hidden, kernel_init=orthogonal(np.sqrt(2)), bias_init=constant(0.0))(a))
        logits = nn.Dense(self.action_dim, kernel_init=orthogonal(0.01), bias_init=constant(0.0))(a)
        c = x
        for _ in range(2):
            c = nn.tanh(nn.Dense(self.hidden, kernel_init=orthogonal(np.sqrt(2)), bias_init=constant(0.0))(c))
        value = nn.Dense(1, kernel_init=orthogonal(1.0), bias_init=constant(0.0))(c)
        return logits, value[..., 0]


class Transition(NamedTuple):
    """One rollout step of every env (time-major ``(NUM_STEPS, NUM_ENVS, ...)`` once scanned)."""

    done: jnp.ndarray
    action: jnp.ndarray
    value: jnp.ndarray
    reward: jnp.ndarray
    log_prob: jnp.ndarray
    obs: jnp.ndarray
    info: dict


def _log_prob(logits, action):
    """Log-probability ``(B,)`` of integer ``action (B,)`` under categorical ``logits (B, A)``."""
    return jnp.take_along_axis(jax.nn.log_softmax(logits), action[..., None], axis=-1)[..., 0]


def _entropy(logits):
    """Entropy ``(B,)`` of categorical ``logits (B, A)`` (nats)."""
    logp = jax.nn.log_softmax(logits)
    return -(jnp.exp(logp) * logp).sum(-1)


def make_env(config: dict, auto_reset: bool = True):
    """``(LogWrapper(env), env_params)`` for ``config["ENV_ID"]`` with ``config["ENV_KWARGS"]``."""
    env, env_params = histojax.make(config["ENV_ID"], auto_reset=auto_reset, **config.get("ENV_KWARGS", {}))
    return LogWrapper(env), env_params


def make_train(config: dict):
    """``train(rng) -> {"runner_state", "metrics"}`` for ``config`` (keys as :data:`CONFIG`); jittable.
    ``metrics`` holds the ``LogWrapper`` info of every step, ``(NUM_UPDATES, NUM_STEPS, NUM_ENVS)``;
    ``runner_state[0].params`` are the trained network's parameters."""
    config = {**CONFIG, **config}
    config["NUM_UPDATES"] = config["TOTAL_TIMESTEPS"] // config["NUM_STEPS"] // config["NUM_ENVS"]
    config["MINIBATCH_SIZE"] = config["NUM_ENVS"] * config["NUM_STEPS"] // config["NUM_MINIBATCHES"]
    env, env_params = make_env(config)
    num_actions = env.action_space(env_params).n

    def linear_schedule(count):
        frac = 1.0 - (count // (config["NUM_MINIBATCHES"] * config["UPDATE_EPOCHS"])) / config["NUM_UPDATES"]
        return config["LR"] * frac

    def train(rng):
        # INIT NETWORK
        network = ActorCritic(num_actions, hidden=config["HIDDEN"])
        rng, _rng = jax.random.split(rng)
        obs_dim = flatten_obs(env.observation_space(env_params).sample(_rng)).shape[-1]
        network_params = network.init(_rng, jnp.zeros((1, obs_dim)))
        lr = linear_schedule if config["ANNEAL_LR"] else config["LR"]
        tx = optax.chain(optax.clip_by_global_norm(config["MAX_GRAD_NORM"]), optax.adam(lr, eps=1e-5))
        train_state = TrainState.create(apply_fn=network.apply, params=network_params, tx=tx)

        # INIT ENV
        rng, _rng = jax.random.split(rng)
        reset_rng = jax.random.split(_rng, config["NUM_ENVS"])
        obsv, env_state = jax.vmap(env.reset, in_axes=(0, None))(reset_rng, env_params)
        obsv = flatten_obs(obsv)

        # TRAIN LOOP
        def _update_step(runner_state, unused):
            # COLLECT TRAJECTORIES
            def _env_step(runner_state, unused):
                train_state, env_state, last_obs, rng = runner_state
                rng, _rng = jax.random.split(rng)
                logits, value = network.apply(train_state.params, last_obs)
                action = jax.random.categorical(_rng, logits)
                log_prob = _log_prob(logits, action)

                rng, _rng = jax.random.split(rng)
                rng_step = jax.random.split(_rng, config["NUM_ENVS"])
                obsv, env_state, reward, terminated, truncated, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                    rng_step, env_state, action, env_params
                )
                done = jnp.logical_or(terminated, truncated)
                info = {
                    k: info[k]
                    for k in (
                        "returned_episode",
                        "returned_episode_returns",
                        "returned_episode_lengths",
                        "returned_episode_success",
                    )
                }
                transition = Transition(done, action, value, reward, log_prob, last_obs, info)
                return (train_state, env_state, flatten_obs(obsv), rng), transition

            runner_state, traj_batch = jax.lax.scan(_env_step, runner_state, None, config["NUM_STEPS"])

            # CALCULATE ADVANTAGE (time limits end episodes, as in PureJaxRL: no bootstrap past them)
            train_state, env_state, last_obs, rng = runner_state
            _, last_val = network.apply(train_state.params, last_obs)

            def _calculate_gae(traj_batch, last_val):
                def _get_advantages(gae_and_next_value, transition):
                    gae, next_value = gae_and_next_value
                    done, value, reward = transition.done, transition.value, transition.reward
                    delta = reward + config["GAMMA"] * next_value * (1 - done) - value
                    gae = delta + config["GAMMA"] * config["GAE_LAMBDA"] * (1 - done) * gae
                    return (gae, value), gae

                _, advantages = jax.lax.scan(
                    _get_advantages, (jnp.zeros_like(last_val), last_val), traj_batch, reverse=True, unroll=16
                )
                return advantages, advantages + traj_batch.value

            advantages, targets = _calculate_gae(traj_batch, last_val)

            # UPDATE NETWORK
            def _update_epoch(update_state, unused):
                def _update_minbatch(train_state, batch_info):
                    traj_batch, advantages, targets = batch_info

                    def _loss_fn(params, traj_batch, gae, targets):
                        logits, value = network.apply(params, traj_batch.obs)
                        log_prob = _log_prob(logits, traj_batch.action)

                        # CALCULATE VALUE LOSS
                        value_pred_clipped = traj_batch.value + (value - traj_batch.value).clip(
                            -config["CLIP_EPS"], config["CLIP_EPS"]
                        )
                        value_losses = jnp.square(value - targets)
                        value_losses_clipped = jnp.square(value_pred_clipped - targets)
                        value_loss = 0.5 * jnp.maximum(value_losses, value_losses_clipped).mean()

                        # CALCULATE ACTOR LOSS
                        ratio = jnp.exp(log_prob - traj_batch.log_prob)
                        gae = (gae - gae.mean()) / (gae.std() + 1e-8)
                        loss_actor1 = ratio * gae
                        loss_actor2 = jnp.clip(ratio, 1.0 - config["CLIP_EPS"], 1.0 + config["CLIP_EPS"]) * gae
                        loss_actor = -jnp.minimum(loss_actor1, loss_actor2).mean()
                        entropy = _entropy(logits).mean()

                        total_loss = loss_actor + config["VF_COEF"] * value_loss - config["ENT_COEF"] * entropy
                        return total_loss, (value_loss, loss_actor, entropy)

                    grad_fn = jax.value_and_grad(_loss_fn, has_aux=True)
                    total_loss, grads = grad_fn(train_state.params, traj_batch, advantages, targets)
                    train_state = train_state.apply_gradients(grads=grads)
                    return train_state, total_loss

                train_state, traj_batch, advantages, targets, rng = update_state
                rng, _rng = jax.random.split(rng)
                batch_size = config["MINIBATCH_SIZE"] * config["NUM_MINIBATCHES"]
                permutation = jax.random.permutation(_rng, batch_size)
                batch = (traj_batch, advantages, targets)
                batch = jax.tree.map(lambda x: x.reshape((batch_size,) + x.shape[2:]), batch)
                shuffled_batch = jax.tree.map(lambda x: jnp.take(x, permutation, axis=0), batch)
                minibatches = jax.tree.map(
                    lambda x: jnp.reshape(x, [config["NUM_MINIBATCHES"], -1] + list(x.shape[1:])), shuffled_batch
                )
                train_state, total_loss = jax.lax.scan(_update_minbatch, train_state, minibatches)
                return (train_state, traj_batch, advantages, targets, rng), total_loss

            update_state = (train_state, traj_batch, advantages, targets, rng)
            update_state, loss_info = jax.lax.scan(_update_epoch, update_state, None, config["UPDATE_EPOCHS"])
            train_state, rng = update_state[0], update_state[-1]
            metric = traj_batch.info
            return (train_state, env_state, last_obs, rng), metric

        rng, _rng = jax.random.split(rng)
        runner_state = (train_state, env_state, obsv, _rng)
        runner_state, metric = jax.lax.scan(_update_step, runner_state, None, config["NUM_UPDATES"])
        return {"runner_state": runner_state, "metrics": metric}

    return train


def make_evaluate(config: dict, num_episodes: int = 256):
    """``evaluate(params, rng) -> {"success", "return", "length"}``: ``num_episodes`` fresh episodes
    (no auto-reset; each runs to its end or the step limit) with actions sampled from the policy;
    success rate and mean return / length (steps) over them. Jittable."""
    config = {**CONFIG, **config}
    env, env_params = make_env(config, auto_reset=False)
    network = ActorCritic(env.action_space(env_params).n, hidden=config["HIDDEN"])
    steps = int(env_params.max_steps_in_episode)

    def evaluate(params, rng):
        rng, _rng = jax.random.split(rng)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(_rng, num_episodes), env_params)

        def body(carry, key):
            obs, state, done, ret, length, success = carry
            k_act, k_step = jax.random.split(key)
            logits, _ = network.apply(params, flatten_obs(obs))
            action = jax.random.categorical(k_act, logits)
            obs2, state2, reward, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(k_step, num_episodes), state, action, env_params
            )
            live = ~done
            ret = ret + jnp.where(live, reward, 0.0)
            length = length + live
            success = success | (live & info["success"])
            done = done | term | trunc
            return (obs2, state2, done, ret, length, success), None

        zeros = jnp.zeros(num_episodes)
        init = (obs, state, jnp.zeros(num_episodes, bool), zeros, zeros, jnp.zeros(num_episodes, bool))
        (_, _, _, ret, length, success), _ = jax.lax.scan(body, init, jax.random.split(rng, steps))
        return {"success": success.mean(), "return": ret.mean(), "length": length.mean()}

    return evaluate


def final_training_success(metrics: dict) -> float:
    """Success rate of the episodes that finished during the last update (nan if none)."""
    done = np.asarray(metrics["returned_episode"][-1])
    succ = np.asarray(metrics["returned_episode_success"][-1])
    return float(succ[done].mean()) if done.any() else float("nan")


def main(argv=None) -> dict:
    """Train ``--seeds`` seeds, evaluate each; print one line per seed and write ``--out`` (JSON) when given."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default=CONFIG["ENV_ID"])
    p.add_argument("--total-timesteps", type=int, default=CONFIG["TOTAL_TIMESTEPS"])
    p.add_argument("--num-envs", type=int, default=CONFIG["NUM_ENVS"])
    p.add_argument("--num-steps", type=int, default=CONFIG["NUM_STEPS"])
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--seed", type=int, default=0, help="first seed")
    p.add_argument("--eval-episodes", type=int, default=256)
    p.add_argument("--out", default=None, help="JSON file for the per-seed figures")
    args = p.parse_args(argv)
    config = {
        **CONFIG,
        "ENV_ID": args.env,
        "TOTAL_TIMESTEPS": args.total_timesteps,
        "NUM_ENVS": args.num_envs,
        "NUM_STEPS": args.num_steps,
    }
    t0 = time.perf_counter()
    key0 = jax.random.PRNGKey(args.seed)
    train = jax.jit(make_train(config)).lower(key0).compile()  # compiled once, run per seed
    evaluate = jax.jit(make_evaluate(config, args.eval_episodes))
    compile_s = time.perf_counter() - t0
    print(f"compiled in {compile_s:.0f} s", flush=True)
    rows = []
    for seed in range(args.seed, args.seed + args.seeds):
        t = time.perf_counter()
        out = jax.block_until_ready(train(jax.random.PRNGKey(seed)))
        train_s = time.perf_counter() - t
        ev = jax.device_get(evaluate(out["runner_state"][0].params, jax.random.PRNGKey(10_000 + seed)))
        row = {
            "seed": seed,
            "train_seconds": train_s,
            "train_success_last_update": final_training_success(out["metrics"]),
            **{f"eval_{k}": float(v) for k, v in ev.items()},
        }
        rows.append(row)
        print(
            f"seed {seed}: {train_s:.0f} s, training success (last update) {row['train_success_last_update']:.1%}, "
            f"eval success {row['eval_success']:.1%}, return {row['eval_return']:.2f}, "
            f"length {row['eval_length']:.1f}",
            flush=True,
        )
    result = {"config": config, "seeds": rows, "compile_seconds": compile_s, "wall_seconds": time.perf_counter() - t0}
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    main()
