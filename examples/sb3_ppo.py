"""Train Stable-Baselines3 PPO on histojax: the batched env as an SB3 ``VecEnv`` (one jitted
``vmap`` steps all sub-environments), then one deterministic episode through the Gymnasium bridge.

Optional extra (needs torch): ``pip install -e '.[sb3]'``, then

    python examples/sb3_ppo.py --steps 20000 --num-envs 8

The pure-JAX baselines are much faster; this shows that SB3 code runs unchanged.
"""

from __future__ import annotations

import argparse

import gymnasium
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecMonitor

import histojax.adapters.gymnasium  # noqa: F401  (registers "histojax/<id>" with Gymnasium)
from histojax.adapters.sb3 import make_sb3_vec_env


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="HistoJAX-Easy-v0")
    p.add_argument("--steps", type=int, default=20_000)
    p.add_argument("--num-envs", type=int, default=8)
    args = p.parse_args()
    venv = VecMonitor(make_sb3_vec_env(args.env, args.num_envs, obs_mode="pixels"))
    model = PPO("CnnPolicy", venv, n_steps=max(256 // args.num_envs, 8), batch_size=64, verbose=1)
    model.learn(total_timesteps=args.steps)
    env = gymnasium.make(f"histojax/{args.env}", obs_mode="pixels")
    obs, _ = env.reset(seed=0)
    done, total = False, 0.0
    while not done:
        action, _ = model.predict(obs, deterministic=True)
        obs, reward, terminated, truncated, _ = env.step(int(action))
        total += reward
        done = terminated or truncated
    print(f"one deterministic episode after training: return {total:.2f}")


if __name__ == "__main__":
    main()
