"""The older import path of HistoGym's API, kept for users: this name *is*
:mod:`histojax.adapters.histogym` (it puts that module in ``sys.modules`` under its own name), so
every name importable from there, private or not, and every attribute patched, is the same object.
Where each audience's adapter lives: :mod:`histojax.adapters`."""
import sys

from histojax.adapters import histogym as _module

sys.modules[__name__] = _module
