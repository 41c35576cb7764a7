"""The two inputs the published C16 tables were built from, and a check of a user's inputs against them.

``python -m data_tools c16 --annotations A --patches P`` builds the true-scale CAMELYON16 set from NCRF's
polygons and 20,000 PCam patches. The published tables (docs/c16-benchmark.md, docs/results/c16.md) were
built from the two ``.tar.gz`` files below, byte for byte; :func:`check_known_inputs` hashes the ``.tar.gz``
files a run is given and says, in one line each, which of them differs. Other inputs are allowed (other
patches, other polygons): the line only warns that the published figures came from other bytes.
A leaf module: it imports only the standard library.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

# the inputs of the published tables; docs/c16-benchmark.md ("Where the inputs come from") shows the same
KNOWN_INPUTS: dict[str, dict[str, str]] = {
    "annotations": {
        "file": "camelyon16_ncrf_train.tar.gz",
        "sha256": "3edffc64008597e3d2bed0651e5cd12f3948d1eca6972900487875df2e4b1e33",
        "source": "baidu-research/NCRF, jsons/train/*.json (revision 6c707d7ef23ebb19c7e8b2f49b2cf6b70d27072e), "
        "packed as train/*.json",
    },
    "patches": {
        "file": "pcam_train_patches.tar.gz",
        "sha256": "cacbd5842fdcf88e2ffa0196f741f0a10918c3e236812605b05d9ef957f41e4e",
        "source": "PatchCamelyon (CC0) as redistributed in vflorenc/AI4ALL-PCam, data/train/{0,1}/*.jpg "
        "(revision ac2baa8be379e6057bd456a59993723946e61701), packed as train/{0,1}/*.jpg",
    },
}


def _file_sha256(path: Path) -> str:
    """Hex SHA-256 of one file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def check_known_inputs(**inputs) -> dict[str, dict]:
    """Compare each given ``.tar.gz`` input (``annotations=PATH``, ``patches=PATH``) with :data:`KNOWN_INPUTS`.

    Only existing files whose name ends in ``.tar.gz`` are hashed (folders, ``.npz`` banks, the shipped
    defaults and missing paths are left to the loaders, which name their own problems). Returns, per input
    checked, ``{"file": str, "sha256": hex, "matches_published": bool}`` — what ``dataset.json`` records
    under ``inputs``; an empty dict when nothing was checked.
    """
    record = {}
    for kind, path in inputs.items():
        if path is None or kind not in KNOWN_INPUTS:
            continue
        path = Path(path)
        if not (path.name.endswith(".tar.gz") and path.is_file()):
            continue
        digest = _file_sha256(path)
        record[kind] = {
            "file": str(path),
            "sha256": digest,
            "matches_published": digest == KNOWN_INPUTS[kind]["sha256"],
        }
    return record


def differing_lines(record: dict[str, dict]) -> list[str]:
    """One warning line per input of ``record`` (from :func:`check_known_inputs`) that differs from the
    published tables' input: the file, its sha256 and the expected one."""
    return [
        f"c16: {kind} {r['file']} has sha256 {r['sha256'][:16]}…, not the {KNOWN_INPUTS[kind]['file']} "
        f"of the published tables ({KNOWN_INPUTS[kind]['sha256'][:16]}…): the published tables were built "
        f"from other inputs (see docs/c16-benchmark.md)"
        for kind, r in record.items()
        if not r["matches_published"]
    ]
