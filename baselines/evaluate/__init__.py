"""Evaluate a trained checkpoint against reference policies: ``python -m baselines.evaluate`` / ``histojax evaluate``
(the command and its help: :mod:`baselines.evaluate.cli`).

Modules (import each name from its own module; this package re-exports nothing): ``heads``, ``pictures``,
``checks``, ``scoring``, ``cli`` (the command: ``add_arguments``, ``run``, ``main``). The policies it scores and
their episodes are :mod:`baselines.episodes` (``policies``, ``rollout``), a floor it shares with
:mod:`baselines.reading`."""
