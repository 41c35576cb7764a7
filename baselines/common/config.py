"""A trainer's config, typed: a frozen dataclass per algorithm (:class:`baselines.ppo.PPOConfig`,
:class:`baselines.dqn.DQNConfig`, :class:`baselines.ppo_rnn.PPORNNConfig`) on the common base :class:`EnvConfig`
(which trainer, the env it trains on, the first seed).

A config is made once at the entry (the command line, or ``make_train`` given a dict) with
:meth:`EnvConfig.from_dict`, which refuses an unknown entry or a value of the wrong type in one line
(:class:`ConfigError`), and stays typed until the env (through :class:`histojax.make_options.MakeOptions`,
:meth:`EnvConfig.make_arguments`) and the network are built. :meth:`EnvConfig.as_dict` is the record a run writes to
``config.json`` (the same JSON as before the configs were typed: every field, ``seed`` last and only when set), so
resumed runs and published agents keep loading: ``from_dict(as_dict())`` gives the config back, and every
``config.json`` a trainer wrote loads (older spellings such as ``obs`` renamed; entries it lacks take the defaults).
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import os
import types
import typing
from typing import Any, ClassVar

from histojax.make_options import MakeOptions

OLDER_SPELLINGS = {"obs": "obs_mode"}  # config keys of older runs → the env's spelling

MAKE_ARGUMENTS = (
    "slide",
    "verify",
    "max_device_bytes",
    "slides",
    "slide_weights",
    "dataset",
    "split",
    "labels",
    "fold",
)
"""``histojax.make``'s own arguments (the slides and how they load) that ``env_kwargs`` may hold beside its options."""


RECORD_NOTES = ("stopped_at_update", "checkpoint_train_seconds")
"""Entries a run folder's ``config.json`` may hold beside the settings, about the run rather than for it
(``experiments.checkpoint_to_run`` notes where a stopped run stopped): read without a word, not kept."""


class ConfigError(ValueError):
    """A trainer config that cannot be made: an unknown entry or a value of the wrong type. ``str``: one line,
    ``"WHERE: DETAIL"`` (``where`` the file or the call, ``detail`` the entry and what is wrong)."""

    def __init__(self, where: str, detail: str):
        super().__init__(f"{where}: {detail}")
        self.where, self.detail = where, detail


def canonical_config(config: dict) -> dict:
    """``config`` with older key spellings renamed to the env's (``obs`` → ``obs_mode``); a copy."""
    out = dict(config)
    for old, new in OLDER_SPELLINGS.items():
        if old in out:
            value = out.pop(old)
            out.setdefault(new, value)
    return out


_NAMES = {
    bool: "true or false",
    int: "a whole number",
    float: "a number",
    str: "a string",
    dict: "an object",
    type(None): "null",
    os.PathLike: "a path",
}


def _fits(value, hint) -> bool:
    """Whether ``value`` (as read from JSON) has the annotated type ``hint`` (``X | None`` unions, ``object``: any).
    A bool is not a number here; an int is a float."""
    if hint is Any or hint is object:
        return True
    options = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)
    for t in options:
        if t is object or t is Any:
            return True
        if t is type(None):
            if value is None:
                return True
        elif t is bool:
            if isinstance(value, bool):
                return True
        elif t in (int, float):
            if isinstance(value, (int, float) if t is float else int) and not isinstance(value, bool):
                return True
        elif isinstance(value, t):
            return True
    return False


def _describe(hint) -> str:
    """``hint`` in words: ``"a whole number or null"``."""
    options = typing.get_args(hint) or (hint,)
    return " or ".join(_NAMES.get(t, getattr(t, "__name__", str(t))) for t in options)


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """The settings every trainer shares: which trainer, the env it trains on (spelled as ``histojax.make`` spells
    them) and the first seed. Each algorithm's config (``PPOConfig``, ``DQNConfig``, ``PPORNNConfig``) adds its own.

    ``env_kwargs`` holds any other ``histojax.make`` keyword: its options (:class:`~histojax.make_options.MakeOptions`,
    e.g. ``read_budget`` as a fraction of tissue views, ``glimpse_grid`` in cells) and its own arguments
    (:data:`MAKE_ARGUMENTS`: ``dataset`` folder, ``split``, ``fold``, ...)."""

    algo: str = ""  # the trainer (recorded in config.json)
    env_id: str = "HistoJAX-Easy-v0"  # registered env id
    slide: str | os.PathLike | None = None  # bundle folder; None: the id's slide (the sample slide)
    action_mode: str = "discrete"  # the env's action_mode
    obs_mode: str = "pixels"  # the env's obs_mode
    with_position: bool = False  # observation dict with the view position
    reward: str | None = None  # reward preset; None: the env's
    max_steps_in_episode: int | None = None  # env steps before truncation; None: the id's
    env_kwargs: dict | None = None  # any other histojax.make keyword
    # the first seed (PRNGKey(seed) is split into num_seeds keys); None: 0, and not recorded
    seed: int | None = dataclasses.field(default=None, metadata={"recorded_last": True})

    RECORDED_WITHOUT: ClassVar[tuple[str, ...]] = ()
    """Fields this trainer has but does not record in ``config.json`` (a setting it refuses, e.g. ``devices``)."""

    # ----------------------------------------------------------------------- dict ↔ config
    @classmethod
    @functools.cache
    def _hints(cls) -> dict:
        return typing.get_type_hints(cls)

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """The entries this config holds (its fields), in order."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def from_dict(cls, config: dict, where: str = "config", strict: bool = True):
        """The config of ``config`` (a ``config.json`` object, a command line's entries, or ``make_train``'s dict):
        older spellings renamed, entries it lacks at their defaults, a run's notes (:data:`RECORD_NOTES`) dropped. ``ConfigError`` naming ``where`` and the entry,
        one line, for an entry this trainer does not have (unless ``strict=False``: then ignored) or a value of the
        wrong type (``"lr": "fast"``; an int is accepted for a float)."""
        if isinstance(config, EnvConfig):
            config = config.as_dict()
        if not isinstance(config, dict):
            raise ConfigError(where, f"a config is an object of settings, not a {type(config).__name__}")
        config = canonical_config(config)
        names, hints = cls.field_names(), cls._hints()
        unknown = [k for k in config if k not in names and k not in RECORD_NOTES]
        if unknown and strict:
            key = unknown[0]
            close = difflib.get_close_matches(str(key), names, n=1)
            algo = config.get("algo") or cls.__dataclass_fields__["algo"].default or "this trainer"
            raise ConfigError(
                where,
                f"unknown config entry {key!r} for {algo}"
                + (f" (did you mean {close[0]!r}?)" if close else "")
                + f"; known: {', '.join(names)}",
            )
        values = {k: copy.deepcopy(v) for k, v in config.items() if k in names}
        for k, v in values.items():
            if not _fits(v, hints[k]):
                raise ConfigError(where, f"{k}={v!r} must be {_describe(hints[k])}, not a {type(v).__name__}")
        return cls(**values)

    @classmethod
    def coerce(cls, config, where: str = "config"):
        """``config`` as this class: itself when it is one, else :meth:`from_dict` of a dict (or of another
        trainer's config's record)."""
        if type(config) is cls:
            return config
        return cls.from_dict(config, where=where)

    def as_dict(self) -> dict:
        """The record of this config written to ``config.json`` (a copy): every field in order but those of
        :attr:`RECORDED_WITHOUT`, and the fields recorded last (``seed``) at the end, only when set."""
        out, last = {}, {}
        for f in dataclasses.fields(self):
            if f.name in self.RECORDED_WITHOUT:
                continue
            value = copy.deepcopy(getattr(self, f.name))
            if f.metadata.get("recorded_last"):
                if value is not None:
                    last[f.name] = value
            else:
                out[f.name] = value
        return {**out, **last}

    @classmethod
    def defaults(cls) -> dict:
        """The record of the default config (:meth:`as_dict` of ``cls()``)."""
        return cls().as_dict()

    def replace(self, **changes):
        """A copy with ``changes`` (``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)

    # ----------------------------------------------------------------------- the env
    def make_arguments(self, auto_reset: bool = True) -> tuple[dict, MakeOptions]:
        """``(arguments, options)`` of the ``histojax.make`` call that builds this config's env: ``make``'s own
        arguments (``slide`` and those of :data:`MAKE_ARGUMENTS` in ``env_kwargs``) and the typed
        :class:`~histojax.make_options.MakeOptions` of the rest (``action_mode``, ``obs_mode`` unless pixels,
        ``with_position``, ``reward`` and ``max_steps_in_episode`` when set, ``auto_reset``, ``env_kwargs``).
        ``TypeError`` naming ``make(env_id)`` and the unknown names for an ``env_kwargs`` entry ``make`` has not."""
        settings = dict(env_overrides(self))
        arguments = {"slide": self.slide, **{k: settings.pop(k) for k in MAKE_ARGUMENTS if k in settings}}
        options = MakeOptions.of({"auto_reset": auto_reset, **settings}, where=f"make({self.env_id!r})")
        return arguments, options


def env_overrides(config) -> dict:
    """The ``histojax.make`` overrides named in a trainer config (an :class:`EnvConfig` or its dict)."""
    if isinstance(config, dict):
        config = EnvConfig.from_dict(
            {k: v for k, v in canonical_config(config).items() if k in EnvConfig.field_names()}
        )
    kw = {"action_mode": config.action_mode, "with_position": bool(config.with_position)}
    if config.obs_mode != "pixels":
        kw["obs_mode"] = config.obs_mode  # e.g. "features" once the env has it
    for k in ("reward", "max_steps_in_episode"):
        if getattr(config, k) is not None:
            kw[k] = getattr(config, k)
    kw.update(config.env_kwargs or {})
    return kw
