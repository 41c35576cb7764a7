"""The environment half of `make demo`: jitted, vmapped random-agent episodes on Easy / Medium /
Hard of the embedded sample slide, a table of steps/s, episode return and success rate, and a
trajectory picture. `make demo` (``python -m baselines.demo``) runs this, then trains PPO.

    python -m histojax.demo [--envs 256] [--steps 400] [--out out/]
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import histojax
from histojax.render import animate, render_trajectory
from histojax.wrappers import LogWrapper

SCENARIOS = ("HistoJAX-Easy-v0", "HistoJAX-Medium-v0", "HistoJAX-Hard-v0")


def make_random_rollout(env, num_envs: int, num_steps: int):
    """A jitted function ``(key, params) -> (info, last observations)`` that runs ``num_steps`` steps of ``num_envs``
    random-agent environments (auto-reset, episode statistics, every observation extracted) with
    ``lax.scan`` over ``vmap``."""
    env = LogWrapper(env)
    space = env.action_space()

    def rollout(key, params):
        key, key_reset = jax.random.split(key)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key_reset, num_envs), params)

        def body(carry, key):
            state, _ = carry
            key_act, key_step = jax.random.split(key)
            action = jax.vmap(space.sample)(jax.random.split(key_act, num_envs))
            obs, state, reward, _, _, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key_step, num_envs), state, action, params)
            keep = ("returned_episode", "returned_episode_returns", "returned_episode_success")
            # the observations go into the carry, so every view is really extracted (a random agent
            # ignores them, and XLA would otherwise skip the crop and overstate steps/s)
            return (state, obs), {k: info[k] for k in keep}

        (_, last_obs), infos = jax.lax.scan(body, (state, obs), jax.random.split(key, num_steps))
        return infos, last_obs  # returning the carried views keeps them alive

    return jax.jit(rollout)


def first_episode(env, params, key, num_envs: int = 64):
    """``(z, x, y)`` sequences of one random-agent episode (a successful one when any of
    ``num_envs`` tries succeeds), from the start to the step that ended it."""
    env = histojax.HistoEnv(**{**env.__dict__, "auto_reset": False})
    space = env.action_space()
    steps = int(params.max_steps_in_episode)

    @jax.jit
    def run(key):
        key, key_reset = jax.random.split(key)
        _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key_reset, num_envs), params)

        def body(carry, key):
            state, done = carry
            action = jax.vmap(space.sample)(jax.random.split(key, num_envs))
            _, new, _, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key, num_envs), state, action, params)
            new = jax.tree.map(lambda a, b: jnp.where(done, a, b), state, new)  # freeze finished envs
            return (new, done | term | trunc), (new.z, new.x, new.y, done, info["success"] & ~done)

        (_, _), out = jax.lax.scan(body, (state, jnp.zeros(num_envs, bool)), jax.random.split(key, steps))
        return state, out

    start, (z, x, y, done_before, success) = jax.device_get(run(key))
    success_any = success.any(axis=0)
    pick = int(np.argmax(success_any)) if success_any.any() else 0
    length = int((~done_before[:, pick]).sum())
    zs = np.concatenate([[start.z[pick]], z[:length, pick]])
    xs = np.concatenate([[start.x[pick]], x[:length, pick]])
    ys = np.concatenate([[start.y[pick]], y[:length, pick]])
    return zs, xs, ys, bool(success_any[pick])


def random_agent_table(num_envs: int = 256, num_steps: int = 400, seed: int = 0, out="out",
                       scenarios=SCENARIOS, picture_max_steps: int | None = None) -> dict:
    """Print the random-agent table (one row per scenario: levels, steps/s, compile seconds,
    finished episodes, mean return, success rate) and write ``demo_trajectory.png`` / ``.gif``
    (one random Easy episode over the slide; ``picture_max_steps`` shortens its step limit, for
    quick runs) to ``out``. Returns ``{"rows": [...], "files": [...]}``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    key = jax.random.PRNGKey(seed)
    for env_id in scenarios:
        env, params = histojax.make(env_id)
        rollout = make_random_rollout(env, num_envs, num_steps)
        t0 = time.perf_counter()
        jax.block_until_ready(rollout(key, params))
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        info, _ = jax.device_get(rollout(jax.random.fold_in(key, 1), params))
        run_s = time.perf_counter() - t0
        done = info["returned_episode"]
        n_episodes = int(done.sum())
        mean_return = float(info["returned_episode_returns"][done].mean()) if n_episodes else float("nan")
        success = float(info["returned_episode_success"][done].mean()) if n_episodes else float("nan")
        rows.append({"env_id": env_id, "levels": env.n_levels, "steps_per_second": num_envs * num_steps / run_s,
                     "compile_seconds": compile_s, "episodes": n_episodes, "mean_return": mean_return,
                     "success_rate": success})
    print(f"\nrandom agent, {num_envs} envs × {num_steps} steps, reward preset 'dense'")
    print(f"{'scenario':<20} {'levels':>6} {'steps/s':>12} {'compile s':>9} {'episodes':>8} {'mean return':>11} "
          f"{'target reached':>14}")
    for r in rows:
        print(f"{r['env_id']:<20} {r['levels']:>6} {r['steps_per_second']:>12,.0f} {r['compile_seconds']:>9.1f} "
              f"{r['episodes']:>8} {r['mean_return']:>11.3f} {r['success_rate']:>13.1%}")
    limit = {"max_steps_in_episode": picture_max_steps} if picture_max_steps else {}
    env, params = histojax.make("HistoJAX-Easy-v0", **limit)
    z, x, y, reached = first_episode(env, params, jax.random.fold_in(key, 2))
    picture = out / "demo_trajectory.png"
    title = f"Easy, random agent, {len(z) - 1} steps, target {'reached' if reached else 'not reached'}"
    render_trajectory(env, z, x, y, path=picture, title=title)
    gif = animate(env, z, x, y, out / "demo_trajectory.gif")
    print(f"\ntrajectory picture: {picture.resolve()}\nanimation:          {Path(gif).resolve()}")
    return {"rows": rows, "files": [picture, Path(gif)]}


def print_banner() -> None:
    print(f"histojax demo on the embedded sample slide (CMU-1-Small-Region.svs, CC0; the target is an "
          f"illustrative navigation target, not a diagnosis); JAX {jax.__version__} on {jax.devices()[0].platform}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", type=int, default=256, help="parallel environments (vmap)")
    p.add_argument("--steps", type=int, default=400, help="steps per environment (lax.scan)")
    p.add_argument("--out", default="out", help="folder for the trajectory picture")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    print_banner()
    random_agent_table(args.envs, args.steps, args.seed, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
