"""A hostile pass over the rerun of ``histojax train ... --out RUN`` (:func:`~baselines.harness.run_folder.claim_run`:
an unfinished run of the same config continues, ``--restart`` moves it into ``RUN/previous-N/``): ``previous-N``
that is a file, a link, a FIFO or a folder of a user's files; hundreds of them; a ``checkpoint/config.json`` or
``checkpoint.json`` that is a FIFO, a link, huge, nested past the parser, not an object, with NaN or wrong types; a
``runner.msgpack`` truncated, garbage or a FIFO when the rerun continues; a config differing in one nested
``env_kwargs`` value; a second rerun while one holds the lock. Each is a decision or one line naming the file; none
blocks, none writes or moves anything on a refusal. No real trainer compiles here."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from baselines import ppo
from baselines.harness import cli
from baselines.harness.run_folder import LOCK, RunFolderError, claim_run, release
from baselines.harness.runner import resume_config
from data_tools.errors import HistojaxDataError

CONFIG = {"algo": "ppo", "env_id": "HistoJAX-Easy-v0", "lr": 0.001, "seed": 0}
DEEP = '{"algo": "ppo", "env_id": "HistoJAX-Easy-v0", "x": ' + "[" * 100_000 + "]" * 100_000 + "}"


def _tree(out: Path) -> dict:
    return {str(p.relative_to(out)): (p.is_symlink(), p.lstat().st_size) for p in sorted(out.rglob("*"))}


def _unfinished(out: Path, config=CONFIG, summary=None, runner: bytes = b"state") -> Path:
    (out / "checkpoint").mkdir(parents=True)
    (out / "checkpoint" / "config.json").write_text(config if isinstance(config, str) else json.dumps(config))
    (out / "checkpoint" / "runner.msgpack").write_bytes(runner)
    summary = json.dumps({"update": 3, "num_updates": 8}) if summary is None else summary
    (out / "checkpoint" / "checkpoint.json").write_text(summary)
    return out


@pytest.mark.parametrize(
    "summary",
    [
        '{"update": Infinity, "num_updates": 8}',  # was: OverflowError traceback (int(inf))
        '{"update": 1e400, "num_updates": 8}',  # was: OverflowError traceback (1e400 reads as inf)
        '{"update": NaN, "num_updates": 8}',
        '{"update": true, "num_updates": 8}',  # was: "at update 1/8"
        '{"update": -5, "num_updates": 8}',  # was: "at update -5/8"
        '{"update": 99, "num_updates": 8}',  # was: "at update 99/8"
        '{"update": "3", "num_updates": [8]}',
        "[1]",
        "[" * 100_000 + "]" * 100_000,  # nested past the parser: was a RecursionError traceback
    ],
)
def test_a_hostile_checkpoint_summary_only_loses_the_progress_words(tmp_path, capsys, summary):
    out, state = claim_run(_unfinished(tmp_path / "run", summary=summary), CONFIG)
    release(out)
    assert state == "resume"
    assert capsys.readouterr().out.strip().endswith("at its last checkpoint: continuing it (--restart starts again)")


@pytest.mark.parametrize(
    "kind",
    ["fifo", "link", "huge", "list", "env_id-int", "deep"],
)
def test_a_checkpoint_config_that_is_not_a_runs_is_a_users_file_refused_untouched(tmp_path, kind):
    """Was (``deep``: arrays nested past the JSON parser's recursion): a RecursionError traceback."""
    out = _unfinished(tmp_path / "run")
    path = out / "checkpoint" / "config.json"
    path.unlink()
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "link":
        (tmp_path / "elsewhere.json").write_text(json.dumps(CONFIG))
        path.symlink_to(tmp_path / "elsewhere.json")
    elif kind == "huge":
        with open(path, "wb") as f:
            f.truncate((16 << 20) + 1)  # sparse: no disk used
    else:
        path.write_text({"list": "[1, 2]", "env_id-int": '{"env_id": 5}', "deep": DEEP}[kind])
    before = _tree(out)
    for restart in (False, True):
        with pytest.raises(RunFolderError, match=r"holds files histojax did not write \(e\.g\. 'checkpoint/config"):
            claim_run(out, CONFIG, restart=restart)
    assert _tree(out) == before and not (out / LOCK).exists()


def test_resume_of_a_deeply_nested_config_is_one_line(tmp_path):
    """Was: ``--resume RUN`` on a config.json of arrays nested past the parser raised RecursionError."""
    out = _unfinished(tmp_path / "run", config=DEEP)
    with pytest.raises(HistojaxDataError, match="not valid JSON") as e:
        resume_config(out, "ppo", ppo.PPOConfig)
    assert "\n" not in str(e.value) and "config.json" in str(e.value)


def test_a_checkpoint_config_with_nan_or_a_wrong_type_is_another_configs_run(tmp_path):
    for i, lr in enumerate(["NaN", '"0.001"']):
        text = json.dumps(CONFIG).replace("0.001", lr)
        out = _unfinished(tmp_path / f"run{i}", config=text)
        with pytest.raises(RunFolderError, match=f"an unfinished run of another config, whose lr is {lr}, not 0.001"):
            claim_run(out, CONFIG)


def test_a_config_differing_in_one_nested_env_kwargs_value_is_named_by_it(tmp_path):
    """Was: ``whose env_kwargs is {"dataset": "/a/long/path...", "..., not {"dataset": "/a/long/path...", "...``:
    both values cut at 80 characters before the entry that differs."""
    kwargs = {"dataset": "/data/" + "cohort-" * 20, "split": "train", "read_budget": 0.2}
    saved = {**CONFIG, "env_kwargs": {**kwargs, "glimpse_grid": [4, 4]}}  # a trainer's own completion: not named
    out = _unfinished(tmp_path / "run", config=saved)
    with pytest.raises(RunFolderError, match=r"whose env_kwargs\.read_budget is 0\.2, not 0\.3;"):
        claim_run(out, {**CONFIG, "env_kwargs": {**kwargs, "read_budget": 0.3}})
    with pytest.raises(RunFolderError, match=r"whose env_kwargs has no fold \(this command's: 1\);"):
        claim_run(out, {**CONFIG, "env_kwargs": {**kwargs, "fold": 1}})


@pytest.mark.parametrize("kind", ["file", "link", "fifo"])
def test_a_previous_n_that_is_not_a_folder_is_refused_even_with_restart(tmp_path, kind):
    out = _unfinished(tmp_path / "run")
    prev = out / "previous-1"
    if kind == "file":
        prev.write_text("mine")
    elif kind == "link":
        (tmp_path / "elsewhere").mkdir()
        prev.symlink_to(tmp_path / "elsewhere")
    else:
        os.mkfifo(prev)
    before = _tree(out)
    for restart in (False, True):
        with pytest.raises(RunFolderError, match=r"\(e\.g\. 'previous-1'\)"):
            claim_run(out, CONFIG, restart=restart)
    assert _tree(out) == before and not (out / LOCK).exists()
    assert kind != "link" or list((tmp_path / "elsewhere").iterdir()) == []


def test_previous_n_folders_are_kept_whole_and_restart_numbers_past_the_largest(tmp_path, capsys):
    out = _unfinished(tmp_path / "run")
    for n in range(1, 301):
        (out / f"previous-{n}").mkdir()
    (out / "previous-7" / "thesis.txt").write_text("mine")  # a user's file in a moved-aside run: never looked into
    (out / "previous-0450").mkdir()
    out_, state = claim_run(out, CONFIG)  # previous-N beside an unfinished run: it still continues
    release(out_)
    assert state == "resume"
    out_, state = claim_run(out, CONFIG, restart=True)
    release(out_)
    assert state == "restarted" and (out / "previous-451" / "checkpoint" / "runner.msgpack").read_bytes() == b"state"
    assert (out / "previous-7" / "thesis.txt").read_text() == "mine"
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith("previous-")) == []


class _Toy:
    """A chunked trainer of PPO's config whose runner state is one array: enough for the rerun to reach
    :func:`~baselines.harness.runner.load_runner`."""

    def __init__(self, config):
        self.config = {**config.as_dict(), "algo": "ppo"}
        self.num_updates, self.steps_per_update = 4, 1
        self.env, self.env_params = None, jnp.float32(0.0)

    def init_params(self, key, p):
        return {"w": jnp.zeros(2)}

    def init_runner(self, key, p, params):
        return params, key

    def update(self, runner, i, p):
        return runner, {"return": p, "success": p, "length": p, "steps_to_success": p}

    def runner_params(self, runner):
        return runner[0]


@pytest.mark.parametrize("runner", ["garbage", "truncated", "fifo", "link"])
def test_a_broken_runner_state_when_the_rerun_continues_is_one_line_nothing_written(tmp_path, capsys, runner):
    args = ppo.parse_args(["--seeds", "1", "--checkpoint-every", "2", "--out", str(tmp_path / "run")])
    config = ppo.PPOConfig.from_dict(cli.config_from_args(args, defaults=ppo.PPOConfig.defaults()), where="test")
    out = _unfinished(tmp_path / "run", config=_Toy(config).config)
    state = out / "checkpoint" / "runner.msgpack"
    if runner == "truncated":
        state.write_bytes(b"\x85\xa6format")  # a map of 5 entries cut after its first key
    elif runner in ("fifo", "link"):
        state.unlink()
        os.mkfifo(state) if runner == "fifo" else state.symlink_to(tmp_path / "elsewhere")
    before = _tree(out)
    with pytest.raises(HistojaxDataError) as e:
        cli.train_and_save("ppo", _Toy, args, ppo.PPOConfig, "updates")
    assert "runner.msgpack" in str(e.value) and "\n" not in str(e.value)
    assert _tree(out) == before and not (out / LOCK).exists()
    assert "continuing it" in capsys.readouterr().out


def test_a_second_rerun_while_one_holds_the_lock_is_refused_and_touches_nothing(tmp_path):
    out = _unfinished(tmp_path / "run")
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import fcntl, os, sys; fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT); os.write(fd, b'4242');"
            "fcntl.flock(fd, fcntl.LOCK_EX); print('held', flush=True); sys.stdin.read()",
            str(out / LOCK),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        before = _tree(out)
        for restart in (False, True):
            with pytest.raises(RunFolderError, match=r"another training run \(process 4242\) is writing"):
                claim_run(out, CONFIG, restart=restart)
        assert _tree(out) == before  # not moved aside under another writer
    finally:
        holder.stdin.close()
        holder.wait(10)
    out_, state = claim_run(out, CONFIG)  # the holder gone: the rerun continues
    release(out_)
    assert state == "resume"


@pytest.mark.parametrize(
    "edit",
    [
        {"num_updates": None},  # was: KeyError traceback
        {"leaves": [1, 2]},  # was: AttributeError traceback (list.get)
        {"update": 1.5},  # was: continued, a traceback further on
        {"update": 9},  # past num_updates: was continued, a traceback further on
        {"train_seconds": float("nan")},  # was: a ValueError writing the NaN into the logs
        {"metrics": {"return": np.zeros((1, 5), np.float32)}},  # 5 columns for 2 updates: was a traceback further on
    ],
    ids=["no-num_updates", "leaves-list", "update-float", "update-past", "seconds-nan", "metrics-shape"],
)
def test_a_crafted_runner_state_of_this_config_is_one_line(tmp_path, capsys, edit):
    """A ``runner.msgpack`` of this config's digest and arrays with one field damaged; ``edit={}`` continues."""
    from flax import serialization

    from baselines.harness.runner import RUNNER_FORMAT, chunked_runner, config_digest

    args = ppo.parse_args(["--seeds", "1", "--checkpoint-every", "2", "--out", str(tmp_path / "run")])
    config = ppo.PPOConfig.from_dict(cli.config_from_args(args, defaults=ppo.PPOConfig.defaults()), where="test")
    train = _Toy(config)
    toy, (start, _) = train.config, chunked_runner(train)
    template = jax.tree.leaves(start.template(jax.random.split(jax.random.PRNGKey(0), 1)))
    state = {
        "format": RUNNER_FORMAT,
        "update": 2,
        "num_updates": 4,
        "chunk": 2,
        "config_sha256": config_digest(toy),
        "train_seconds": 1.0,
        "leaves": {str(i): np.zeros(t.shape, t.dtype) for i, t in enumerate(template)},  # the toy's own arrays
        "metrics": {"return": np.zeros((1, 2), np.float32)},
    }
    state = {k: v for k, v in {**state, **edit}.items() if v is not None}
    out = _unfinished(tmp_path / "run", config=toy, runner=serialization.msgpack_serialize(state))
    before = _tree(out)
    with pytest.raises(HistojaxDataError, match=r"runner\.msgpack: ") as e:
        cli.train_and_save("ppo", _Toy, args, ppo.PPOConfig, "updates")
    assert "\n" not in str(e.value) and _tree(out) == before and not (out / LOCK).exists()
