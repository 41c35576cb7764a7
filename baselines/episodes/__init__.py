"""A policy's episodes on an env, shared by ``baselines.evaluate`` and ``baselines.reading``: the policies
(``policies``: the reference policies and a checkpoint's learned policy) and running them without auto-reset
(``rollout``: ``run_episodes``, per-episode slides and budgets, the summary, the evaluation env).

A floor under both: it imports neither, so that ``evaluate`` may import ``reading`` and ``reading`` the episodes
without a circle. Import each name from its module; this package re-exports nothing."""
