"""The tiny PPO config the trainer tests share: the sample slide's Easy env, 4 envs × 8 steps, one update of 2
minibatches, 16 units (seconds to compile and run on a CPU)."""

TINY = dict(
    env_id="HistoJAX-Easy-v0",
    with_position=True,
    num_envs=4,
    num_steps=8,
    total_timesteps=64,
    update_epochs=1,
    num_minibatches=2,
    hidden=16,
    num_seeds=1,
    print_progress=False,
)
