"""Real H&E patches from PatchCamelyon (Veeling et al. 2018, CC0 1.0): 96 × 96 px RGB at ~0.97 µm/px
(CAMELYON16 level 0 downsampled 4×); label 1 = tumour in the central 32 × 32 px, 0 = no tumour.

A :class:`PatchBank` keeps the patches JPEG-encoded in memory (as distributed) and decodes only
those a slide uses. Sources: the small bank shipped in the package (``data_tools/pcam/bank.npz``,
500 + 500 patches, the JPEG bytes as distributed), a folder laid out ``.../0/*.jpg`` and ``.../1/*.jpg``
(e.g. the unpacked ``pcam_train_patches.tar.gz``), or such a ``.tar.gz`` itself.
"""

from __future__ import annotations

import tarfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import HistojaxDataError

SHIPPED_BANK = Path(__file__).resolve().parents[1] / "pcam" / "bank.npz"
PATCH = 96  # px a side
PATCH_MPP = 0.972  # µm per px (CAMELYON16 level 0, 0.243 µm/px, downsampled 4×)
CITATION = (
    "B. S. Veeling, J. Linmans, J. Winkens, T. Cohen, M. Welling. Rotation Equivariant CNNs for Digital "
    "Pathology. MICCAI 2018 (PatchCamelyon, CC0 1.0)"
)


@dataclass(frozen=True)
class PatchBank:
    """JPEG-encoded patches: ``blob`` uint8 bytes, ``offsets`` ``(N + 1,)`` int64, ``labels`` ``(N,)`` uint8,
    ``names`` ``(N,)`` str; ``source`` says where they came from."""

    blob: np.ndarray
    offsets: np.ndarray
    labels: np.ndarray
    names: np.ndarray
    source: str

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def indices(self, label: int) -> np.ndarray:
        """Indices of the patches with ``label`` (0 no tumour, 1 tumour)."""
        return np.flatnonzero(self.labels == label)

    def decode(self, indices) -> np.ndarray:
        """RGB uint8 ``(len(indices), 96, 96, 3)`` of the chosen patches."""
        import imagecodecs

        out = np.empty((len(indices), PATCH, PATCH, 3), np.uint8)
        for j, i in enumerate(indices):
            img = imagecodecs.jpeg8_decode(self.blob[self.offsets[i] : self.offsets[i + 1]].tobytes())
            if img.shape != (PATCH, PATCH, 3):
                raise HistojaxDataError(self.source, f"patch {self.names[i]} is {img.shape}, not 96×96 RGB")
            out[j] = img
        return out

    def take(self, indices, source: str | None = None) -> "PatchBank":
        """A bank of the patches at ``indices`` (in that order), JPEG bytes shared by copy."""
        indices = np.asarray(indices, np.int64)
        items = [
            (str(self.names[i]), int(self.labels[i]), self.blob[self.offsets[i] : self.offsets[i + 1]].tobytes())
            for i in indices
        ]
        return _from_items(items, source or self.source)

    def save(self, path) -> Path:
        """Write the bank as one ``.npz`` (no pickles)."""
        path = Path(path)
        np.savez(path, blob=self.blob, offsets=self.offsets, labels=self.labels, names=self.names)
        return path


def _from_items(items: list[tuple[str, int, bytes]], source: str) -> PatchBank:
    items = sorted(items, key=lambda it: (it[1], it[0]))
    sizes = np.array([len(b) for _, _, b in items], np.int64)
    return PatchBank(
        blob=np.frombuffer(b"".join(b for _, _, b in items), np.uint8).copy(),
        offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        labels=np.array([lab for _, lab, _ in items], np.uint8),
        names=np.array([n for n, _, _ in items], dtype="U64"),
        source=source,
    )


def _label_of(parts) -> int | None:
    return int(parts[-2]) if len(parts) >= 2 and parts[-2] in ("0", "1") else None


def load_bank(source=None) -> PatchBank:
    """A :class:`PatchBank` from ``source``: ``None`` (the shipped bank), a ``.npz`` bank, a folder with
    ``0/`` and ``1/`` sub-folders of JPEGs, or a ``.tar.gz`` of such a folder. Raises
    ``HistojaxDataError`` naming the source when it holds no patches of one of the two classes."""
    path = Path(source) if source is not None else SHIPPED_BANK
    items: list[tuple[str, int, bytes]] = []
    if path.is_file() and path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                bank = PatchBank(
                    blob=z["blob"], offsets=z["offsets"], labels=z["labels"], names=z["names"], source=str(path)
                )
        except (OSError, ValueError, KeyError) as e:
            raise HistojaxDataError(path, f"not a patch bank .npz ({e})") from None
    elif path.is_dir():
        for f in sorted(path.rglob("*.jp*g")):
            label = _label_of(f.parts)
            if label is not None:
                items.append((f.name, label, f.read_bytes()))
        bank = _from_items(items, str(path))
    elif path.is_file():
        try:
            with tarfile.open(path, "r:*") as tar:
                for m in tar:
                    label = _label_of(Path(m.name).parts)
                    if m.isfile() and m.name.lower().endswith((".jpg", ".jpeg")) and label is not None:
                        items.append((Path(m.name).name, label, tar.extractfile(m).read()))
        except (tarfile.TarError, OSError, EOFError) as e:
            raise HistojaxDataError(path, f"not a readable tar archive of PCam patches ({e})") from None
        bank = _from_items(items, str(path))
    else:
        raise HistojaxDataError(path, "no such patch folder, archive or bank")
    for label in (0, 1):
        if not (bank.labels == label).any():
            raise HistojaxDataError(path, f"holds no patches labelled {label} (expected .../0/*.jpg and .../1/*.jpg)")
    return bank


def subsample(bank: PatchBank, per_class: int, seed: int = 0) -> PatchBank:
    """A bank of ``per_class`` patches of each label drawn without replacement (for shipping a small bank)."""
    rng = np.random.default_rng(seed)
    keep = np.sort(
        np.concatenate(
            [rng.choice(bank.indices(lab), min(per_class, len(bank.indices(lab))), replace=False) for lab in (0, 1)]
        )
    )
    items = [
        (str(bank.names[i]), int(bank.labels[i]), bank.blob[bank.offsets[i] : bank.offsets[i + 1]].tobytes())
        for i in keep
    ]
    return _from_items(items, f"{bank.source} (subsample of {per_class} per class, seed {seed})")


POOL_SEED = 0  # the seed of the train/test patch-pool rule (recorded in dataset.json)
POOL_TEST_FRACTION = 0.5  # share of the patches of each class in the test pool


def in_test_pool(names, labels, seed: int = POOL_SEED, test_fraction: float = POOL_TEST_FRACTION) -> np.ndarray:
    """``bool (N,)``: which patches belong to the **test pool** (the rest form the training pool).

    The rule, recorded in ``dataset.json``: a patch is in the test pool when the first 8 bytes of
    ``sha256(f"{seed}:{label}/{name}")``, read as a big-endian integer over 2**64, are below
    ``test_fraction``. It depends only on the patch's own label and file name, so a patch is on the
    same side in any bank, subset or order; a given patch never textures slides of both splits."""
    import hashlib

    out = np.empty(len(names), bool)
    for i, (n, lab) in enumerate(zip(names, labels)):
        h = hashlib.sha256(f"{int(seed)}:{int(lab)}/{n}".encode()).digest()
        out[i] = int.from_bytes(h[:8], "big") / 2.0**64 < test_fraction
    return out


def pool_rule(seed: int = POOL_SEED, test_fraction: float = POOL_TEST_FRACTION) -> dict:
    """The pool rule of :func:`in_test_pool` as recorded in ``dataset.json``."""
    return {
        "rule": "test pool iff int(sha256(f'{seed}:{label}/{name}')[:8]) / 2**64 < test_fraction",
        "seed": int(seed),
        "test_fraction": float(test_fraction),
    }


def split_pools(
    bank: PatchBank, seed: int = POOL_SEED, test_fraction: float = POOL_TEST_FRACTION
) -> tuple[PatchBank, PatchBank]:
    """``(training pool, test pool)`` of ``bank`` by :func:`in_test_pool`; ``HistojaxDataError`` naming the
    bank when a pool would lack one of the two classes."""
    test = in_test_pool(bank.names, bank.labels, seed, test_fraction)
    pools = (
        bank.take(np.flatnonzero(~test), f"{bank.source} [training pool]"),
        bank.take(np.flatnonzero(test), f"{bank.source} [test pool]"),
    )
    for pool in pools:
        for label in (0, 1):
            if not (pool.labels == label).any():
                raise HistojaxDataError(
                    bank.source, f"too few patches: the {pool.source.rsplit('[', 1)[-1][:-1]} has none labelled {label}"
                )
    return pools


__all__ = [
    "CITATION",
    "POOL_SEED",
    "POOL_TEST_FRACTION",
    "in_test_pool",
    "pool_rule",
    "split_pools",
    "PATCH",
    "PATCH_MPP",
    "PatchBank",
    "SHIPPED_BANK",
    "load_bank",
    "subsample",
]
