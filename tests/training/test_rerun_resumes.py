"""The same ``histojax train ... --out RUN`` rerun after a kill (a scheduler requeueing a preempted job) continues
the run from its last checkpoint and ends with the parameters of the run left alone, bit for bit; it says so in
its first line. Another config's run there is refused in one line naming the difference; ``--restart`` moves the
old run aside into ``RUN/previous-N/`` (never deleted) and starts again; a finished run of the same command is
nothing to train."""

from __future__ import annotations

import functools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from baselines import ppo
from baselines.harness import cli
from baselines.harness.run_folder import LOCK, RunFolderError, claim_run, foreign_entries, release
from baselines.harness.runner import run_and_save

ROOT = Path(__file__).resolve().parents[2]


class Killed(Exception):
    """Stands for the process being killed right after a checkpoint."""


class ToyTrainer:
    """A chunked trainer of PPO's config (``train_and_save`` makes it from PPO's options): noisy SGD on a
    quadratic with its own PRNG key, a few updates in seconds, so the rerun decision is tested end to end
    through the command without compiling PPO (the slow test below does that with a real SIGKILL)."""

    def __init__(self, config):
        record = config.as_dict() if hasattr(config, "as_dict") else dict(config)
        self.config = {**record, "algo": "ppo"}
        self.num_updates, self.steps_per_update = 5, 10
        self.env, self.env_params = None, jnp.float32(0.3)

    def init_params(self, key, p):
        return {"w": jax.random.normal(key, (3,)) + p}

    def init_runner(self, key, p, params):
        return params, key

    def update(self, runner, i, p):
        params, key = runner
        key, k = jax.random.split(key)
        w = params["w"] - 0.1 * (2 * (params["w"] - p) + 0.1 * jax.random.normal(k, (3,)))
        loss = ((w - p) ** 2).sum()
        return ({"w": w}, key), {
            "return": -loss,
            "success": (w[0] > p).astype(jnp.float32),
            "length": loss * 0 + 1.0,
            "steps_to_success": loss * 0 + 1.0,
        }

    def runner_params(self, runner):
        return runner[0]


def _train(argv, monkeypatch, kill_at: int | None = None) -> int:
    """``histojax train --algo ppo ARGV`` in this process with :class:`ToyTrainer`; ``kill_at``: raise
    :class:`Killed` right after the checkpoint of that update (the process dies there)."""
    hook = None
    if kill_at is not None:

        def hook(done):
            if done >= kill_at:
                raise Killed

    monkeypatch.setattr(cli, "run_and_save", functools.partial(run_and_save, on_checkpoint=hook))
    args = ppo.parse_args(["--seeds", "2", "--checkpoint-every", "2", *argv])
    return cli.train_and_save("ppo", _toy_trainer, args, ppo.PPOConfig, "updates")


_TRAINERS: dict[str, ToyTrainer] = {}


def _toy_trainer(config) -> ToyTrainer:
    """One :class:`ToyTrainer` per config, so its chunk compiles once in this test process (a rerun process
    compiles the same program again)."""
    trainer = ToyTrainer(config)
    return _TRAINERS.setdefault(json.dumps(trainer.config, sort_keys=True, default=str), trainer)


@pytest.fixture
def no_reference(monkeypatch):
    # the random-agent reference of the curves compiles its own rollout; not what is tested here
    monkeypatch.setattr(
        "baselines.harness.runner.random_agent_reference", lambda *a, **k: {"return": 0.0, "success": 0.0}
    )
    monkeypatch.setattr("baselines.harness.runner.plot_curves", lambda path, *a, **k: Path(path).write_bytes(b"png"))


def test_the_same_command_rerun_after_a_kill_continues_and_ends_as_the_run_left_alone(
    tmp_path, monkeypatch, capsys, no_reference
):
    """Was: "starting it again", the checkpoint overwritten and the run trained from zero on every requeue."""
    straight, killed = tmp_path / "straight", tmp_path / "killed"
    assert _train(["--out", str(straight)], monkeypatch) == 0
    with pytest.raises(Killed):
        _train(["--out", str(killed)], monkeypatch, kill_at=2)
    saved = json.loads((killed / "checkpoint" / "checkpoint.json").read_text())
    assert saved["update"] == 2 and not (killed / "params.msgpack").exists()
    release(killed)  # the killed process's lock (the operating system drops it when a process dies)
    capsys.readouterr()
    assert _train(["--out", str(killed)], monkeypatch) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert (
        first
        == f"{killed} holds an unfinished run of this config at update 2/5: continuing it (--restart starts again)"
    )
    assert (killed / "params.msgpack").read_bytes() == (straight / "params.msgpack").read_bytes()
    assert (killed / "log.csv").read_text() == (straight / "log.csv").read_text()  # updates 1-2 kept, 3-5 trained
    # the same command once more: a finished run of this config, nothing to train and nothing touched
    before = {p.name: p.stat().st_mtime_ns for p in killed.iterdir()}
    assert _train(["--out", str(killed)], monkeypatch) == 0
    assert "finished run of this config (params.msgpack): nothing to train" in capsys.readouterr().out
    assert {p.name: p.stat().st_mtime_ns for p in killed.iterdir()} == before
    # --overwrite (a job script's) does not discard an unfinished run of this config either
    with pytest.raises(Killed):
        _train(["--out", str(tmp_path / "again"), "--overwrite"], monkeypatch, kill_at=2)
    release(tmp_path / "again")
    capsys.readouterr()
    assert _train(["--out", str(tmp_path / "again"), "--overwrite"], monkeypatch) == 0
    assert "continuing it" in capsys.readouterr().out.splitlines()[0]
    assert (tmp_path / "again" / "params.msgpack").read_bytes() == (straight / "params.msgpack").read_bytes()


def test_another_configs_run_is_refused_naming_the_difference_and_restart_moves_it_aside(
    tmp_path, monkeypatch, capsys, no_reference
):
    out = tmp_path / "run"
    with pytest.raises(Killed):
        _train(["--out", str(out), "--lr", "0.0003"], monkeypatch, kill_at=2)
    release(out)
    before = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    capsys.readouterr()
    assert _train(["--out", str(out), "--lr", "0.001"], monkeypatch) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {out}: holds an unfinished run of another config"), err
    assert "whose lr is 0.0003, not 0.001" in err[0] and "--restart" in err[0]
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == before  # refused: untouched
    # --restart: the old run moved whole into previous-1, the new one trained from zero beside it
    old = (out / "checkpoint" / "runner.msgpack").read_bytes()
    assert _train(["--out", str(out), "--lr", "0.001", "--restart"], monkeypatch) == 0
    assert f"moved the run there aside to {out / 'previous-1'} (--restart)" in capsys.readouterr().out
    assert (out / "previous-1" / "checkpoint" / "runner.msgpack").read_bytes() == old
    assert json.loads((out / "config.json").read_text())["lr"] == 0.001
    # a folder with previous-N is still a run folder: the same command again is nothing to train, a second
    # --restart moves the finished run into previous-2
    assert foreign_entries(out) == []
    assert _train(["--out", str(out), "--lr", "0.001"], monkeypatch) == 0
    assert _train(["--out", str(out), "--lr", "0.001", "--restart"], monkeypatch) == 0
    assert sorted(p.name for p in out.iterdir() if p.name.startswith("previous-")) == ["previous-1", "previous-2"]
    assert (out / "previous-2" / "params.msgpack").is_file() and (out / "params.msgpack").is_file()


def _unfinished(out: Path, config: dict, runner: bool) -> Path:
    (out / "checkpoint").mkdir(parents=True)
    (out / "checkpoint" / "config.json").write_text(json.dumps(config))
    if runner:
        (out / "checkpoint" / "runner.msgpack").write_bytes(b"state")
        (out / "checkpoint" / "checkpoint.json").write_text(json.dumps({"update": 3, "num_updates": 8}))
    return out


CONFIG = {"algo": "ppo", "env_id": "HistoJAX-Easy-v0", "lr": 0.001, "seed": 0}


def test_claim_says_what_a_rerun_does(tmp_path, capsys):
    """One line each: continue (at update k/N), start again (killed before its first checkpoint), nothing to
    train (finished); the folder is claimed (locked) in each case."""
    out, state = claim_run(_unfinished(tmp_path / "a", CONFIG, runner=True), CONFIG)
    release(out)
    assert state == "resume" and "at update 3/8: continuing it (--restart starts again)" in capsys.readouterr().out
    out, state = claim_run(_unfinished(tmp_path / "b", CONFIG, runner=False), CONFIG)
    release(out)
    assert state == "again" and "killed before its first checkpoint: starting it again" in capsys.readouterr().out
    assert (out / "checkpoint" / "config.json").is_file()
    (out / "params.msgpack").write_bytes(b"params")
    (out / "config.json").write_text(json.dumps(CONFIG))
    assert claim_run(out, CONFIG)[1] == "done"
    release(out)
    with pytest.raises(RunFolderError, match=r"a finished run \(params.msgpack\) whose seed is 0, not 1"):
        claim_run(out, {**CONFIG, "seed": 1})


def test_a_trainers_completions_of_the_config_are_the_same_command(tmp_path, capsys):
    """PPO records ``obs_norm="dataset"`` as the numbers it computed and a glimpse grid's shape in ``env_kwargs``:
    the command that wrote them still continues its run; another ``env_kwargs`` entry is another config."""
    command = {**CONFIG, "obs_norm": "dataset", "env_kwargs": {"read_budget": 0.2}}
    saved = {
        **command,
        "obs_norm": {"mean": [0.5], "std": [0.2]},
        "env_kwargs": {"read_budget": 0.2, "glimpse_grid": [4, 4]},
    }
    out, state = claim_run(_unfinished(tmp_path / "a", saved, runner=True), command)
    release(out)
    assert state == "resume"
    with pytest.raises(RunFolderError, match=r"whose env_kwargs\.read_budget is 0\.2, not 0\.5"):
        claim_run(out, {**command, "env_kwargs": {"read_budget": 0.5}})
    with pytest.raises(RunFolderError, match=r'whose obs_norm is .*, not "none"'):
        claim_run(out, {**command, "obs_norm": "none"})


def test_restart_moves_only_the_runs_entries_and_never_a_users_folder(tmp_path):
    out = _unfinished(tmp_path / "run", CONFIG, runner=True)
    (out / "previous-1").mkdir()
    (out / "previous-1" / "anything.txt").write_text("kept as it is")
    got, state = claim_run(out, {**CONFIG, "lr": 0.01}, restart=True)
    release(got)
    assert state == "restarted" and sorted(p.name for p in out.iterdir()) == ["previous-1", "previous-2"]
    assert (out / "previous-2" / "checkpoint" / "runner.msgpack").read_bytes() == b"state"
    assert (out / "previous-1" / "anything.txt").read_text() == "kept as it is"
    (out / "thesis.txt").write_text("mine")  # a user's file: refused, not moved
    with pytest.raises(RunFolderError, match="'thesis.txt'"):
        claim_run(out, CONFIG, restart=True)
    (out / "thesis.txt").unlink()
    (out / "previous-3").write_text("a file, not a run moved aside")
    assert foreign_entries(out) == ["previous-3"]


# ----------------------------------------------------------------------------- a real SIGKILL
TINY_COMMAND = [
    "--env", "HistoJAX-Easy-v0", "--with-position", "--seeds", "1", "--num-envs", "4", "--total-steps", "1024",
    "--set", "num_steps=8", "--set", "num_minibatches=2", "--set", "hidden=16", "--set", "update_epochs=1",
    "--checkpoint-every", "1",
]  # fmt: skip
# 32 updates of 32 env steps, a checkpoint after each


def _command(out: Path) -> list[str]:
    return [sys.executable, "-m", "baselines.ppo", *TINY_COMMAND, "--out", str(out)]


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT), "HISTOJAX_NO_COMPILE_CACHE": "1", "JAX_PLATFORMS": "cpu"}


@pytest.mark.slow  # three PPO processes, each compiling its chunk: about two minutes on a shared 2-core CPU
def test_a_ppo_run_killed_with_sigkill_and_rerun_ends_bitwise_as_the_run_left_alone(tmp_path):
    """A real ``python -m baselines.ppo ... --out RUN`` killed with SIGKILL once its checkpoint says update >= 1
    (while it trains the next updates), then the same command rerun: its ``params.msgpack`` equals the
    uninterrupted run's byte for byte (the same compiled chunk on the same saved float32 / uint32 states)."""
    straight, killed = tmp_path / "straight", tmp_path / "killed"
    subprocess.run(_command(straight), check=True, cwd=tmp_path, env=_env(), capture_output=True, timeout=600)
    run = subprocess.Popen(
        _command(killed), cwd=tmp_path, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    summary, update, deadline = killed / "checkpoint" / "checkpoint.json", 0, time.monotonic() + 600
    try:
        while run.poll() is None and time.monotonic() < deadline:
            try:
                update = json.loads(summary.read_text())["update"]
            except (OSError, ValueError, KeyError):
                update = 0
            if update >= 1:
                break
            time.sleep(0.02)
    finally:
        run.send_signal(signal.SIGKILL)
        run.wait()
    assert 1 <= update < 32 and not (killed / "params.msgpack").exists(), update
    rerun = subprocess.run(_command(killed), cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr[-2000:]
    first = rerun.stdout.splitlines()[0]
    assert first.startswith(f"{killed} holds an unfinished run of this config at update ") and "continuing it" in first
    assert (killed / "params.msgpack").read_bytes() == (straight / "params.msgpack").read_bytes()
    params = np.frombuffer((straight / "params.msgpack").read_bytes(), np.uint8)
    assert params.size > 1000  # a real network's parameters, not an empty file


# ----------------------------------------------------------------------------- train_readers on a rerun
HEAD = ROOT / "baselines" / "published" / "c16-v2-head"


def _readers_command(tmp_path, monkeypatch, trained: list):
    """``train_readers.main`` with its trainer, dataset split and scoring stood in for: the trainer (it is
    ``histojax train``, tested above) records its options and writes ``params.msgpack`` unless its run there is
    finished; what is tested is what ``train_readers`` does around it."""
    import baselines.ppo
    from baselines.reading import readers, train_readers

    def split(dataset, out, fraction, seed, fold=None):
        (out / "validation-set").mkdir(parents=True, exist_ok=True)
        spec = {"train": [], "validation_split": {"fraction": fraction, "seed": seed}, "derived_from": str(dataset)}
        (out / "dataset.json").write_text(json.dumps(spec))
        return out

    def trainer(argv):
        trained.append(argv)
        run = Path(argv[argv.index("--out") + 1])
        if "--restart" in argv or not (run / "params.msgpack").exists():
            run.mkdir(parents=True, exist_ok=True)
            (run / "params.msgpack").write_bytes(os.urandom(8))
        return 0

    monkeypatch.setattr(train_readers, "split_dataset", split)
    monkeypatch.setattr(train_readers, "dataset_levels", lambda *a, **k: 3)
    monkeypatch.setattr(baselines.ppo, "main", trainer)
    monkeypatch.setattr(readers, "main", lambda argv: 0)
    (tmp_path / "data").mkdir(exist_ok=True)
    base = ["--dataset", str(tmp_path / "data"), "--head", str(HEAD), "--out", str(tmp_path / "o")]
    return lambda *more: train_readers.main([*base, *more])


def test_train_readers_rerun_keeps_a_finished_runs_record_and_passes_restart(tmp_path, monkeypatch):
    """Was: a rerun after a kill during the scoring rewrote head_reward.json with the wall time of a run that
    trained nothing; now the record stays until the trainer really trains (here: with --restart)."""
    trained = []
    train = _readers_command(tmp_path, monkeypatch, trained)
    record = tmp_path / "o" / "ppo" / "head_reward.json"
    assert train() == 0 and "--restart" not in trained[-1]
    first = record.read_bytes()
    record.write_text(json.dumps({**json.loads(first), "train_wall_s": 1234.5}))  # the first run's real time
    assert train() == 0  # the same command again: the trainer's finished run, not trained again
    assert json.loads(record.read_text())["train_wall_s"] == 1234.5
    assert train("--restart") == 0 and "--restart" in trained[-1]  # the trainer moves its run aside
    assert json.loads(record.read_text())["train_wall_s"] != 1234.5


def test_train_readers_rerun_with_another_split_is_refused_while_a_run_trained_on_the_old_one(
    tmp_path, monkeypatch, capsys
):
    """Was: the rerun wrote OUT/dataset.json with the new split and the trainer (whose config names only the
    folder) continued the old run on other slides."""
    trained = []
    train = _readers_command(tmp_path, monkeypatch, trained)
    assert train("--val-fraction", "0.3") == 0 and len(trained) == 1
    split = (tmp_path / "o" / "dataset.json").read_bytes()
    capsys.readouterr()
    assert train("--val-fraction", "0.5") == 2 and len(trained) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path / "o" / "dataset.json") in err[0] and "'fraction': 0.3" in err[0], err
    assert (tmp_path / "o" / "dataset.json").read_bytes() == split  # refused before the split is written again
    assert train("--val-fraction", "0.5", "--restart") == 0 and len(trained) == 2


def test_a_rerun_on_several_processes_is_refused_not_continued(tmp_path, monkeypatch, capsys, no_reference):
    """Runs on several processes keep no checkpoints along the way: the rerun is one line, not a traceback."""
    out = tmp_path / "run"
    with pytest.raises(Killed):
        _train(["--out", str(out)], monkeypatch, kill_at=2)
    release(out)
    monkeypatch.setattr(jax, "process_count", lambda: 2)
    capsys.readouterr()
    assert _train(["--out", str(out)], monkeypatch) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "runs on several processes cannot continue" in err[0] and str(out) in err[0], err
    assert not (out / LOCK).exists() and not (out / "params.msgpack").exists()


def test_a_finished_dataset_runs_slides_seen_json_is_its_own_file(tmp_path, capsys):
    """Was: ``slides_seen.json`` (written beside a dataset run's params) counted as a user's file, so the run's
    rerun and its ``--overwrite`` were refused. Now the rerun is nothing to train, ``--overwrite`` removes the old
    record (a new run on no dataset writes none) and ``--restart`` moves it aside with its run."""
    out = tmp_path / "run"
    out.mkdir()
    (out / "params.msgpack").write_bytes(b"params")
    (out / "config.json").write_text(json.dumps(CONFIG))
    (out / "slides_seen.json").write_text("{}")
    assert foreign_entries(out) == []
    assert claim_run(out, CONFIG)[1] == "done"
    release(out)
    assert claim_run(out, {**CONFIG, "seed": 3}, overwrite=True)[1] == "replaced"
    release(out)
    assert not (out / "slides_seen.json").exists() and (out / "params.msgpack").is_file()
    (out / "slides_seen.json").write_text("{}")
    assert claim_run(out, CONFIG, restart=True)[1] == "restarted"
    release(out)
    assert (out / "previous-1" / "slides_seen.json").is_file() and not (out / "slides_seen.json").exists()
