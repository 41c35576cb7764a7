"""The run machinery around a trainer's jitted mathematics (:mod:`baselines.ppo`, :mod:`baselines.ppo_rnn`,
:mod:`baselines.dqn`): what a training run is on the host, apart from what it computes.

Modules (import each name from its module; this package re-exports nothing):

- ``cli``: the trainers' shared command line (options, ``--set``, ``--resume``) and their entry point.
- ``run_folder``: which folder a run may write, and one writer per folder (the run lock).
- ``trainer``: ``Trainer``, what a trainer's ``make_train`` returns (one seed's pieces, the env, the config).
- ``runner``: the one loop over updates (``scan_updates``), seeds vmapped or sharded (``run_seeds``,
  ``compile_seeds``), updates in chunks with a runner checkpoint after each, resume, the outputs.
- ``logs``: progress lines, parameter checkpoints (flax msgpack), ``log.csv`` / ``log.json``, TensorBoard scalars.
- ``curves``: the learning-curve PNG (``curve.png``).
- ``distributed``: several processes (hosts) training one program (``jax.distributed`` from the command line).

The env a run makes, its typed config and its devices are :mod:`baselines.common` (``config``, ``env``,
``devices``)."""
