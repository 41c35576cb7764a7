"""The seals of ``metadata.json`` and ``dataset.json``: the SHA-256 of the rest of the file, written with it
(:func:`write_metadata`) and checked on every verified read (:func:`verify_metadata`;
:func:`data_tools.datasets.index.read_dataset_json`, the one reader of a dataset's index), so an edit of any field
after histojax wrote it is refused in one line naming the file.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from data_tools.bundle_files.format import METADATA
from data_tools.bundle_files.writes import write_json
from data_tools.errors import BundleError

__all__ = [
    "DATASET_DIGEST",
    "MAX_DATASET_JSON_BYTES",
    "METADATA_DIGEST",
    "SEALING_KINDS",
    "metadata_digest",
    "verify_metadata",
    "write_metadata",
]


METADATA_DIGEST = "metadata_sha256"  # the SHA-256 of the rest of metadata.json (see metadata_digest)


def metadata_digest(metadata: dict) -> str:
    """Hex SHA-256 of ``metadata`` without its :data:`METADATA_DIGEST` entry, serialised canonically
    (sorted keys, no spaces; floats as Python writes them, which JSON reads back exactly)."""
    body = {k: v for k, v in metadata.items() if k != METADATA_DIGEST}
    return hashlib.sha256(
        json.dumps(  # json-not-written (a digest)
            body,
            sort_keys=True,
            separators=(",", ":"),
            allow_nan=True,
        ).encode()
    ).hexdigest()


DATASET_DIGEST = "dataset_sha256"
"""Key of ``dataset.json``'s seal (``histojax dataset``, ``c16``): the SHA-256 of the rest (as :func:`metadata_digest`)."""


MAX_DATASET_JSON_BYTES = 256 << 20  # bytes: far above any cohort's index (a few hundred bytes per slide); read, it
# takes about 4.4× its size (a 200 MB file peaked at 885 MB RSS)


SEALING_KINDS = (
    "histojax dataset of real slides (data_tools dataset)",
    "histojax true-scale CAMELYON16 benchmark (data_tools c16)",
)
"""``kind`` of the ``dataset.json`` files ``histojax dataset`` and ``c16`` write, sealed since 2026-11; one of them
without a seal is an older build or a seal removed by hand (a warning says so once per file)."""


def write_metadata(folder, metadata: dict) -> None:
    """Write ``metadata.json`` of the bundle at ``folder`` atomically, sealed with its own digest
    (:data:`METADATA_DIGEST`), so an edit of any field is caught on a verified load."""
    metadata = {k: v for k, v in metadata.items() if k != METADATA_DIGEST}
    write_json(Path(folder) / METADATA, {**metadata, METADATA_DIGEST: metadata_digest(metadata)})


def verify_metadata(path, metadata: dict) -> None:
    """Check the digest of the bundle at ``path``'s metadata (``BundleError`` on a mismatch). Bundles
    written before metadata was sealed have no digest: a warning says so (their fields are still
    cross-checked against the arrays on load)."""
    recorded = metadata.get(METADATA_DIGEST)
    if recorded is None:
        import warnings

        warnings.warn(
            f"{path}: metadata.json is not sealed (bundle built before histojax sealed metadata); "
            "only its cross-checks against the arrays are verified, rebuild the bundle to verify "
            "every field",
            stacklevel=3,
        )
    elif recorded != metadata_digest(metadata):
        raise BundleError(
            Path(path) / METADATA,
            f"metadata digest mismatch ({METADATA_DIGEST}): metadata.json "
            "was edited after the build; rebuild the bundle",
        )
