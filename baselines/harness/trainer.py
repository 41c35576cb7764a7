"""A trainer, declared: what ``make_train`` of :mod:`baselines.ppo`, :mod:`baselines.ppo_rnn` and
:mod:`baselines.dqn` returns, and all the harness (:mod:`baselines.harness.runner`) needs to run it.

The trainer holds one seed's pieces, unjitted: how to make its parameters, its runner state, and one update of
that state. The harness owns the one loop over updates (:func:`baselines.harness.runner.scan_updates`), the
seeds (``jax.vmap`` or ``lax.map``), the jit, the chunks and the checkpoints."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

EPISODE_METRICS = ("episodes", "return", "success", "length", "steps_to_success")  # episode_stats's keys


@dataclasses.dataclass(frozen=True, eq=False)
class Trainer:
    """One algorithm's training, for one seed; the harness runs it for many.

    Fields (``runner`` is the algorithm's runner state of one seed: a pytree of arrays holding the train
    state, the env states, the observations and the PRNG key):

    - ``init_params(key, env_params) -> params``: the network's initial parameters of one seed (a pytree).
    - ``init_runner(key, env_params, params) -> runner``: the runner state before the first update, the envs
      freshly reset (``num_envs`` of them; the optimizer state fresh).
    - ``update(runner, update_index, env_params) -> (runner, metrics)``: one update (PPO: ``num_steps`` env
      steps of every env, GAE, the minibatch epochs; DQN: one log block of ``iterations_per_log``
      iterations); ``update_index`` an int32 scalar (may be traced), ``metrics`` a dict of float32 scalars
      named ``metric_keys``.
    - ``runner_params(runner) -> params``: the network parameters in a runner state.
    - ``env``: the env (wrapped in :class:`~histojax.adapters.jax.LogWrapper`); ``env_params``: its params
      (the slide arrays), an argument of the jitted program, not a constant.
    - ``network``: the flax module whose ``apply`` takes ``params``.
    - ``num_updates``: updates in the run (int); ``steps_per_update``: env steps per seed in one update (int,
      ``num_envs × num_steps`` for PPO), so a run is ``num_updates × steps_per_update`` env steps per seed.
    - ``train_config``: the typed config as trained (``obs_norm`` resolved, the env's shapes pinned);
      ``config``: its record (a dict, ``config.json``).
    - ``progress``: the :class:`~baselines.harness.logs.Progress` the updates print through.
    - ``mesh``: the ``jax.sharding.Mesh`` the env batch is split over (``devices=N``), or ``None``.
    - ``metric_keys``: the names of ``update``'s metrics (tuple of str).
    """

    init_params: Callable[..., Any]
    init_runner: Callable[..., Any]
    update: Callable[..., Any]
    runner_params: Callable[[Any], Any]
    env: Any
    env_params: Any
    network: Any
    num_updates: int
    steps_per_update: int
    train_config: Any
    config: dict
    progress: Any
    mesh: Any = None
    metric_keys: tuple[str, ...] = ()
