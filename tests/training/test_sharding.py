"""``--devices N``: PPO with the env batch sharded over a ``jax.sharding.Mesh``.

The sharded run needs several devices, and on CPU those exist only if
``XLA_FLAGS=--xla_force_host_platform_device_count=4`` is set before jax is imported, so it runs
in a subprocess (``sys.executable``) that trains the same tiny config twice: on one device
(``devices=None``) and on 4 (``devices=4``), and saves what the test checks:

* the sharding is real: the compiled, SPMD-partitioned program of the 4-device run renders
  per-device views of ``num_envs / 4`` envs (``u8[1,2,128,128,3]``: seed, envs, view; or
  ``u8[1,2,32,32,3]`` where XLA fuses the render into the policy's pooling) and never the whole batch's
  (``u8[1,8,...]``), while the one-device program renders all 8 — with the
  sharding constraints removed (a no-op sharding) the 4-device program would render all 8 on
  every device and this fails;
* it trains and matches the one-device run for the same seed: final parameters within
  ``rtol=1e-4, atol=1e-6`` (measured: max abs difference ~3e-8, the order of float sums in the
  gradient all-reduce), the per-update metrics within ``rtol=1e-4, atol=1e-5`` (the losses are
  ~1e-5 themselves), losses finite, and the progress callback still prints.

Both compiles use ``--xla_backend_optimization_level=0`` (same flags for both runs) to keep the
test at ~25 s on 2 cores. The clear errors (``num_envs`` not divisible, too few devices, DQN)
run in-process.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from baselines import dqn, ppo
from baselines.common.devices import batch_mesh
from baselines.harness.distributed import cpu_child_env

ROOT = Path(__file__).resolve().parents[2]
TINY = dict(
    env_id="HistoJAX-Easy-v0",
    num_envs=8,
    num_steps=16,
    total_timesteps=384,
    update_epochs=1,
    num_minibatches=2,
    hidden=32,
    num_seeds=1,
    print_progress=True,
    log_every=1,
)

CHILD = r"""
import json, sys
import jax, numpy as np
from baselines import ppo
from baselines.harness.runner import compile_seeds

config, out = json.loads(sys.argv[1]), sys.argv[2]
assert len(jax.devices()) == 4, jax.devices()
keys = jax.random.split(jax.random.PRNGKey(0), config["num_seeds"])
saved = {}
for name, devices in (("one", None), ("four", 4)):
    train = ppo.make_train({**config, "devices": devices})
    view = jax.eval_shape(lambda k: train.env.reset(k, train.env_params)[0], keys[0]).shape
    compiled = compile_seeds(train, keys)
    hlo = compiled.exe.as_text()
    result = jax.block_until_ready(compiled(keys))
    leaves = jax.tree.leaves(result["params"])
    saved[name + "_param_devices"] = len(leaves[0].sharding.device_set)
    # the env batch's views, as rendered or (when XLA fuses the render into the policy's pooling, the step
    # observing once) as pooled for the policy: seed, envs, then the view's or the pooled view's shape
    from baselines.networks import POOLED_SIZE
    shapes = (tuple(view), (POOLED_SIZE, POOLED_SIZE, view[-1]))
    per_device = lambda n: ["u8[%d,%d,%s]" % (config["num_seeds"], n, ",".join(map(str, s))) for s in shapes]
    saved[name + "_renders_all"] = any(s in hlo for s in per_device(config["num_envs"]))
    saved[name + "_renders_quarter"] = any(s in hlo for s in per_device(config["num_envs"] // 4))
    for i, leaf in enumerate(leaves):
        saved[f"{name}_param_{i}"] = np.asarray(leaf)
    for k, v in result["metrics"].items():
        saved[f"{name}_metric_{k}"] = np.asarray(v)
np.savez(out, **saved)
"""


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = tmp_path_factory.mktemp("sharding") / "runs.npz"
    env = cpu_child_env(4, fast_compile=True)
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(TINY), str(out)],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-5000:]
    return dict(np.load(out)), proc.stdout


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_env_batch_is_split_over_four_devices(runs):
    saved, _ = runs
    assert saved["one_renders_all"] and not saved["one_renders_quarter"]
    assert saved["four_renders_quarter"], "the 4-device program does not render 2 envs per device"
    assert not saved["four_renders_all"], "the 4-device program renders the whole env batch somewhere"
    assert saved["one_param_devices"] == 1 and saved["four_param_devices"] == 4  # params replicated on the mesh


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_sharded_run_trains_and_matches_one_device(runs):
    saved, stdout = runs
    params = sorted(k for k in saved if k.startswith("one_param_") and k != "one_param_devices")
    assert params
    for k in params:
        np.testing.assert_allclose(saved["four" + k[3:]], saved[k], rtol=1e-4, atol=1e-6, err_msg=k)
    metrics = sorted(k for k in saved if k.startswith("one_metric_"))
    for k in metrics:
        np.testing.assert_allclose(saved["four" + k[3:]], saved[k], rtol=1e-4, atol=1e-5, err_msg=k)
    for name in ("one", "four"):
        for m in ("pg_loss", "v_loss", "entropy", "approx_kl"):
            v = saved[f"{name}_metric_{m}"]
            assert v.shape == (1, 3) and np.isfinite(v).all(), (name, m)
        assert saved[f"{name}_metric_episodes"][0, 0] > 0
        v_loss = saved[f"{name}_metric_v_loss"][0]
        assert v_loss[-1] < v_loss[0]  # the value function fits the returns: it learns
    # the progress callback (jax.pure_callback) runs in both programs
    assert stdout.count("update 3/3") == 2, stdout


def test_clear_errors_for_bad_device_counts():
    with pytest.raises(ValueError, match="num_envs=6 must divide by devices=4"):
        ppo.make_train({**TINY, "num_envs": 6, "devices": 4})
    too_many = len(jax.devices()) + 1
    with pytest.raises(ValueError, match=f"xla_force_host_platform_device_count={too_many}"):
        ppo.make_train({**TINY, "num_envs": 8 * too_many, "devices": too_many})
    with pytest.raises(ValueError, match="devices must be >= 1"):
        batch_mesh(0, 8)
    assert batch_mesh(None, 8) is None
    with pytest.raises(ValueError, match="PPO only"):
        dqn.make_train({"devices": 1})


def test_devices_flag_on_the_command_line():
    config = ppo.config_from_args(ppo.parse_args(["--devices", "4"]))
    assert config["devices"] == 4
    assert ppo.config_from_args(ppo.parse_args([]))["devices"] is None
    with pytest.raises(SystemExit, match="PPO baseline only"):
        ppo.config_from_args(ppo.parse_args(["--devices", "2"], defaults=dqn.DEFAULTS), defaults=dqn.DEFAULTS)
