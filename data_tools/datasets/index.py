"""The one reader of a dataset's index, ``dataset.json`` (:func:`read_dataset_json`): the file checked against its
seal (:mod:`data_tools.bundle_files.seals`) and its size, kind and patients record checked, for ``make``, the head
fits, the readers and ``histojax evaluate --dataset``. The writer is :mod:`data_tools.datasets.build`."""

from __future__ import annotations

import json
import os
import stat
import warnings
from pathlib import Path

from data_tools.bundle_files.safe_files import not_regular
from data_tools.bundle_files.seals import DATASET_DIGEST, MAX_DATASET_JSON_BYTES, SEALING_KINDS, metadata_digest
from data_tools.datasets.split import patient_key
from data_tools.errors import BundleError

__all__ = ["read_dataset_json"]

_UNSEALED_WARNED: set[str] = set()


def read_dataset_json(folder, _depth: int = 0) -> dict:
    """:func:`_read_dataset_json` (its doc), then its ``patients`` record checked: an object naming each slide's
    patient by a non-empty string (a BundleError naming the file otherwise, not a grouping by ``str(None)`` or
    ``"[1]"``, nor every slide of an empty id made one patient)."""
    spec = _read_dataset_json(folder, _depth)
    patients = spec.get("patients")
    if patients is not None:
        path = Path(folder) / "dataset.json"
        if not isinstance(patients, dict):
            raise BundleError(
                path, f"its patients record is a JSON {type(patients).__name__}, not an object of slide name to patient"
            )
        for name, patient in patients.items():
            if not isinstance(patient, str) or not patient_key(patient):
                shown = json.dumps(patient)  # json-not-written (a message)
                raise BundleError(
                    path,
                    f"its patients record gives slide {name[:80]!r} the patient "
                    f"{shown if len(shown) <= 80 else shown[:77] + '...'}, not a patient id (a non-empty string); "
                    "rebuild the dataset",
                )
    return spec


def _read_dataset_json(folder, _depth: int = 0) -> dict:
    """``FOLDER/dataset.json`` read with its seal checked: the one reader of a dataset's index for ``make``, the head
    fits and ``histojax evaluate --dataset``. A file that carries a seal (:data:`~data_tools.bundle_files.seals.DATASET_DIGEST`) must match it: an
    edit since histojax wrote it (a label, a split) is a ``BundleError`` naming the file. A split derived from a
    sealed dataset (``baselines.validation``: a ``validation.source`` record; the readers' ``derived_from``)
    carries its source's seal: the source's seal is checked and the labels must be the source's. Files without a
    seal (``data_tools synth``, older builds) are read as they are; one of a kind ``histojax dataset`` or ``c16``
    writes (:data:`~data_tools.bundle_files.seals.SEALING_KINDS`) with a warning, once per file, that its labels are unchecked. ``FileNotFoundError``, ``OSError`` and
    ``json.JSONDecodeError`` pass as ``json.loads(path.read_text())`` raises them; a ``BundleError`` naming the
    file when it is not a regular file (a FIFO would block the read for ever; a folder, a device), larger than
    :data:`~data_tools.bundle_files.seals.MAX_DATASET_JSON_BYTES`, or not a JSON object. Returns the object."""
    path = Path(folder) / "dataset.json"
    st = os.stat(path)  # a link to a regular file is read (the user's choice); FileNotFoundError as before
    if not stat.S_ISREG(st.st_mode):
        raise BundleError(
            path,
            f"is {not_regular(st)}, not a dataset index file; refusing to read it (rebuild the "
            "dataset, or give the folder histojax wrote)",
        )
    if st.st_size > MAX_DATASET_JSON_BYTES:
        raise BundleError(
            path,
            f"is {st.st_size / 2**20:.0f} MiB, more than a dataset index holds "
            f"({MAX_DATASET_JSON_BYTES // 2**20} MiB); not a histojax dataset.json",
        )
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))  # swapped for a FIFO since: never blocks
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise BundleError(path, "changed while it was opened (not a regular file now); refusing to read it")
        data = f.read(MAX_DATASET_JSON_BYTES + 1)
    if len(data) > MAX_DATASET_JSON_BYTES:
        raise BundleError(path, f"grew past {MAX_DATASET_JSON_BYTES // 2**20} MiB while it was read; refusing it")
    try:
        spec = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as e:  # a ValueError the callers' JSONDecodeError misses
        raise BundleError(
            path, f"is not UTF-8 text (byte {data[e.start]:#04x} at offset {e.start}); not a dataset.json"
        ) from None
    except RecursionError:  # arrays or objects nested deeper than the parser recurses
        raise BundleError(path, "nests its JSON deeper than Python's parser reads; not a dataset index") from None
    if not isinstance(spec, dict):
        raise BundleError(
            path,
            f"holds a JSON {type(spec).__name__}, not a dataset index (an object with the "
            "train and test splits histojax writes); rebuild the dataset",
        )
    if DATASET_DIGEST not in spec:
        if spec.get("kind") in SEALING_KINDS and str(path.resolve()) not in _UNSEALED_WARNED:
            _UNSEALED_WARNED.add(str(path.resolve()))
            warnings.warn(
                f"{path}: carries no seal ({DATASET_DIGEST}): written before histojax sealed its dataset "
                "indexes, or the seal was removed; its labels and splits are read unchecked. Rebuild it "
                "with the command that made it to seal it",
                stacklevel=2,
            )
        return spec
    validation = spec.get("validation")
    source = spec.get("derived_from") or (validation.get("source") if isinstance(validation, dict) else None)
    if isinstance(source, str) and _depth < 4:
        try:
            base = read_dataset_json(source, _depth + 1)
        except FileNotFoundError:
            return spec  # the source moved away: its bundles' own checks report it
        if isinstance(base, dict) and isinstance(base.get("labels"), dict) and isinstance(spec.get("labels"), dict):
            theirs = {Path(str(k)).name: v for k, v in base["labels"].items()}
            changed = [k for k, v in spec["labels"].items() if theirs.get(Path(str(k)).name, v) != v]
            if changed:
                raise BundleError(
                    path,
                    f"labels differ from those of the sealed dataset it was split from ({source}; "
                    f"e.g. {changed[0]!r}): edited since; split it again from {source}",
                )
        return spec
    if spec[DATASET_DIGEST] != metadata_digest({k: v for k, v in spec.items() if k != DATASET_DIGEST}):
        raise BundleError(
            path,
            f"does not match its seal ({DATASET_DIGEST}): edited after histojax wrote it (a label, "
            "a split or a slide record); restore it or rebuild it with the command that made it "
            "(`histojax dataset SLIDES --out DIR`, `python -m data_tools c16 ... --out DIR`)",
        )
    return spec
