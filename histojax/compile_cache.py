"""JAX's persistent compilation cache for the command line: a warm second start.

Every ``histojax`` command and trainer entry point (``python -m baselines.ppo | dqn | ppo_rnn |
readers``) calls :func:`setup` first, so the XLA programs it compiles (env steps, a whole PPO run)
are written to a folder and read back by the next process that compiles the same program with the
same JAX version, backend and flags, instead of compiling again.

Where: ``$HISTOJAX_COMPILE_CACHE`` if set, else ``$XDG_CACHE_HOME/histojax/jax``, else
``~/.cache/histojax/jax``. Off: ``HISTOJAX_NO_COMPILE_CACHE=1`` or the ``--no-compile-cache`` flag on
any command. Only programs that took at least :data:`MIN_COMPILE_SECONDS` to compile are stored.
The folder can be deleted at any time (it is only a cache; JAX does not bound its size).

Importing ``histojax`` never turns the cache on: library users call ``jax.config.update(
"jax_compilation_cache_dir", ...)`` themselves, or :func:`enable`.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

FLAG = "--no-compile-cache"
OFF_ENV = "HISTOJAX_NO_COMPILE_CACHE"
DIR_ENV = "HISTOJAX_COMPILE_CACHE"
MIN_COMPILE_SECONDS = 0.5  # programs compiled faster than this are not worth a disk read


def cache_dir() -> Path:
    """The compilation cache folder: ``$HISTOJAX_COMPILE_CACHE``, ``$XDG_CACHE_HOME/histojax/jax`` or
    ``~/.cache/histojax/jax`` (not created here)."""
    if os.environ.get(DIR_ENV):
        return Path(os.environ[DIR_ENV]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "histojax" / "jax"


def disabled_by_env() -> bool:
    """True when ``HISTOJAX_NO_COMPILE_CACHE`` is set to anything but ``""``, ``0``, ``false`` or ``no``."""
    return os.environ.get(OFF_ENV, "").strip().lower() not in ("", "0", "false", "no")


def enable(path: str | os.PathLike | None = None) -> Path:
    """Turn JAX's persistent compilation cache on in ``path`` (default :func:`cache_dir`), creating
    the folder; returns it. Call before the first compilation of the process."""
    folder = Path(path) if path is not None else cache_dir()
    folder.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder


def setup(argv: list[str]) -> list[str]:
    """A command line's first call: ``argv`` without ``--no-compile-cache``; the cache turned on
    (:func:`enable`) unless that flag or ``HISTOJAX_NO_COMPILE_CACHE=1`` says not to. A folder that
    cannot be created (read-only home) leaves the cache off rather than stopping the command."""
    argv = list(argv)
    off = FLAG in argv or disabled_by_env()
    argv = [a for a in argv if a != FLAG]
    if not off:
        try:
            enable()
        except OSError:
            pass
    return argv


__all__ = ["DIR_ENV", "FLAG", "MIN_COMPILE_SECONDS", "OFF_ENV", "cache_dir", "disabled_by_env", "enable", "setup"]
