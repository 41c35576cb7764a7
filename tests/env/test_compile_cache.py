"""JAX's persistent compilation cache for the command line (histojax.compile_cache): where its folder
is, that the flag and the environment variable turn it off, that the ``histojax`` command creates the
folder where documented, and that a second process reads what the first wrote. Every test uses its own
temporary folder (conftest.py turns the cache off for all other tests)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from histojax import compile_cache

ROOT = Path(__file__).resolve().parents[2]
SAMPLE_SLIDE = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"


def _env(tmp_path, **extra) -> dict:
    """The test process's environment with the cache on and rooted in ``tmp_path`` (XDG_CACHE_HOME)."""
    env = {k: v for k, v in os.environ.items() if k not in (compile_cache.OFF_ENV, compile_cache.DIR_ENV)}
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    env.update(extra)
    return env


def test_cache_dir_follows_xdg_then_home(monkeypatch, tmp_path):
    monkeypatch.delenv(compile_cache.DIR_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compile_cache.cache_dir() == tmp_path / "xdg" / "histojax" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert compile_cache.cache_dir() == tmp_path / "home" / ".cache" / "histojax" / "jax"
    monkeypatch.setenv(compile_cache.DIR_ENV, str(tmp_path / "mine"))
    assert compile_cache.cache_dir() == tmp_path / "mine"


@pytest.mark.parametrize(
    "flag, env_value, on",
    [(False, None, True), (True, None, False), (False, "1", False), (False, "0", True), (True, "0", False)],
)
def test_flag_and_env_turn_it_off(monkeypatch, flag, env_value, on):
    calls = []
    monkeypatch.setattr(compile_cache, "enable", lambda path=None: calls.append(path))
    if env_value is None:
        monkeypatch.delenv(compile_cache.OFF_ENV, raising=False)
    else:
        monkeypatch.setenv(compile_cache.OFF_ENV, env_value)
    argv = ["demo", "--no-train"] + ([compile_cache.FLAG] if flag else [])
    assert compile_cache.setup(argv) == ["demo", "--no-train"]  # the flag never reaches the command's parser
    assert bool(calls) == on


def _histojax(args, env, cwd):
    return subprocess.run(
        [sys.executable, "-m", "histojax.cli", *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=120
    )


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_command_creates_the_documented_folder_and_the_flag_keeps_it_off(tmp_path):
    """End to end through ``histojax`` (the environment variable's path is the same: test_flag_and_env_turn_it_off)."""
    folder = tmp_path / "xdg" / "histojax" / "jax"
    r = _histojax(["info", str(SAMPLE_SLIDE), "--no-compile-cache"], _env(tmp_path), tmp_path)
    assert r.returncode == 0, r.stderr
    assert not folder.exists()
    r = _histojax(["info", str(SAMPLE_SLIDE)], _env(tmp_path), tmp_path)
    assert r.returncode == 0, r.stderr
    assert folder.is_dir()


# one jitted program big enough to pass MIN_COMPILE_SECONDS on any machine would make this test slow: the
# subprocess lowers the threshold to 0, then counts JAX's own cache-hit events
PROGRAM = """
import jax, jax.numpy as jnp
from histojax import compile_cache
compile_cache.MIN_COMPILE_SECONDS = 0.0
compile_cache.setup([])
hits = []
jax.monitoring.register_event_listener(lambda name, **kw: hits.append(name) if name.endswith("cache_hits") else None)
jax.jit(lambda x: jnp.cumsum(jnp.sin(x) * 3.0) @ x)(jnp.arange(16.0)).block_until_ready()
print("hits", len(hits))
"""


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_second_process_hits_the_cache(tmp_path):
    folder = tmp_path / "xdg" / "histojax" / "jax"
    runs = [
        subprocess.run(
            [sys.executable, "-c", PROGRAM], env=_env(tmp_path), cwd=ROOT, capture_output=True, text=True, timeout=120
        )
        for _ in range(2)
    ]
    for r in runs:
        assert r.returncode == 0, r.stderr
    entries = sorted(p.name for p in folder.iterdir())
    assert entries, "the first process wrote nothing to the cache"
    assert runs[0].stdout.split()[-1] == "0"  # empty cache: compiled
    assert int(runs[1].stdout.split()[-1]) >= 1  # warm cache: read back
