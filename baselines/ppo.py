"""PPO in the PureJaxRL style: the whole training run — rollouts with ``lax.scan`` over vmapped
environments, GAE, minibatch epochs — is one jitted function, vmapped over seeds.

    python -m baselines.ppo --env HistoJAX-Easy-v0 --with-position --seeds 4 --total-steps 500000 --out runs/ppo-easy

Writes to ``--out``: ``log.csv`` / ``log.json`` (per logged update: env steps, mean return,
success rate, mean episode length, mean steps to success), ``curve.png`` (learning curves, seed
mean and min–max band, random agent dashed), ``params.msgpack`` + ``config.json`` (the trained
parameters of every seed, flax msgpack; ``python -m baselines.evaluate runs/ppo-easy``), and
``checkpoint/``: the whole training state every ``checkpoint_every`` updates, from which ``--resume
runs/ppo-easy`` continues a killed run to the uninterrupted result (:func:`baselines.harness.runner.run_chunked`).

Seeds: ``make_train`` returns a :class:`~baselines.harness.trainer.Trainer` (one seed's pieces); the harness
runs it as one jitted program for all seeds (:func:`baselines.harness.runner.run_seeds`): ``jax.vmap`` over the keys
(default), or ``vmap_seeds=False`` to run them one after another with ``lax.map`` in the same
program (same results up to float rounding; on the 2-core CPU the two ran at 1,737 and 1,549 env
steps/s for 2 seeds). Initial parameters are always made with ``lax.map``: ``jit(vmap(init))`` of
flax's orthogonal initialisers (a batched QR) never finished on jaxlib 0.10's CPU backend.

Devices: ``--devices N`` (config ``devices``) splits the env batch over the first ``N`` devices
(``jax.sharding``, a ``Mesh`` with one axis ``"batch"``): env states, observations and the
rollout are sharded along the envs, each minibatch along its samples; parameters, optimizer
state and slide arrays are replicated, and XLA's SPMD partitioner adds the gradient all-reduce.
The same code runs on one CPU (``XLA_FLAGS=--xla_force_host_platform_device_count=N``), several
GPUs, or several hosts after ``jax.distributed.initialize()``. ``devices=None`` (default) adds
nothing to the program. ``--shard-slides`` (config ``shard_slides``) also splits the dataset's
slides over the devices (:mod:`histojax.sharding`): each device holds and draws only its own
slides, so slide memory per device falls as 1 / N (docs/scaling.md).

Observations are pooled to 32 px before they are stored (see :func:`networks.preprocess_obs`),
so a rollout of 64 envs × 64 steps needs ~13 MB, not ~200 MB. Time limits are treated as episode
ends in GAE (no bootstrap from the final observation), as in PureJaxRL.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.training.train_state import TrainState

from baselines.cell_set_networks import CellSetActorCritic, EpisodeTables, RecurrentCellSetActorCritic, uses_cell_sets
from baselines.common.config import EnvConfig
from baselines.common.devices import batch_mesh, check_rollout_memory, shard_batch
from baselines.common.env import env_vmap, episode_stats, make_env, params_initialiser, pin_env_shapes, reset_envs
from baselines.harness import cli
from baselines.harness.cli import trainer_command
from baselines.harness.logs import Progress, report
from baselines.harness.trainer import EPISODE_METRICS, Trainer
from baselines.networks import (
    ActorCritic,
    RecurrentActorCritic,
    is_discrete,
    policy_entropy,
    policy_log_prob,
    preprocess_obs,
    rollout_apply,
    rollout_sampler,
)
from histojax import compile_cache
from histojax.adapters.jax import LogWrapper


@dataclasses.dataclass(frozen=True)
class PPOConfig(EnvConfig):
    """PPO's settings, typed (``config.json`` records them, :meth:`as_dict`; ``--set KEY=VALUE`` changes any;
    :meth:`from_dict` makes one from a dict and refuses an unknown entry or a wrong type in one line). Steps are
    env steps, widths are units of a dense layer; ``lr`` is Adam's step size, the coefficients are loss weights."""

    algo: str = "ppo"  # the trainer (recorded in config.json)
    num_envs: int = 64  # parallel envs per seed
    num_steps: int = 64  # env steps per env per update
    total_timesteps: int = 500_000  # env steps per seed
    update_epochs: int = 2
    num_minibatches: int = 8
    minibatch_by: str = "sample"  # "sample": each minibatch a shuffle of all samples; "env": whole env sequences
    # (num_envs must divide by num_minibatches), so a minibatch holds only its envs' episodes and slides
    lr: float = 3e-4  # Adam learning rate
    anneal_lr: bool = True  # linear decay to 0
    gamma: float = 0.99  # discount
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    ent_coef: float = 0.01
    ent_coef_final: float | None = None  # entropy coefficient at the last update (linear from ent_coef); None: constant
    obs_norm: object = None  # feature observations standardised: None, "dataset" (mean / std of the
    # training env's feature grids, recorded as numbers), or {"mean", "std"}
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    hidden: int = 256  # network width
    cell_hidden: int = 32  # cell-set readers (glimpse, step_obs): width of the layers shared by the cells
    num_seeds: int = 1
    vmap_seeds: bool = True  # all seeds in one vmapped program
    log_every: int = 4  # updates per progress line
    print_progress: bool = True
    checkpoint_every: int = 50  # updates between checkpoints of the whole training state (0: only the end)
    devices: int | None = None  # shard the env batch over the first N devices
    shard_slides: bool = False  # with devices: split the dataset's slides over them


DEFAULTS = PPOConfig.defaults()  # the record of the default config (config.json's entries)


def settings(config) -> PPOConfig:
    """``config`` as a :class:`PPOConfig` (itself, or a subclass's, when it is one): a dict, e.g. a recorded
    ``config.json``, through :meth:`~baselines.common.config.EnvConfig.from_dict` with entries PPO has not ignored
    (an evaluated run's record may hold other trainers' entries)."""
    return config if isinstance(config, PPOConfig) else PPOConfig.from_dict(config, strict=False)


LOG_KEYS = ("returned_episode", "returned_episode_returns", "returned_episode_lengths", "returned_episode_success")
METRIC_KEYS = (*EPISODE_METRICS, "pg_loss", "v_loss", "entropy", "approx_kl")  # an update's metrics


class Transition(NamedTuple):
    """One rollout step (arrays with the env batch axis; time-major once scanned)."""

    done: jnp.ndarray  # float: this step ended the episode (GAE)
    action: jnp.ndarray
    value: jnp.ndarray
    reward: jnp.ndarray
    log_prob: jnp.ndarray
    obs: object
    info: dict
    first: object = None  # recurrent PPO: obs is the first of an episode (reset the memory first)


def make_network(config, env, network_cls=ActorCritic):
    """``network_cls`` (an actor-critic) sized for ``env``'s action space: ``n`` logits for discrete
    actions, the Box size for continuous ones; width ``hidden``; feature observations
    standardised by ``obs_norm`` when it holds numbers (``{"mean", "std"}``). For a ``glimpse``
    env with ``step_obs=True`` (the ``-v2`` ids) the cell-set reader of the same kind (feed-forward or
    recurrent, :class:`~baselines.cell_set_networks.CellSetActorCritic`), holding ``env``'s episode tables: its
    parameters fit any slide size, so the same parameters run on another dataset's env."""
    config = settings(config)
    space = env.action_space()
    action_dim = space.n if is_discrete(config.action_mode) else int(np.prod(space.shape))
    norm = config.obs_norm
    if isinstance(norm, dict):
        norm = (tuple(float(v) for v in norm["mean"]), tuple(float(v) for v in norm["std"]))
    elif norm is not None:
        raise ValueError(f"obs_norm={norm!r}: resolve it with resolve_obs_norm(config, env_params) first")
    if uses_cell_sets(env):  # a reader over the set of cells, built with this env's own per-slide tables
        cls = {ActorCritic: CellSetActorCritic, RecurrentActorCritic: RecurrentCellSetActorCritic}.get(network_cls)
        if cls is None:
            raise ValueError(f"{network_cls.__name__} cannot read a step_obs glimpse env; use PPO or recurrent PPO")
        return cls(
            action_dim=action_dim,
            tables=EpisodeTables(env.episode_tables()),
            action_mode=config.action_mode,
            hidden=config.hidden,
            obs_norm=norm,
            cell_hidden=config.cell_hidden,
        )
    return network_cls(action_dim=action_dim, action_mode=config.action_mode, hidden=config.hidden, obs_norm=norm)


def dataset_normaliser(slide, eps: float = 1e-3) -> dict:
    """``{"mean", "std"}`` (lists of ``D`` floats) of every feature vector of every level of the
    slide(s) ``slide`` (:class:`histojax.core.slide.SlideArrays`, one slide or a stacked dataset: only each
    slide's own rows count, not the padding); ``std`` at least ``eps``. For a training env this is a
    fixed per-dataset normaliser computed from the training slides only."""
    if slide.features is None:
        raise ValueError(
            "obs_norm='dataset' needs feature observations (obs_mode='features'; the slides have no "
            "feature grids loaded)"
        )
    feats = np.asarray(jax.device_get(slide.features), np.float64)
    widths = np.asarray(jax.device_get(slide.feature_grid_width)).reshape(-1, np.shape(slide.feature_grid_width)[-1])
    heights = np.asarray(jax.device_get(slide.feature_grid_height)).reshape(widths.shape)
    feats = feats.reshape(-1, *feats.shape[-2:])
    rows = np.concatenate([feats[i, : int((widths[i] * heights[i]).sum())] for i in range(feats.shape[0])])
    mean, std = rows.mean(0), np.maximum(rows.std(0), eps)
    return {"mean": mean.tolist(), "std": std.tolist()}


def resolve_obs_norm(config, env_params):
    """``config`` (a :class:`PPOConfig` or its dict; the same kind back) with ``obs_norm="dataset"`` replaced by
    :func:`dataset_normaliser` of the training env's slides (so ``config.json`` records the numbers and evaluation
    on other slides uses them)."""
    if settings(config).obs_norm == "dataset":
        norm = dataset_normaliser(env_params.slide)
        return config.replace(obs_norm=norm) if isinstance(config, PPOConfig) else {**config, "obs_norm": norm}
    return config


def entropy_coef(config, update_index, num_updates: int):
    """The entropy coefficient at update ``update_index``: ``ent_coef``, or with ``ent_coef_final``
    a linear anneal from ``ent_coef`` (first update) to ``ent_coef_final`` (last update)."""
    config = settings(config)
    if config.ent_coef_final is None:
        return config.ent_coef
    frac = jnp.clip(update_index / max(num_updates - 1, 1), 0.0, 1.0)
    return config.ent_coef + frac * (config.ent_coef_final - config.ent_coef)


def gae(traj: Transition, last_value, gamma: float, lam: float):
    """Generalised advantage estimates and value targets over a time-major trajectory."""

    def body(carry, t):
        adv, next_value = carry
        delta = t.reward + gamma * next_value * (1 - t.done) - t.value
        adv = delta + gamma * lam * (1 - t.done) * adv
        return (adv, t.value), adv

    _, advantages = jax.lax.scan(body, (jnp.zeros_like(last_value), last_value), traj, reverse=True, unroll=8)
    return advantages, advantages + traj.value


def make_optimizer(config, num_updates: int):
    """Adam with global-norm clipping; the learning rate decays linearly to 0 over
    ``num_updates`` updates of ``num_minibatches × update_epochs`` steps (``anneal_lr``)."""
    config = settings(config)

    def lr_schedule(count):
        frac = 1.0 - (count // (config.num_minibatches * config.update_epochs)) / num_updates
        return config.lr * frac

    return optax.chain(
        optax.clip_by_global_norm(config.max_grad_norm),
        optax.adam(lr_schedule if config.anneal_lr else config.lr, eps=1e-5),
    )


def clipped_loss(pi, value, traj, adv, target, config, ent_coef=None):
    """PPO's loss on a minibatch (any batch shape): clipped policy objective on normalised
    advantages, clipped value loss, entropy bonus. ``pi``/``value``: the network's outputs for
    ``traj.obs`` now; ``traj.action``/``traj.log_prob``/``traj.value``: from the rollout.
    ``ent_coef``: the entropy coefficient now (:func:`entropy_coef`; default ``ent_coef``).
    Returns ``(total, (pg_loss, v_loss, entropy, approx_kl))``."""
    config = settings(config)
    mode = config.action_mode
    log_prob = policy_log_prob(pi, traj.action, mode)
    v_clipped = traj.value + jnp.clip(value - traj.value, -config.clip_eps, config.clip_eps)
    v_loss = 0.5 * jnp.maximum((value - target) ** 2, (v_clipped - target) ** 2).mean()
    ratio = jnp.exp(log_prob - traj.log_prob)
    adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    pg_loss = -jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - config.clip_eps, 1 + config.clip_eps) * adv).mean()
    entropy = policy_entropy(pi, mode).mean()
    total = pg_loss + config.vf_coef * v_loss - (config.ent_coef if ent_coef is None else ent_coef) * entropy
    approx_kl = ((ratio - 1) - (log_prob - traj.log_prob)).mean()
    return total, (pg_loss, v_loss, entropy, approx_kl)


def split_minibatches(key, data, num_minibatches: int, by_env: bool = False):
    """One epoch's minibatches of an update's time-major rollout ``data`` (a pytree of ``(num_steps, num_envs,
    ...)`` arrays), shuffled with ``key``: a pytree of ``(num_minibatches, num_steps * num_envs / num_minibatches,
    ...)`` arrays. ``by_env=False`` (PPO's ``minibatch_by="sample"``): every sample shuffled; ``by_env=True``
    (``"env"``): the envs shuffled, each minibatch the whole ``num_steps``-step sequences of ``num_envs /
    num_minibatches`` envs (so it holds only those envs' episodes, and their slides)."""
    num_steps, num_envs = jax.tree.leaves(data)[0].shape[:2]
    batch = num_steps * num_envs
    if by_env:
        perm = jax.random.permutation(key, num_envs)
        flat = jax.tree.map(lambda a: jnp.swapaxes(a, 0, 1)[perm].reshape(batch, *a.shape[2:]), data)
    else:
        perm = jax.random.permutation(key, batch)
        flat = jax.tree.map(lambda a: a.reshape(batch, *a.shape[2:])[perm], data)
    return jax.tree.map(lambda a: a.reshape(num_minibatches, batch // num_minibatches, *a.shape[1:]), flat)


def run_epochs(state, key, loss_fn, minibatches, epochs: int):
    """``epochs`` passes over one update's data: each pass splits ``key`` once, takes the minibatches
    ``minibatches(k)`` (a pytree with a leading minibatch axis, shuffled with ``k``) and one gradient
    step of ``loss_fn(params, mb) -> (loss, aux)`` per minibatch. Returns ``(state, key, aux)``
    with ``aux`` stacked ``(epochs, minibatches, ...)``."""

    def epoch(carry, _):
        state, key = carry
        key, k_perm = jax.random.split(key)

        def minibatch_step(state, mb):
            grads, aux = jax.grad(loss_fn, has_aux=True)(state.params, mb)
            return state.apply_gradients(grads=grads), aux

        state, aux = jax.lax.scan(minibatch_step, state, minibatches(k_perm))
        return (state, key), aux

    (state, key), aux = jax.lax.scan(epoch, (state, key), None, epochs)
    return state, key, aux


def update_metrics(info: dict, aux, progress, update_index, config) -> dict:
    """One update's metrics: episode statistics of the rollout's ``info`` and the means of the
    losses ``aux`` (from :func:`clipped_loss`); printed through ``progress`` when asked (``print_progress``)."""
    pg_loss, v_loss, entropy, kl = (a.mean() for a in aux)
    metrics = {**episode_stats(info), "pg_loss": pg_loss, "v_loss": v_loss, "entropy": entropy, "approx_kl": kl}
    if settings(config).print_progress:
        ack = report(progress, update_index, metrics)
        metrics = {**metrics, "episodes": metrics["episodes"] + ack}
    return metrics


def make_train(config) -> Trainer:
    """PPO's :class:`~baselines.harness.trainer.Trainer`: one seed's ``init_params``, ``init_runner`` (runner state
    ``(train state, env states, observations, key)``) and ``update`` (``num_steps`` steps of every env, GAE,
    ``update_epochs`` epochs of ``num_minibatches`` minibatches), with the env, its params (slide arrays, an
    argument of the jitted program, not a constant), the network and ``num_updates``. The harness runs it:
    :func:`baselines.harness.runner.run_seeds` (all seeds in one jitted program, ``jax.vmap`` over keys or
    ``lax.map`` with ``vmap_seeds=False``), :func:`~baselines.harness.runner.run_chunked` (in chunks with
    checkpoints). ``devices = N`` shards the env batch over ``N`` devices (``trainer.mesh``).

    ``config``: a :class:`PPOConfig`, or a dict made into one with :meth:`PPOConfig.from_dict` (an unknown entry
    or a wrong type is refused in one line). It stays typed until the env and the network are built;
    ``trainer.train_config`` is the config as trained (``obs_norm`` resolved, the env's shapes pinned) and
    ``trainer.config`` its record, the ``config.json`` the run writes (:meth:`PPOConfig.as_dict`)."""
    config = PPOConfig.coerce(config, where="ppo.make_train")
    num_envs, num_steps = config.num_envs, config.num_steps
    mesh = batch_mesh(config.devices, num_envs)
    sharded = bool(config.shard_slides)
    if sharded and mesh is None:
        raise ValueError("shard_slides=True splits the slides over the devices: give devices=N too")
    env, env_params = make_env(config, mesh=mesh)
    config = pin_env_shapes(resolve_obs_norm(config, env_params), env_params)
    check_rollout_memory(env, env_params, config)
    env = LogWrapper(env)
    reset_all = env_vmap(env.reset, 1, mesh, sharded)
    step_all = env_vmap(env.step, 3, mesh, sharded)
    network = make_network(config, env)
    mode = config.action_mode
    sample = rollout_sampler(network, mode)
    num_updates = max(1, config.total_timesteps // (num_envs * num_steps))
    batch = num_envs * num_steps
    minibatch = batch // config.num_minibatches
    assert minibatch * config.num_minibatches == batch, "num_envs * num_steps must divide by num_minibatches"
    if config.minibatch_by not in ("sample", "env"):
        raise ValueError(f"minibatch_by={config.minibatch_by!r}: 'sample' or 'env'")
    by_env = config.minibatch_by == "env"
    if by_env and num_envs % config.num_minibatches:
        raise ValueError(
            f"minibatch_by='env': num_envs={num_envs} must divide by num_minibatches={config.num_minibatches}"
        )
    if mesh is not None and minibatch % mesh.size:
        raise ValueError(
            f"the minibatch ({minibatch} = num_envs * num_steps / num_minibatches) must divide by devices={mesh.size}"
        )
    shard = functools.partial(shard_batch, mesh)  # identity without devices
    progress = Progress(config.num_seeds, num_updates, batch, config.log_every, name=f"ppo {config.env_id}")

    init_params = params_initialiser(env, network, num_envs, reset_all)

    tx = make_optimizer(config, num_updates)

    def init_runner(key, env_params, params):
        """One seed's runner state before the first update: ``(train state, env states, observations, key)``
        with the envs freshly reset."""
        key, _, obs0, env_state = reset_envs(env, key, env_params, num_envs, reset_all)
        obs0, env_state = shard((obs0, env_state))
        return TrainState.create(apply_fn=network.apply, params=params, tx=tx), env_state, obs0, key

    def update(carry, update_index, env_params):
        """One PPO update (``num_steps`` steps of every env, GAE, minibatch epochs) of a runner state
        ``carry`` (:func:`init_runner`): ``(carry, metrics)``."""
        policy = rollout_apply(network, carry[0].params)  # the params are fixed during the rollout

        def env_step(carry, _):
            state, env_state, obs, key = carry
            key, k_act, k_step = jax.random.split(key, 3)
            pi, value = policy(obs)
            action = sample(k_act, pi)
            log_prob = policy_log_prob(pi, action, mode)
            next_obs, env_state, reward, term, trunc, info = step_all(
                jax.random.split(k_step, num_envs), env_state, action, env_params
            )
            keep = {k: info[k] for k in LOG_KEYS}
            done = jnp.logical_or(term, trunc).astype(jnp.float32)
            t = shard(Transition(done, action, value, reward, log_prob, obs, keep))
            next_obs, env_state = shard((preprocess_obs(next_obs), env_state))
            return (state, env_state, next_obs, key), t

        (state, env_state, obs, key), traj = jax.lax.scan(env_step, carry, None, num_steps)
        _, last_value = policy(obs)
        advantages, targets = gae(traj, last_value, config.gamma, config.gae_lambda)

        def loss_fn(params, mb):
            traj, adv, target = mb
            pi, value = network.apply(params, traj.obs)
            return clipped_loss(pi, value, traj, adv, target, config, entropy_coef(config, update_index, num_updates))

        def minibatches(k_perm):
            mbs = split_minibatches(k_perm, (traj, advantages, targets), config.num_minibatches, by_env)
            return shard(mbs, axis=1)  # each minibatch split over the devices

        state, key, aux = run_epochs(state, key, loss_fn, minibatches, config.update_epochs)
        metrics = update_metrics(traj.info, aux, progress, update_index, config)
        return (state, env_state, obs, key), metrics

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
        mesh=mesh,
        metric_keys=METRIC_KEYS,
    )


def parse_args(argv=None, defaults=DEFAULTS, description=__doc__):
    """The baselines' command line (:func:`baselines.harness.cli.parse_args`) with PPO's defaults."""
    return cli.parse_args(argv, defaults, description)


def config_from_args(args, defaults=DEFAULTS) -> dict:
    """The config of parsed arguments (:func:`baselines.harness.cli.config_from_args`) with PPO's defaults."""
    return cli.config_from_args(args, defaults)


# python -m baselines.ppo and histojax train --algo ppo: options, command, entry point
add_arguments, run, main = trainer_command("ppo", make_train, PPOConfig, "updates", __doc__)


if __name__ == "__main__":
    raise SystemExit(main(compile_cache.setup(sys.argv[1:])))  # the persistent compilation cache, --no-compile-cache
