"""The declared trainer: ``make_train`` of every algorithm returns a frozen :class:`Trainer`, the harness owns the
one loop over updates, and its one-shot run (``run_seeds``) equals its run in chunks (``run_chunked``)."""

import ast
import dataclasses
from pathlib import Path

import jax
import numpy as np
import ppo_configs
import pytest

from baselines import dqn, ppo, ppo_rnn
from baselines.harness.runner import compile_seeds, run_chunked, run_seeds
from baselines.harness.trainer import Trainer

ROOT = Path(__file__).resolve().parents[2]
TINY = {**ppo_configs.TINY, "total_timesteps": 96, "num_seeds": 2, "checkpoint_every": 2}
TINY_DQN = dict(
    env_id="HistoJAX-Easy-v0",
    with_position=True,
    num_envs=4,
    total_timesteps=192,
    buffer_size=256,
    learning_starts=16,
    batch_size=16,
    iterations_per_log=16,
    hidden=16,
    num_seeds=1,
    print_progress=False,
)


@pytest.mark.parametrize("module, config", [(ppo, TINY), (ppo_rnn, TINY), (dqn, TINY_DQN)])
def test_make_train_of_every_algorithm_returns_a_frozen_trainer_with_its_metric_keys(module, config):
    """A :class:`Trainer`, nothing pinned on it afterwards (frozen), whose ``update`` emits exactly the metric keys
    it declares (traced with ``jax.eval_shape``, nothing runs)."""
    trainer = module.make_train(config)
    assert type(trainer) is Trainer
    with pytest.raises(dataclasses.FrozenInstanceError):
        trainer.chunked = None
    assert trainer.config == trainer.train_config.as_dict() and trainer.num_updates >= 1
    key = jax.random.PRNGKey(0)
    params = jax.eval_shape(trainer.init_params, key, trainer.env_params)
    runner = jax.eval_shape(trainer.init_runner, key, trainer.env_params, params)
    _, metrics = jax.eval_shape(trainer.update, runner, np.int32(0), trainer.env_params)
    assert set(metrics) == set(trainer.metric_keys)
    got = jax.eval_shape(trainer.runner_params, runner)
    assert jax.tree.structure(got) == jax.tree.structure(params)


def _scans(path: Path) -> list[str]:
    """The source of every ``lax.scan(...)`` call in ``path``."""
    text = path.read_text()
    calls = [n for n in ast.walk(ast.parse(text)) if isinstance(n, ast.Call)]
    return [ast.get_source_segment(text, n) for n in calls if ast.unparse(n.func).endswith("lax.scan")]


def test_the_harness_owns_the_one_loop_over_updates():
    """No algorithm file scans over its updates (the update index, ``num_updates`` / ``num_logs``, or its own
    ``update``); the harness's :func:`scan_updates` is the one loop, defined once."""
    for name in ("ppo.py", "ppo_rnn.py", "dqn.py"):
        for call in _scans(ROOT / "baselines" / name):
            assert not any(w in call for w in ("num_updates", "num_logs", "update(", "n_updates")), (name, call)
    defined = [p for p in (ROOT / "baselines").rglob("*.py") if "def scan_updates(" in p.read_text()]
    assert defined == [ROOT / "baselines" / "harness" / "runner.py"]


def test_one_shot_run_equals_its_compiled_call_and_nearly_the_run_in_chunks(tmp_path):
    """PPO's 3 updates in one program (:func:`run_seeds`) and ahead-of-time compiled (:func:`compile_seeds`): the
    same params and metrics bit for bit; in chunks of 2 with checkpoints (:func:`run_chunked`, the last chunk
    skipping one update, another compiled program) the same to float rounding."""
    trainer = ppo.make_train(TINY)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    one = jax.device_get(run_seeds(trainer, keys))
    compiled = jax.device_get(compile_seeds(trainer, keys)(keys))
    chunked, _, _ = run_chunked(trainer, tmp_path / "run", keys)
    for other, exact in ((compiled, True), (chunked, False)):
        check = np.testing.assert_array_equal if exact else lambda a, b: np.testing.assert_allclose(a, b, 1e-4, 1e-6)
        for a, b in zip(jax.tree.leaves(one["params"]), jax.tree.leaves(other["params"]), strict=True):
            check(np.asarray(a), np.asarray(b))
        for k in ("pg_loss", "v_loss", "entropy", "approx_kl"):
            check(np.asarray(one["metrics"][k]), np.asarray(other["metrics"][k]))
