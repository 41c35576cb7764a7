"""What the trainers' jitted side shares: the typed trainer config (``config``: ``EnvConfig``, ``ConfigError``), the
env made from a config with episode statistics and the random-agent reference (``env``), and the devices a run's
env batch is sharded over (``devices``: ``--devices N``, memory checks).

Import each name from its module; this package re-exports nothing. The run machinery (command line, run folders,
checkpoints, logs, curves, several hosts) is :mod:`baselines.harness`."""
