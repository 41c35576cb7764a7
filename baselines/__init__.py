"""Baselines for histojax: PPO and DQN trainers (pure JAX, one jitted program per run), small
networks, and an evaluation script with random and scripted reference policies. See docs/baselines.md."""
