"""Moved to :mod:`data_tools.datasets.synth_large` (the dataset builders live together in ``data_tools/datasets/``);
this name stays as an alias of that very module."""
import importlib
import sys

sys.modules[__name__] = importlib.import_module("data_tools.datasets.synth_large")
