"""Your own encoder: ``--encoder module:function`` (``data_tools features``, ``c16``, ``histojax dataset``)
embeds every view with any Python callable ``images uint8 (N, H, W, 3) → float32 (N, D)``.

The callable is imported like an entry point (``package.module:function``; the module is found on
``sys.path`` or in the working folder, with ``histojax dataset`` as with ``python -m data_tools``). What is
recorded in each bundle's ``metadata.json`` and in ``dataset.json``:

* ``encoder``: the callable's ``name`` attribute (a string, e.g. ``"uni-v1"``), else the spec
  ``module:function`` itself; it may not be one of the built-in names (``pcam-cnn``, ...).
* ``encoder_version``: its ``version`` attribute (a string; weights' date or hash), else ``null``.
* ``encoder_spec``: the ``module:function`` it was loaded from.

Views are given at the bundle's tile size (128 px for the C16 benchmark), as ``numpy.uint8``; return a
NumPy, JAX (or CPU PyTorch) array. Every call's result is checked: 2-D, one row per image, the same ``D`` on
every call, ``float32`` and finite. An encoder that breaks a rule is refused with one line naming it.
"""

from __future__ import annotations

import functools
import importlib
import os
import sys

import numpy as np

from data_tools.errors import HistojaxDataError
from data_tools.features.encoders import ENCODERS

PROBE_SIZE = 128  # views of the probe call (load_custom_encoder): the C16 and default tile size


def is_custom(spec) -> bool:
    """True for a ``module:function`` encoder spec (not a built-in name)."""
    return isinstance(spec, str) and ":" in spec


def _import_module(module_name: str):
    """``importlib.import_module``, looking in the working folder too (as ``python -m`` does; the ``histojax``
    script's path holds only its own folder): the working folder is put on ``sys.path`` when the module is
    not found elsewhere, so worker processes started later find it as well; last, so that a folder there named
    like one of histojax's own packages is never imported in their place."""
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        cwd = os.getcwd()
        if e.name != module_name.split(".")[0] or cwd in sys.path or "" in sys.path:
            raise
        sys.path.append(cwd)
        return importlib.import_module(module_name)


def _import(spec: str):
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr:
        raise HistojaxDataError(None, f"--encoder {spec!r}: give module:function (e.g. my_encoders:uni)")
    try:
        module = _import_module(module_name)
    except ImportError as e:
        raise HistojaxDataError(
            None,
            f"--encoder {spec}: cannot import {module_name!r} ({e}) from the working "
            f"folder {os.getcwd()} nor the Python path: run from the folder holding "
            f"{module_name.split('.')[0]}.py (or its package), or pip install it",
        ) from e
    except KeyboardInterrupt:
        raise
    except BaseException as e:  # noqa: BLE001 (the user's module: SystemExit(0) at import must not end us with 0)
        raise HistojaxDataError(
            None, f"--encoder {spec}: importing {module_name!r} raised {type(e).__name__}: {e}"
        ) from e
    fn = module
    for part in attr.split("."):
        fn = getattr(fn, part, None)
        if fn is None:
            raise HistojaxDataError(None, f"--encoder {spec}: module {module_name!r} has no {attr!r}")
    if not callable(fn):
        raise HistojaxDataError(None, f"--encoder {spec}: {attr!r} is not callable")
    return fn


class CustomEncoder:
    """A user's callable as an encoder (the interface of :class:`data_tools.features.efficientnet.Encoder`):
    ``embed(uint8 (N, H, W, 3)) → float32 (N, D)``, checked on every call; views fed at their own size."""

    image_size = None  # views are fed at their own size
    variables = None

    def __init__(self, spec: str, fn):
        self.spec, self.fn = spec, fn
        name = getattr(fn, "name", None)
        version = getattr(fn, "version", None)
        if name is not None and (not isinstance(name, str) or not name.strip()):
            raise HistojaxDataError(
                None, f"--encoder {spec}: its name attribute must be a non-empty string, got {name!r}"
            )
        if version is not None and not isinstance(version, (str, int)):
            raise HistojaxDataError(None, f"--encoder {spec}: its version attribute must be a string, got {version!r}")
        self.name = name or spec
        self.version = None if version is None else str(version)
        if self.name in ENCODERS:
            raise HistojaxDataError(
                None,
                f"--encoder {spec}: named {self.name!r}, a built-in encoder's name; "
                "give it a name of its own (fn.name)",
            )
        self.dim = None  # set by the first call (the probe of load_custom_encoder)

    def __repr__(self):
        return f"encoder {self.spec} ({self.name}{', version ' + self.version if self.version else ''})"

    def embed(self, images) -> np.ndarray:
        """``uint8 (N, H, W, 3)`` → ``float32 (N, D)``; a wrong shape, dtype or a non-finite value raises
        HistojaxDataError naming the encoder, and so does any exception of the callable (``SystemExit`` included;
        only ``KeyboardInterrupt`` passes)."""
        images = np.asarray(images, np.uint8)
        try:
            out = self.fn(images)
        except (HistojaxDataError, KeyboardInterrupt):
            raise
        except BaseException as e:  # noqa: BLE001 (the user's code: any error, named; a SystemExit(0) too, which
            # would otherwise end `features` / `c16` with status 0 having written nothing)
            raise HistojaxDataError(
                None,
                f"{self!r} failed on {images.shape[0]} views of "
                f"{images.shape[1]}x{images.shape[2]} px: {type(e).__name__}: {e}",
            ) from e
        try:
            arr = np.asarray(out)
        except Exception as e:  # noqa: BLE001
            raise HistojaxDataError(None, f"{self!r} returned a {type(out).__name__}, not an array") from e
        n = images.shape[0]
        if arr.ndim != 2 or arr.shape[0] != n or arr.shape[1] < 1:
            raise HistojaxDataError(
                None, f"{self!r} returned shape {arr.shape} for {n} views; it must return (N, D) = ({n}, D) with D >= 1"
            )
        if self.dim is not None and arr.shape[1] != self.dim:
            raise HistojaxDataError(
                None,
                f"{self!r} returned D = {arr.shape[1]} after D = {self.dim} before; every call must return the same D",
            )
        if arr.dtype != np.float32:
            raise HistojaxDataError(None, f"{self!r} returned dtype {arr.dtype}; it must return float32")
        if not np.isfinite(arr).all():
            bad = int((~np.isfinite(arr)).any(axis=1).sum())
            raise HistojaxDataError(None, f"{self!r} returned NaN or infinite values for {bad} of {n} views")
        self.dim = int(arr.shape[1])
        return arr

    def logits(self, images):
        raise HistojaxDataError(None, f"{self!r} has no ImageNet classes (--check needs efficientnet-lite0)")

    def record(self) -> dict:
        """What ``metadata.json`` / ``dataset.json`` record about it."""
        return {"encoder": self.name, "encoder_version": self.version, "encoder_spec": self.spec}


@functools.lru_cache(maxsize=8)
def load_custom_encoder(spec: str, probe_size: int = PROBE_SIZE) -> CustomEncoder:
    """The encoder ``spec`` (``module:function``), imported and probed once on two views (white glass and
    a pink-purple view of ``probe_size`` px) so that its ``dim`` is known and a broken one is refused before
    any slide is read. Cached per spec."""
    encoder = CustomEncoder(spec, _import(spec))
    probe = np.empty((2, probe_size, probe_size, 3), np.uint8)
    probe[0] = 245
    probe[1] = (200, 120, 190)
    encoder.embed(probe)
    return encoder
