"""Experiment drivers: commands that train, evaluate or score agents, heads and encoders to produce the figures
of the results pages (the C16 reference table, held-out targets, the diagnosis ceilings, the encoders' patch
AUC, what the integration snippets learn, the cost of hostile annotation files), each ``python -m
experiments.<name>``. They import ``baselines``, ``histojax`` and ``data_tools``; nothing imports them.
Speed and memory measurements are in ``benchmarks``."""
