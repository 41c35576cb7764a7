"""Shared by the trainers: making the env from a config, episode statistics, progress printing,
checkpoints (flax.serialization msgpack), logs (CSV / JSON), learning-curve PNGs (Pillow) and
sharding the env batch over devices (``--devices N``).

Modules: ``config`` (the typed trainer config), ``env``, ``devices``, ``logs``, ``runner``, ``cli``."""
from __future__ import annotations

from baselines.common.config import (ConfigError, EnvConfig, MAKE_ARGUMENTS, OLDER_SPELLINGS, canonical_config,
                                     env_overrides)
from baselines.common.env import (env_config, pin_env_shapes, make_env, env_vmap, reset_envs, params_initialiser,
                                  episode_stats, make_random_rollout, random_agent_reference)
from baselines.common.devices import device_memory_bytes, check_rollout_memory, batch_mesh, shard_batch, replicate_on
from baselines.common.logs import (Progress, report, save_checkpoint, load_checkpoint, write_logs, finite_mean,
                                   finite_extreme, smooth, tensorboard_writer)
from baselines.common.runner import (seeds_runner, CHECKPOINT_DIR, RUNNER_FORMAT, chunk_plan, scan_updates,
                                     chunked_runner, save_runner, config_digest, load_runner, run_chunked, finish_run,
                                     resume_config, compile_and_run, run_and_save)
from baselines.common.cli import add_arguments, parse_args, config_from_args, train_and_save, trainer_command
from baselines.curves import plot_curves  # the learning-curve PNG, for callers of common
from data_tools.errors import HistojaxDataError  # what a resume refuses with

__all__ = ['CHECKPOINT_DIR', 'ConfigError', 'EnvConfig', 'HistojaxDataError', 'MAKE_ARGUMENTS', 'OLDER_SPELLINGS',
           'Progress', 'RUNNER_FORMAT',
           'add_arguments', 'batch_mesh', 'canonical_config', 'check_rollout_memory', 'chunk_plan', 'chunked_runner',
           'compile_and_run', 'config_digest', 'config_from_args', 'device_memory_bytes', 'env_config', 'env_overrides', 'env_vmap',
           'episode_stats', 'finish_run', 'finite_extreme', 'finite_mean', 'load_checkpoint', 'load_runner', 'make_env',
           'make_random_rollout', 'params_initialiser', 'parse_args', 'pin_env_shapes', 'plot_curves',
           'random_agent_reference', 'replicate_on', 'report', 'reset_envs', 'resume_config', 'run_and_save',
           'run_chunked', 'save_checkpoint', 'save_runner', 'scan_updates', 'seeds_runner', 'shard_batch', 'smooth',
           'tensorboard_writer', 'train_and_save', 'trainer_command', 'write_logs']
