"""Checkpoints along the way and ``--resume``: a run killed after a checkpoint and resumed ends with the same
parameters, bit for bit, as the same run left alone (the same compiled chunk of updates runs on the same
saved states); a run's files are written as a whole (a full disk keeps the previous run's files together and
names the file); resume errors are one line naming the file."""

from __future__ import annotations

import builtins
import errno
import json

import jax
import numpy as np
import pytest

from baselines import dqn, outputs, ppo, ppo_rnn
from baselines.common.config import env_overrides
from baselines.harness.logs import _tensorboard_scalars, tensorboard_writer
from baselines.harness.runner import (
    chunk_plan,
    chunked_runner,
    finish_run,
    load_runner,
    run_and_save,
    run_chunked,
    save_runner,
)
from data_tools.errors import HistojaxDataError

TINY = dict(
    env_id="HistoJAX-Easy-v0",
    with_position=True,
    num_envs=4,
    num_steps=8,
    total_timesteps=4 * 8 * 5,
    update_epochs=1,
    num_minibatches=2,
    hidden=16,
    num_seeds=2,
    print_progress=False,
    checkpoint_every=2,
)


class Killed(Exception):
    """Stands for the process being killed right after a checkpoint."""


def _kill_after(update: int):
    def hook(done):
        if done >= update:
            raise Killed

    return hook


def _no_reference(monkeypatch):
    # the random-agent reference of the curves compiles its own rollout; not what is tested here
    monkeypatch.setattr(
        "baselines.harness.runner.random_agent_reference", lambda *a, **k: {"return": 0.0, "success": 0.0}
    )


def _straight_and_resumed(tmp_path, algo: str, make_train, config: dict, kill_at: int):
    """(params straight, params killed at ``kill_at`` then resumed, the two run folders); one trainer object,
    so its chunk compiles once (a resumed process compiles the same program again)."""
    train = make_train(config)
    _, straight, _ = run_and_save(algo, lambda c: train, config, tmp_path / "straight")
    with pytest.raises(Killed):
        run_and_save(algo, lambda c: train, config, tmp_path / "killed", on_checkpoint=_kill_after(kill_at))
    saved = json.loads((tmp_path / "killed" / "checkpoint" / "checkpoint.json").read_text())
    assert saved["update"] == kill_at and not (tmp_path / "killed" / "params.msgpack").exists()
    _, resumed, _ = run_and_save(algo, lambda c: train, config, tmp_path / "killed", resume=True)
    return straight, resumed, tmp_path / "straight", tmp_path / "killed", train


def _assert_bitwise_equal(a, b):
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb) and la
    for x, y in zip(la, lb):
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_chunk_plan_even_chunks_no_more_than_every():
    assert chunk_plan(122, 100) == (61, 2)
    assert chunk_plan(5, 2) == (2, 3)  # 6 slots, the last skipped
    assert chunk_plan(10, 0) == (10, 1)  # 0: one chunk, a checkpoint at the end only
    assert chunk_plan(10, None) == (10, 1)
    assert chunk_plan(3, 50) == (3, 1)
    for n in range(1, 40):
        for every in range(1, 12):
            chunk, k = chunk_plan(n, every)
            assert chunk <= every and chunk * k >= n > chunk * (k - 1) and chunk * k - n < k


class _Toy:
    """A trainer of the chunked driver's shape with a cheap update (noisy SGD on a quadratic, its own PRNG key
    and an update counter in the runner state), so the driver (chunks, the skipped tail, save, load, resume)
    is tested in seconds; the PPO test below (slow) does the same through the real trainer."""

    def __init__(self, num_updates=7, every=3, seeds=2, vmap_seeds=True):
        import jax.numpy as jnp

        self.config = {
            "seed": 0,
            "num_seeds": seeds,
            "vmap_seeds": vmap_seeds,
            "checkpoint_every": every,
            "algo": "toy",
        }
        self.num_updates, self.steps_per_update, self.env, self.env_params = num_updates, 10, None, jnp.float32(0.3)
        self.traces = 0

    def init_params(self, key, p):
        return {"w": jax.random.normal(key, (3,)) + p}

    def init_runner(self, key, p, params):
        import jax.numpy as jnp

        return params, key, jnp.zeros((), jnp.int32)

    def update(self, runner, i, p):
        import jax.numpy as jnp

        self.traces += 1
        params, key, n = runner
        key, k = jax.random.split(key)
        grad = 2 * (params["w"] - p) + 0.1 * jax.random.normal(k, (3,))
        w = params["w"] - 0.1 * grad / (1.0 + i.astype(jnp.float32))
        return ({"w": w}, key, n + 1), {"loss": ((w - p) ** 2).sum(), "success": (w[0] > p).astype(jnp.float32)}

    def runner_params(self, runner):
        return runner[0]


@pytest.mark.parametrize("vmap_seeds", [True, False])
def test_driver_killed_and_resumed_equals_the_uninterrupted_run(tmp_path, vmap_seeds):
    """7 updates in chunks of 3 (the last chunk runs 1 and skips 2): killed after 3 or 6, resumed, the params
    and every update's metrics equal the straight run's bit for bit; the chunk is traced once, not again on
    resume; the runner state saved holds the update counter (the skipped updates did not run)."""
    toy = _Toy(vmap_seeds=vmap_seeds)
    straight, _, _ = run_chunked(toy, tmp_path / "straight")
    traces = toy.traces
    assert straight["metrics"]["loss"].shape == (2, 7) and np.isfinite(straight["metrics"]["loss"]).all()
    for kill_at in (3, 6):
        out = tmp_path / f"killed-{kill_at}"
        with pytest.raises(Killed):
            run_chunked(toy, out, on_checkpoint=_kill_after(kill_at))
        resumed, _, _ = run_chunked(toy, out, resume=True)
        _assert_bitwise_equal(straight["params"], resumed["params"])
        for k in straight["metrics"]:
            np.testing.assert_array_equal(straight["metrics"][k], resumed["metrics"][k])
    assert toy.traces == traces  # compiled once: neither the kill nor the resume traced the chunk again
    start, _ = chunked_runner(toy)  # the pair run_chunked made and ran
    runners, done, metrics, _ = load_runner(
        tmp_path / "straight" / "checkpoint", start.template(jax.random.split(jax.random.PRNGKey(0), 2)), 7, 3
    )
    assert done == 7 and np.asarray(runners[2]).tolist() == [7, 7] and metrics["loss"].shape == (2, 7)
    # a different run (not resumed) really differs: the comparison above can fail
    other, _, _ = run_chunked(_Toy(num_updates=6, vmap_seeds=vmap_seeds), tmp_path / "other")
    assert not np.array_equal(np.asarray(other["params"]["w"]), np.asarray(straight["params"]["w"]))


@pytest.mark.slow
def test_ppo_killed_and_resumed_equals_the_uninterrupted_run(tmp_path, monkeypatch):
    """PPO, 5 updates in chunks of 2 (the last chunk has one update skipped), killed after update 2, resumed:
    params, the per-update metrics and log.csv equal the run left alone, bit for bit: the resumed process runs
    the same compiled chunk on the same saved states (params, Adam state and step, env states, observations,
    PRNG keys: float32 / uint32 saved exactly by msgpack), so nothing can round differently."""
    _no_reference(monkeypatch)
    straight, resumed, a, b, train = _straight_and_resumed(tmp_path, "ppo", ppo.make_train, TINY, kill_at=2)
    _assert_bitwise_equal(straight, resumed)
    la, lb = json.loads((a / "log.json").read_text()), json.loads((b / "log.json").read_text())
    assert la["step"] == lb["step"] == [32 * (i + 1) for i in range(5)]
    assert la["per_seed"] == lb["per_seed"]
    assert (a / "log.csv").read_text() == (b / "log.csv").read_text()
    # the parameters really moved (a run that did nothing would also be "equal")
    init = jax.jit(train.init_params)(jax.random.split(jax.random.PRNGKey(0), 2)[0], train.env_params)
    moved = [
        not np.array_equal(np.asarray(x)[0], np.asarray(y))
        for x, y in zip(jax.tree.leaves(straight), jax.tree.leaves(init))
    ]
    assert any(moved)
    assert sorted(p.name for p in b.iterdir() if not p.name.startswith("events.")) == [
        "checkpoint",
        "config.json",
        "curve.png",
        "log.csv",
        "log.json",
        "params.msgpack",
    ]
    if _has_tensorboardx():
        assert any(p.name.startswith("events.out.tfevents") for p in a.iterdir())


def _has_tensorboardx() -> bool:
    try:
        import tensorboardX  # noqa: F401
    except ImportError:
        return False
    return True


@pytest.mark.slow
@pytest.mark.parametrize(
    "algo, module, config",
    [
        ("ppo_rnn", ppo_rnn, {**TINY, "hidden": 16}),
        (
            "dqn",
            dqn,
            dict(
                env_id="HistoJAX-Easy-v0",
                with_position=True,
                num_envs=4,
                total_timesteps=4 * 8 * 5,
                buffer_size=64,
                batch_size=8,
                learning_starts=16,
                iterations_per_log=8,
                hidden=16,
                num_seeds=2,
                print_progress=False,
                checkpoint_every=2,
            ),
        ),
    ],
)
def test_recurrent_ppo_and_dqn_resume_equal_the_uninterrupted_run(tmp_path, monkeypatch, algo, module, config):
    """The same for recurrent PPO (GRU states carried) and DQN (replay buffer, target network carried)."""
    _no_reference(monkeypatch)
    straight, resumed, *_ = _straight_and_resumed(tmp_path, algo, module.make_train, config, kill_at=2)
    _assert_bitwise_equal(straight, resumed)


def test_tensorboard_events_beside_log_csv(tmp_path):
    """With tensorboardX installed, the seed means of each update's metrics go to event files in the run folder."""
    pytest.importorskip("tensorboardX")
    writer = tensorboard_writer(tmp_path)
    _tensorboard_scalars(writer, {"success": np.array([[0.0, 0.5], [1.0, np.nan]])}, 3, 100)
    writer.close()
    from tensorboardX.proto import event_pb2

    events = [p for p in tmp_path.iterdir() if p.name.startswith("events.out.tfevents")]
    assert len(events) == 1
    data, at, scalars = events[0].read_bytes(), 0, {}
    while at < len(data):  # TFRecord: length (8 bytes), its CRC (4), the record, its CRC (4)
        n = int.from_bytes(data[at : at + 8], "little")
        event = event_pb2.Event.FromString(data[at + 12 : at + 12 + n])
        at += 16 + n
        for v in event.summary.value:
            scalars[(v.tag, event.step)] = v.simple_value
    # updates 4 and 5 (after 3 before them) at 100 env steps per update: seed means, NaN seeds left out
    assert scalars == {("train/success", 400): 0.5, ("train/success", 500): 0.5}


def test_resume_of_a_folder_without_a_checkpoint_is_one_line_naming_the_file(tmp_path, capsys):
    from histojax.cli import main

    (tmp_path / "run").mkdir()
    assert main(["train", "--resume", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path / "run" / "checkpoint" / "config.json") in err[0], err
    assert "nothing to resume" in err[0]


def test_resume_of_a_corrupt_or_foreign_checkpoint_names_it(tmp_path, capsys):
    from histojax.cli import main

    folder = tmp_path / "run" / "checkpoint"
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({**ppo.DEFAULTS, **TINY, "seed": 0}))
    (folder / "runner.msgpack").write_bytes(b"\x93not msgpack at all")
    assert main(["train", "--resume", str(tmp_path / "run")]) == 2
    # (the sample slide's bundle may be built into the cache first, with a progress bar)
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("building ")]
    assert len(err) == 1 and f"{folder / 'runner.msgpack'}: not a" in err[0], err
    # a checkpoint of another trainer is named too, before anything is compiled
    (folder / "config.json").write_text(json.dumps({**TINY, "algo": "dqn"}))
    assert main(["train", "--algo", "ppo", "--resume", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a dqn run; resume it with --algo dqn" in err[0], err
    # without --algo, the run's own trainer resumes it (here: DQN, which then names the corrupt state)
    dqn_config = {k: v for k, v in {**dqn.DEFAULTS, **TINY, "algo": "dqn"}.items() if k in dqn.DEFAULTS or k == "seed"}
    (folder / "config.json").write_text(json.dumps({**dqn_config, "seed": 0}))
    assert main(["train", "--resume", str(tmp_path / "run")]) == 2
    # (the sample slide's bundle may be built into the cache first, with a progress bar)
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("building ")]
    assert len(err) == 1 and f"{folder / 'runner.msgpack'}: not a" in err[0], err


def test_a_checkpoint_of_another_config_is_refused(tmp_path):
    """A runner state whose arrays do not fit the config (e.g. another width) names the file, not a flax error."""
    train = ppo.make_train(TINY)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    start, _ = chunked_runner(train)
    template = start.template(keys)
    fake = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), template)
    save_runner(tmp_path, fake, 2, {}, 0.0, train.config, train.num_updates, start.size)
    runners, done, _, _ = load_runner(tmp_path, template, train.num_updates, start.size)
    assert done == 2
    wider = ppo.make_train({**TINY, "hidden": 32})
    with pytest.raises(HistojaxDataError, match="do not match the runner state"):
        load_runner(tmp_path, chunked_runner(wider)[0].template(keys), train.num_updates, start.size)
    with pytest.raises(HistojaxDataError, match="saved for 5 updates in chunks of 2"):
        load_runner(tmp_path, template, train.num_updates, 3)
    # the same shapes but another config (a new run started in the folder, killed before its first checkpoint)
    load_runner(tmp_path, template, train.num_updates, start.size, train.config)
    with pytest.raises(HistojaxDataError, match="written by a run of another config"):
        load_runner(tmp_path, template, train.num_updates, start.size, {**train.config, "lr": 1e-3})


def _full_disk_on(monkeypatch, name: str):
    """``open`` in baselines.outputs gives files that raise ENOSPC on their first write when the file being
    written is (a temporary of) ``name``."""
    real = builtins.open

    class Full:
        def __init__(self, f):
            self.f = f

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        def __getattr__(self, attr):
            return getattr(self.f, attr)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    def fake_open(file, mode="r", *a, **k):
        f = real(file, mode, *a, **k)
        stem = name.split(".")[0]
        return Full(f) if "w" in mode and stem in str(file).rsplit("/", 1)[-1] else f

    monkeypatch.setattr(outputs, "open", fake_open, raising=False)


def test_a_run_on_a_full_disk_keeps_the_previous_runs_files_together_and_names_the_file(tmp_path, monkeypatch):
    """Was: the new log.csv / log.json / curve.png were in place beside the previous run's params.msgpack
    (each file atomic, the set not), and the error named no file. Now the run's files are staged and renamed
    together: the previous run's five files stay as they were, no temporary file is left, and the error names
    params.msgpack."""
    _no_reference(monkeypatch)
    out = tmp_path / "run"
    metrics = {k: np.full((1, 3), 0.5) for k in ("return", "success", "length", "steps_to_success")}
    config = {**ppo.DEFAULTS, **TINY}
    finish_run("ppo", config, out, {"w": np.arange(10, dtype=np.float32)}, metrics, 32, 1.0, 1.0)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(before) == ["config.json", "curve.png", "log.csv", "log.json", "params.msgpack"]
    _full_disk_on(monkeypatch, "params.msgpack")
    new = {k: np.zeros((1, 5)) for k in metrics}
    with pytest.raises(OSError) as e:
        finish_run("ppo", {**config, "lr": 1e-3}, out, {"w": np.zeros(10, np.float32)}, new, 32, 1.0, 1.0)
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(out / "params.msgpack")
    monkeypatch.undo()
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_train_dataset_and_split_options_reach_make():
    args = ppo.parse_args(["--dataset", "DS", "--split", "test", "--set", 'env_kwargs={"tumour_slides_only": true}'])
    config = ppo.config_from_args(args)
    assert config["env_kwargs"] == {"tumour_slides_only": True, "dataset": "DS", "split": "test"}
    assert env_overrides(config)["dataset"] == "DS" and env_overrides(config)["split"] == "test"
    with pytest.raises(SystemExit, match="--split needs --dataset"):
        ppo.config_from_args(ppo.parse_args(["--split", "test"]))
    assert ppo.config_from_args(ppo.parse_args(["--checkpoint-every", "7"]))["checkpoint_every"] == 7
