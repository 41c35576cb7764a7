"""What the rejax and Stable-Baselines3 snippets of docs/integrations.md learn, beside a random policy.

Trains rejax's PPO (the ``rejax`` extra) and SB3's PPO with ``MlpPolicy`` (the ``sb3`` extra) on
``HistoJAX-Easy-v0`` with ``max_steps_in_episode=50`` and ``obs_mode="features"`` (the view's feature
vector instead of its pixels: cheap enough for a CPU), with the snippets' settings, and evaluates each
trained policy on fresh episodes of the same env beside uniform random actions. Prints, per agent and
budget: mean return per episode, success rate (episodes that found the tumour), mean episode length,
and the wall time of training.

``obs_mode="features"`` needs a bundle with a feature grid; the sample slide's bundle has none. When
``--slide DIR`` does not exist, the sample bundle is copied to ``DIR`` and its feature grid computed there
(``python -m data_tools features DIR``: efficientnet-lite0, 1280-d, 1.5–3 min on a 2-core CPU; needs torch,
which the ``sb3`` extra brings); an existing ``DIR`` must be a bundle with features::

    python -m experiments.integrations_learning --slide easy-features [--algo random rejax sb3] [--seed 0]

Budgets: rejax 100 k env steps (16 envs, rejax's defaults otherwise, as in the snippet); SB3 20 k and
100 k env steps (16 envs, ``n_steps=64``, SB3's defaults otherwise; one run, evaluated at 20 k and again
after training on to 100 k). Evaluation: ``--episodes`` episodes (default 1024), each from its own reset.
"""

from __future__ import annotations

import argparse
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import histojax

ENV_ID = "HistoJAX-Easy-v0"
MAX_STEPS = 50


def make_env(slide: str):
    """The measured env: ``HistoJAX-Easy-v0`` on ``slide``, 50 steps, features observed."""
    return histojax.make(ENV_ID, slide=slide, max_steps_in_episode=MAX_STEPS, obs_mode="features")


def prepare(slide: str) -> None:
    """Make ``slide`` (a folder that does not exist yet) a copy of the sample Easy bundle with an
    efficientnet-lite0 feature grid; built in a temporary sibling and renamed, so never half-written."""
    target = Path(slide)
    if target.exists():
        return
    source = histojax.make(ENV_ID)[0].bundles[0].path
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent)) / "bundle"
    try:
        shutil.copytree(source, tmp)
        subprocess.run([sys.executable, "-m", "data_tools", "features", str(tmp), "--quiet"], check=True)
        tmp.rename(target)
    finally:
        shutil.rmtree(tmp.parent, ignore_errors=True)


def evaluate_jax(env, params, act, key, episodes: int) -> dict:
    """Run ``episodes`` episodes (one each, from its own reset) of ``act(obs, key) -> action`` (jittable,
    one observation) on the 6-value env; mean return per episode, success rate, mean length."""

    def one(k):
        k_reset, k_run = jax.random.split(k)
        obs, state = env.reset(k_reset, params)

        def body(carry, k_t):
            obs, state, done, ret, success, length = carry
            k_act, k_step = jax.random.split(k_t)
            action = act(obs, k_act)
            obs2, state2, reward, term, trunc, info = env.step(k_step, state, action, params)
            live = jnp.logical_not(done)
            ended = jnp.logical_or(term, trunc)
            ret = ret + jnp.where(live, reward, 0.0)
            success = jnp.where(live & ended, info["success"], success)
            length = length + live.astype(jnp.int32)
            return (obs2, state2, done | ended, ret, success, length), None

        carry = (obs, state, jnp.array(False), jnp.float32(0.0), jnp.array(False), jnp.int32(0))
        (_, _, _, ret, success, length), _ = jax.lax.scan(body, carry, jax.random.split(k_run, MAX_STEPS))
        return ret, success, length

    ret, success, length = jax.jit(jax.vmap(one))(jax.random.split(key, episodes))
    return {"return": float(ret.mean()), "success": float(success.mean()), "length": float(length.mean())}


def random_row(env, params, seed: int, episodes: int) -> dict:
    """Uniform random actions (the env's action space)."""
    space = env.action_space(params)
    return evaluate_jax(env, params, lambda obs, k: space.sample(k), jax.random.PRNGKey(10_000 + seed), episodes)


def rejax_rows(env, params, seed: int, episodes: int) -> list[dict]:
    """The rejax snippet (100 k env steps, 16 envs, rejax's PPO defaults) on the features env; the trained
    actor evaluated sampling its actions (as rejax's own evaluation does) and greedily."""
    import rejax

    from histojax import GymnaxV0Wrapper

    algo = rejax.PPO.create(env=GymnaxV0Wrapper(env), env_params=params, total_timesteps=100_000, num_envs=16)
    start = time.perf_counter()
    ts, (lengths, returns) = jax.jit(algo.train)(jax.random.PRNGKey(seed))
    jax.block_until_ready(ts)
    wall = time.perf_counter() - start
    curve = np.asarray(returns).mean(axis=1)
    sampled = algo.make_act(ts)

    def greedy(obs, k):
        logits = algo.actor.apply(ts.actor_ts.params, obs[None], method="_action_dist").logits
        return jnp.argmax(logits[0])

    base = {
        "agent": "rejax 0.1.3 PPO",
        "steps": int(ts.global_step),
        "train_s": wall,
        "rejax_eval": " ".join(f"{r:.2f}" for r in curve),
    }
    key = jax.random.PRNGKey(20_000 + seed)
    return [
        {**base, "policy": "sampled", **evaluate_jax(env, params, sampled, key, episodes)},
        {**base, "policy": "greedy", **evaluate_jax(env, params, greedy, key, episodes)},
    ]


def evaluate_sb3(model, slide: str, seed: int, episodes: int, deterministic: bool, num_envs: int = 64) -> dict:
    """``episodes`` episodes of an SB3 model on :class:`SB3VecEnv` (``episodes / num_envs`` per sub-env)."""
    from histojax.adapters.sb3 import make_sb3_vec_env

    venv = make_sb3_vec_env(ENV_ID, num_envs=num_envs, slide=slide, max_steps_in_episode=MAX_STEPS, obs_mode="features")
    venv.seed(30_000 + seed)
    obs = venv.reset()
    per_env = -(-episodes // num_envs)
    acc = np.zeros(num_envs)
    rets, succ, lens, steps = (
        [[] for _ in range(num_envs)],
        [[] for _ in range(num_envs)],
        [[] for _ in range(num_envs)],
        np.zeros(num_envs, int),
    )
    while min(len(r) for r in rets) < per_env:
        action, _ = model.predict(obs, deterministic=deterministic)
        obs, reward, done, infos = venv.step(action)
        acc += reward
        steps += 1
        for i in np.flatnonzero(done):
            if len(rets[i]) < per_env:
                rets[i].append(acc[i])
                succ[i].append(bool(infos[i]["success"]))
                lens[i].append(steps[i])
            acc[i], steps[i] = 0.0, 0
    venv.close()
    flat = lambda xs: np.concatenate([np.asarray(x, float) for x in xs])  # noqa: E731
    return {"return": float(flat(rets).mean()), "success": float(flat(succ).mean()), "length": float(flat(lens).mean())}


def sb3_rows(slide: str, seed: int, episodes: int) -> list[dict]:
    """The SB3 snippet with ``MlpPolicy`` on features (16 envs, ``n_steps=64``): evaluated at 20 k env
    steps, then trained on to 100 k and evaluated again; deterministic and sampled actions."""
    import stable_baselines3
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor

    from histojax.adapters.sb3 import make_sb3_vec_env

    venv = VecMonitor(
        make_sb3_vec_env(ENV_ID, num_envs=16, slide=slide, max_steps_in_episode=MAX_STEPS, obs_mode="features")
    )
    model = PPO("MlpPolicy", venv, n_steps=64, seed=seed)
    rows, wall = [], 0.0
    for budget in (20_000, 100_000):
        start = time.perf_counter()
        model.learn(total_timesteps=budget - model.num_timesteps, reset_num_timesteps=False)
        wall += time.perf_counter() - start
        base = {
            "agent": f"SB3 {stable_baselines3.__version__} PPO MlpPolicy (torch {torch.__version__})",
            "steps": int(model.num_timesteps),
            "train_s": wall,
        }
        for deterministic in (True, False):
            rows.append(
                {
                    **base,
                    "policy": "deterministic" if deterministic else "sampled",
                    **evaluate_sb3(model, slide, seed, episodes, deterministic),
                }
            )
    return rows


def show(row: dict) -> None:
    """One printed line per measured row (flushed: the runs are long)."""
    extra = f"  rejax eval curve: {row['rejax_eval']}" if "rejax_eval" in row else ""
    train = f"  trained {row['steps']:,} env steps in {row['train_s']:.0f} s" if "steps" in row else ""
    print(
        f"{row['agent']:<48} {row.get('policy', ''):<13} return {row['return']:6.2f}  success "
        f"{100 * row['success']:5.1f} %  length {row['length']:5.1f}{train}{extra}",
        flush=True,
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--slide",
        required=True,
        help="bundle folder with a feature grid; made from the sample "
        "slide's bundle (features computed) when it does not exist",
    )
    p.add_argument("--algo", nargs="+", choices=["random", "rejax", "sb3"], default=["random", "rejax", "sb3"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=1024, help="evaluation episodes per policy")
    args = p.parse_args()
    try:
        prepare(args.slide)
    except subprocess.CalledProcessError as e:
        print(f"{args.slide}: computing the feature grid failed (exit {e.returncode})", file=sys.stderr)
        raise SystemExit(2)
    try:
        env, params = make_env(args.slide)
    except Exception as e:  # a bundle without features, or no bundle: one line naming it
        print(str(e) if args.slide in str(e) else f"{args.slide}: {e}", file=sys.stderr)
        raise SystemExit(2)
    print(
        f"{ENV_ID}, max_steps_in_episode={MAX_STEPS}, obs_mode='features' {env.observation_space(params).shape}; "
        f"jax {jax.__version__}; {platform.machine()}; seed {args.seed}; {args.episodes} evaluation episodes",
        flush=True,
    )
    start = time.perf_counter()
    if "random" in args.algo:
        show({"agent": "random actions", **random_row(env, params, args.seed, args.episodes)})
    if "rejax" in args.algo:
        for row in rejax_rows(env, params, args.seed, args.episodes):
            show(row)
    if "sb3" in args.algo:
        for row in sb3_rows(args.slide, args.seed, args.episodes):
            show(row)
    print(f"total wall time {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
