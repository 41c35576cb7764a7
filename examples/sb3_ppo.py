"""Train Stable-Baselines3 PPO on histojax through the Gymnasium bridge.

Optional extra (needs torch): ``pip install -e '.[sb3]'`` (on these machines,
``pip install torch==2.13.0`` first takes the CPU build from disk), then

    python examples/sb3_ppo.py --steps 20000

The pure-JAX baselines are much faster; this shows that SB3 / Tianshou code runs unchanged.
"""
from __future__ import annotations

import argparse

import gymnasium
from stable_baselines3 import PPO

import histojax.gymnasium_bridge  # noqa: F401  (registers "histojax/<id>" with Gymnasium)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="HistoJAX-Easy-v0")
    p.add_argument("--steps", type=int, default=20_000)
    args = p.parse_args()
    env = gymnasium.make(f"histojax/{args.env}", obs_mode="pixels")
    model = PPO("CnnPolicy", env, n_steps=256, batch_size=64, verbose=1)
    model.learn(total_timesteps=args.steps)
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
