"""Slides sharded over devices (``histojax.sharding``, PPO ``--shard-slides``).

Several devices on CPU exist only if ``XLA_FLAGS=--xla_force_host_platform_device_count=4`` is set
before jax is imported, so the checks run in a subprocess (``sys.executable``) on a dataset of
small semi-synthetic slides built here, and save what the tests assert:

* memory: each device's addressable shards of the slide arrays hold about a quarter of the
  bytes of the same 8 slides stacked on one device (padding to the largest group makes it a bit
  more), and the compiled 4-device PPO program takes about a quarter of them as its per-device
  arguments (``memory_analysis``) — with the slides replicated it would take all of them;
* trajectories: 5 slides over 4 devices (groups of 2, 1, 1, 1: slides and pools padded), 8 envs
  (2 per device), 12 random steps: every env's observations, states and rewards equal those of
  the same env on one device made from its device's slides only, with the same keys and actions;
* PPO trains on the sharded dataset (3 updates, finite losses, the parameters identical on all
  4 devices: XLA's gradient all-reduce).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from baselines import ppo
from baselines.harness.distributed import cpu_child_env
from histojax import sharding

ROOT = Path(__file__).resolve().parents[2]

CHILD = r"""
import json, sys
import jax, jax.numpy as jnp, numpy as np
from jax.sharding import Mesh
import histojax
from histojax import sharding
from baselines import ppo
from baselines.harness.runner import compile_seeds

paths, out = json.loads(sys.argv[1]), sys.argv[2]
assert len(jax.devices()) == 4, jax.devices()
mesh = Mesh(np.array(jax.devices()), ("batch",))
saved = {}

# memory: 8 slides, 2 per device
env, params = sharding.make_sharded("HistoJAX-Easy-v0", mesh, slides=paths)
per_device = sharding.device_bytes(params.slide)
_, whole = histojax.make("HistoJAX-Easy-v0", slides=paths)
saved["per_device_bytes"] = [per_device[d] for d in mesh.devices.flat]
saved["whole_bytes"] = sum(int(a.nbytes) for a in jax.tree.leaves(whole.slide))
saved["pixel_rows"] = int(params.slide.pixels.shape[1])

# trajectories: 5 slides over 4 devices, 8 envs, 12 random steps
n, steps = 8, 12
five = paths[:5]
env, params = sharding.make_sharded("HistoJAX-Easy-v0", mesh, slides=five)
keys = jax.random.split(jax.random.PRNGKey(3), steps + 1)
step_keys = jnp.stack([jax.random.split(k, n) for k in keys[1:]])
actions = jax.random.randint(jax.random.PRNGKey(4), (steps, n), 0, 7)

def rollout(reset_all, step_all, reset_keys, step_keys, actions, p):
    obs, s = reset_all(reset_keys, p)
    def body(s, x):
        k, a = x
        obs, s, r, term, trunc, _ = step_all(k, s, a, p)
        return s, (obs, s, r, term, trunc)
    _, traj = jax.lax.scan(body, s, (step_keys, actions))
    return obs, traj

sharded = jax.jit(lambda *a: rollout(sharding.vmap_local(env.reset, mesh, 1), sharding.vmap_local(env.step, mesh, 3), *a))
first, traj = sharded(jax.random.split(keys[0], n), step_keys, actions, params)
groups = sharding.slide_groups(five, mesh)
saved["group_sizes"] = [len(g) for g in groups]
equal = []
for d, group in enumerate(groups):
    e1, p1 = histojax.make("HistoJAX-Easy-v0", slides=group, slide_weights=[1.0] * len(group))
    block = slice(2 * d, 2 * d + 2)
    one = jax.jit(lambda *a: rollout(jax.vmap(e1.reset, in_axes=(0, None)), jax.vmap(e1.step, in_axes=(0, 0, 0, None)), *a))
    first1, traj1 = one(jax.random.split(keys[0], n)[block], step_keys[:, block], actions[:, block], p1)
    mine = jax.tree.map(lambda a: np.asarray(a)[block], first), jax.tree.map(lambda a: np.asarray(a)[:, block], traj)
    theirs = jax.tree.map(np.asarray, (first1, traj1))
    equal.append(all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(mine), jax.tree.leaves(theirs))))
    saved[f"slides_drawn_{d}"] = np.unique(np.asarray(traj[1].slide_index)[:, block]).tolist()
saved["trajectories_equal"] = equal
saved["moved"] = int(np.asarray(traj[1].z).max())

# PPO on the 8 slides sharded over the 4 devices
config = dict(env_id="HistoJAX-Easy-v0", num_envs=8, num_steps=16, total_timesteps=384, update_epochs=1,
              num_minibatches=2, hidden=32, num_seeds=1, print_progress=False, devices=4, shard_slides=True,
              env_kwargs={"slides": paths})
train = ppo.make_train(config)
keys = jax.random.split(jax.random.PRNGKey(0), 1)
compiled = compile_seeds(train, keys)
saved["ppo_argument_bytes"] = int(compiled.exe.memory_analysis().argument_size_in_bytes)
result = jax.block_until_ready(compiled(keys))
leaf = jax.tree.leaves(result["params"])[0]
saved["ppo_params_same_on_devices"] = all(np.array_equal(np.asarray(s.data), np.asarray(leaf.addressable_shards[0].data))
                                          for s in leaf.addressable_shards) and len(leaf.addressable_shards) == 4
saved["ppo_losses"] = {k: np.asarray(v).tolist() for k, v in result["metrics"].items() if k in ("pg_loss", "v_loss")}
saved["ppo_episodes"] = float(np.asarray(result["metrics"]["episodes"]).sum())
json.dump(saved, open(out, "w"))
"""


@pytest.fixture(scope="module")
def runs(small_slides, tmp_path_factory):
    out = tmp_path_factory.mktemp("shard-run") / "saved.json"
    env = cpu_child_env(4, fast_compile=True)
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(small_slides), str(out)],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-5000:]
    return json.loads(out.read_text())


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_each_device_holds_about_a_quarter_of_the_slides(runs):
    whole, per = runs["whole_bytes"], runs["per_device_bytes"]
    assert len(per) == 4 and len(set(per)) == 1  # padded to one shape
    assert 0.2 * whole <= per[0] <= 0.3 * whole, (per, whole)
    # the compiled PPO program takes one device's share as its per-device arguments (not all slides)
    assert runs["ppo_argument_bytes"] < 0.3 * whole, (runs["ppo_argument_bytes"], whole)
    assert runs["ppo_argument_bytes"] >= per[0]


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_an_env_on_its_device_equals_the_same_env_on_one_device(runs):
    assert runs["group_sizes"] == [2, 1, 1, 1]
    assert runs["trajectories_equal"] == [True] * 4
    assert runs["moved"] > 0  # the random actions did zoom in
    assert set(runs["slides_drawn_0"]) <= {0, 1}
    for d in (1, 2, 3):  # the padded second slide (weight 0) is never drawn
        assert runs[f"slides_drawn_{d}"] == [0]


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_ppo_trains_on_sharded_slides(runs):
    assert runs["ppo_params_same_on_devices"]
    for name, values in runs["ppo_losses"].items():
        assert np.isfinite(values).all() and np.shape(values) == (1, 3), name
    assert runs["ppo_episodes"] > 0


def test_clear_errors():
    with pytest.raises(ValueError, match="3 slide\\(s\\) cannot be sharded over 4 devices"):
        sharding.round_robin([1, 2, 3], 4)
    assert sharding.round_robin(list(range(5)), 2) == [[0, 2, 4], [1, 3]]
    with pytest.raises(ValueError, match="give devices=N too"):
        ppo.make_train({"shard_slides": True, "num_envs": 8})
    config = ppo.config_from_args(ppo.parse_args(["--devices", "4", "--shard-slides"]))
    assert config["shard_slides"] and config["devices"] == 4
