"""A run's recorded config, typed: :func:`read_run_config` reads the ``config.json`` a trainer wrote (or its dict)
as the trainer's config (:class:`baselines.ppo.PPOConfig`, :class:`baselines.dqn.DQNConfig`,
:class:`baselines.ppo_rnn.PPORNNConfig`), leniently, for the commands that read runs (evaluate, the readers'
pipeline, the diagnosis, the experiment drivers).

Lenient, as a run's reader has always been, where a trainer's entry is strict
(:meth:`~baselines.common.config.EnvConfig.from_dict`): a record without ``algo`` is PPO's (DQN's when it
records ``buffer_size``, as older DQN runs did); an entry no trainer writes is a warning naming the file and the
closest known entry, not a refusal; entries of another trainer are ignored. What cannot be read is one line naming
the file (``HistojaxDataError``): a record that is not an object, a value of the wrong type, a network width that is
not a whole number of at least 1."""

from __future__ import annotations

import difflib
import json
import os
from pathlib import Path

from baselines import dqn, ppo, ppo_rnn
from baselines.common.config import OLDER_SPELLINGS, ConfigError, EnvConfig
from data_tools.errors import HistojaxDataError

RUN_CONFIGS = {"ppo": ppo.PPOConfig, "dqn": dqn.DQNConfig, "ppo_rnn": ppo_rnn.PPORNNConfig}
"""The config class of each trainer, by the ``algo`` its ``config.json`` records."""


def known_config_keys() -> set[str]:
    """The ``config.json`` keys some trainer writes (its defaults), ``seed``, and older spellings."""
    return {*ppo.DEFAULTS, *dqn.DEFAULTS, *ppo_rnn.DEFAULTS, "seed", *OLDER_SPELLINGS}


def algo_of(record: dict) -> str:
    """The trainer of a recorded config: its ``algo``; without one (older runs), ``"dqn"`` when it records
    ``buffer_size``, else ``"ppo"``."""
    return record.get("algo") or ("dqn" if "buffer_size" in record else "ppo")


def config_class(record: dict) -> type[EnvConfig]:
    """The config class of a recorded config: DQN's when its ``algo`` is ``"dqn"`` or it records ``buffer_size``
    (a Q-network's run), else :data:`RUN_CONFIGS` by :func:`algo_of` (PPO's for a trainer it does not know, whose
    ``algo`` is kept)."""
    if algo_of(record) == "dqn" or "buffer_size" in record:
        return dqn.DQNConfig
    return RUN_CONFIGS.get(algo_of(record), ppo.PPOConfig)


def unknown_key_warnings(record: dict, where) -> list[str]:
    """One warning per key of ``record`` no trainer writes (:func:`known_config_keys`), naming ``where`` and the
    closest known key: ``"WHERE: unknown key 'lr_rate' ignored (did you mean 'lr'?)"``."""
    known = known_config_keys()
    out = []
    for key in sorted(set(record) - known):
        close = difflib.get_close_matches(key, sorted(known), n=1)
        out.append(f"{where}: unknown key {key!r} ignored" + (f" (did you mean {close[0]!r}?)" if close else ""))
    return out


def check_record(record, where) -> None:
    """Refuse (``HistojaxDataError`` naming ``where``, one line) a recorded config that is not an object, whose
    ``hidden`` is not a whole number of at least 1, whose ``action_mode`` is not a string or whose ``env_kwargs`` is
    not an object."""
    if not isinstance(record, dict):
        raise HistojaxDataError(
            where,
            f"holds a JSON {type(record).__name__}, not an object of settings "
            "(the config.json a trainer writes); train again or restore it",
        )
    hidden = record.get("hidden", 256)
    if isinstance(hidden, bool) or not isinstance(hidden, int) or hidden < 1:
        raise HistojaxDataError(where, f"hidden={hidden!r}: the network width must be a whole number of at least 1")
    mode = record.get("action_mode", "discrete")
    if not isinstance(mode, str):
        raise HistojaxDataError(where, f"action_mode={mode!r}: must be a string such as 'discrete' or 'glimpse:1'")
    if not isinstance(record.get("env_kwargs") or {}, dict):
        raise HistojaxDataError(where, f"env_kwargs={record['env_kwargs']!r}: must be an object of make() settings")


def read_record(path) -> dict:
    """The JSON object of a run's ``config.json`` (``path``: the file or its run folder), as written. Unreadable
    or not JSON: ``HistojaxDataError`` naming the file, one line."""
    path = Path(path)
    if path.is_dir():
        path = path / "config.json"
    try:
        return json.loads(path.read_text())
    except OSError as e:
        raise HistojaxDataError(path, f"cannot read the run's config ({e.strerror or e})") from None
    except ValueError as e:
        raise HistojaxDataError(path, f"not valid JSON, truncated or corrupt ({e})") from None


def read_run_config(source, where=None, warnings: list | None = None):
    """The typed config of a run: ``source`` is its ``config.json`` (or the run folder holding it), the JSON object
    read from one, or a config already typed (returned as it is). The class is the trainer's
    (:func:`config_class`: by ``algo``; a record without it is PPO's, DQN's when it records ``buffer_size``); older
    spellings are renamed, entries it lacks take the trainer's defaults, entries of other trainers are ignored.

    ``where`` names the file in messages (default: the file read, or ``"config"``). Each key no trainer writes adds
    a warning line to ``warnings`` when given (:func:`unknown_key_warnings`), never a refusal. ``HistojaxDataError``
    naming ``where``, one line, for a record that cannot be a config (:func:`check_record`) or a value of the wrong
    type (``"lr": "fast"``)."""
    if isinstance(source, EnvConfig):
        return source
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        record = read_record(path)
        where = where if where is not None else (path / "config.json" if path.is_dir() else path)
    else:
        record = source
    where = "config" if where is None else where
    check_record(record, where)
    if warnings is not None:
        warnings += unknown_key_warnings(record, where)
    try:
        return config_class(record).from_dict({**record, "algo": algo_of(record)}, where=str(where), strict=False)
    except ConfigError as e:
        raise HistojaxDataError(where, e.detail) from None
