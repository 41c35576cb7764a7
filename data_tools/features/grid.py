"""Embed every view of a bundle's feature grid with a frozen encoder (``python -m data_tools features``).

Views are taken on the grid of :mod:`data_tools.features.store` (every ``stride`` px of every bundle
level), embedded in batches of ``batch`` by a jitted encoder (the last batch is padded, so one
compiled shape serves all), and written as ``features_KK.npy`` with the metadata updated atomically.

Resumable: the raw embeddings of each batch go to ``BUNDLE/features.partial/CCCCCC.npy`` (written
atomically) as soon as they are computed; a restarted run with the same encoder, input size and
stride skips every chunk already there, and the folder is removed once the grid is written.

Optional reduction to ``dim`` < 1280: ``projection="random"`` — a seeded Gaussian matrix
``(1280, dim) / √dim`` (Johnson–Lindenstrauss), or ``"pca"`` — the top ``dim`` principal
directions of this slide's embeddings (centred with their mean); the matrix (and the PCA mean) are
stored as ``features_projection.npy`` (``features_projection_mean.npy``).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from data_tools.bundle_files.reading import load_bundle, load_tiled_level, read_metadata
from data_tools.bundle_files.writes import remove_partial
from data_tools.cli_output import progress_bar
from data_tools.errors import BundleError
from data_tools.features.encoders import encoder_scale
from data_tools.features.store import level_grids, save_array, update_metadata

PARTIAL = "features.partial"
PROJECTIONS = ("random", "pca")


def _settings(metadata: dict, encoder, stride: int, batch: int) -> dict:
    items = "pool tiles" if metadata.is_tiled and stride == metadata.tile_size else "views"
    return {
        "encoder": encoder.name,
        "image_size": encoder.image_size,
        "stride": stride,
        "batch": batch,
        "items": items,
        "tile_size": metadata.tile_size,
        "source_sha256": metadata.source["sha256"],
        "levels": [[lv["width"], lv["height"], lv["downsample"]] for lv in metadata.levels],
    }


def _projection(raw: np.ndarray, dim: int | None, kind: str, seed: int):
    """``(matrix (E, dim) or None, mean (E,) or None)``."""
    e = raw.shape[1]
    if dim is None or (dim == e and kind == "random"):
        return None, None
    if kind == "random":
        rng = np.random.default_rng(seed)
        return (rng.standard_normal((e, dim)) / np.sqrt(dim)).astype(np.float32), None
    mean = raw.mean(axis=0, dtype=np.float64)
    centred = raw.astype(np.float64) - mean
    if dim > min(centred.shape):
        raise BundleError(None, f"PCA to {dim} dimensions needs at least {dim} views; this grid has {raw.shape[0]}")
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    components = vt[:dim].T
    components *= np.where(components[np.abs(components).argmax(axis=0), np.arange(dim)] < 0, -1.0, 1.0)
    return components.astype(np.float32), mean.astype(np.float32)


def _items(bundle: Path, metadata, grids, stride: int, verify: bool):
    """What to embed for the feature grid: ``(items per level, fetch(k, ids) -> (n, T, T, 3) uint8,
    expand(k, embeddings of level k's items) -> (gh * gw, E) grid rows)``."""
    tile = metadata.tile_size
    if metadata.is_tiled and stride == tile:  # the distinct tiles of each pool
        pools = [load_tiled_level(bundle, lv, metadata, verify, "pixels") for lv in metadata["levels"]]
        missing = [k for k, p in enumerate(pools) if not p.has_pixels]
        if missing:
            raise BundleError(
                bundle,
                f"keeps no pixels at levels {missing} (a feature-only bundle); make the "
                "slide again with its pixels to compute another feature grid",
            )
        return (
            [int(p.pool.shape[0]) for p in pools],
            lambda k, ids: np.asarray(pools[k].pool[ids]),
            lambda k, emb: emb[pools[k].index[: grids[k][0], : grids[k][1]].ravel()],
        )
    cache: dict[int, np.ndarray] = {}

    def fetch(k, ids):
        if k not in cache:
            cache.clear()  # one level in memory at a time (levels come finest first, in order)
            cache[k] = load_bundle(bundle, verify=verify, levels=[k]).pixels[0]
        gw = grids[k][1]
        return np.stack(
            [
                cache[k][(j // gw) * stride : (j // gw) * stride + tile, (j % gw) * stride : (j % gw) * stride + tile]
                for j in ids
            ]
        )

    return [gh * gw for gh, gw in grids], fetch, lambda k, emb: emb


def check_storable(grids, dtype: str, bundle, encoder) -> None:
    """Refuse (``BundleError`` naming the bundle and the encoder, one line) feature values that ``dtype`` cannot
    hold: beyond float16's ±65504 a float16 grid would store infinity in those cells (as imported ``.h5`` features
    are refused, :func:`data_tools.features.hdf5.import_features`). ``grids``: the ``(n_views, D)`` arrays of
    every level, checked before anything is written."""
    if dtype != "float16":
        return
    top = max((float(np.abs(g).max(initial=0.0)) for g in grids), default=0.0)
    if top > float(np.finfo(np.float16).max):
        who = getattr(encoder, "spec", None) or getattr(encoder, "name", "the encoder")
        raise BundleError(
            bundle,
            f"encoder {who} gives feature values up to {top:.3g}, beyond float16's ±65504 (they "
            "would be stored as infinity): scale them in the encoder, or store float32 (--dtype float32)",
        )


def compute_features(
    bundle,
    encoder_name: str = "efficientnet-lite0",
    dim: int | None = None,
    projection: str = "random",
    seed: int = 0,
    stride: int | None = None,
    batch: int = 64,
    image_size: int | None = 224,
    dtype: str = "float16",
    progress: bool = True,
    max_chunks: int | None = None,
    verify: bool = True,
    scale_remedy: str | None = None,
) -> dict | None:
    """Compute the feature grid of the bundle at ``bundle`` (see the module doc) and return the new
    ``metadata["features"]``. ``stride`` defaults to the tile size; ``image_size`` is the encoder's
    input size (views are resized to it; None feeds them at their own size). ``max_chunks`` stops
    after that many new chunks and returns None (for tests of resuming)."""
    from data_tools.features.efficientnet import load_encoder

    bundle = Path(bundle)
    metadata = read_metadata(bundle)
    tile = metadata.tile_size
    stride = int(stride or tile)
    if stride < 1 or batch < 1:
        raise BundleError(bundle, f"stride ({stride}) and batch ({batch}) must be at least 1")
    if projection not in PROJECTIONS:
        raise BundleError(bundle, f"projection must be one of {PROJECTIONS}, got {projection!r}")
    if dtype not in ("float16", "float32"):
        raise BundleError(bundle, f"dtype must be float16 or float32, got {dtype!r}")
    encoder = load_encoder(encoder_name, image_size=image_size)
    scale = encoder_scale(
        encoder.name,
        (metadata.get("source") or {}).get("mpp"),
        [lv.downsample for lv in metadata.levels],
        scale_remedy,
    )  # scale_remedy: what a command without --mpp offers instead (c16)
    if scale is not None and scale["warning"]:  # one line naming the bundle; recorded in features.encoder_scale
        from data_tools.cli_output import without_temporaries  # the bundle, not the folder it is built in

        warnings.warn(f"{without_temporaries(bundle / 'metadata.json')}: {scale['warning']}", stacklevel=2)
    if dim is not None and not 1 <= dim <= encoder.dim:
        raise BundleError(bundle, f"--dim must be between 1 and the encoder's {encoder.dim}, got {dim}")
    grids = level_grids(metadata, stride)

    partial = bundle / PARTIAL
    settings = _settings(metadata, encoder, stride, batch)
    settings_file = partial / "settings.json"
    if partial.exists():
        try:
            same = json.loads(settings_file.read_text()) == settings
        except (OSError, json.JSONDecodeError):
            same = False
        if not same:  # another encoder, stride or slide: start over (only histojax's chunks are removed)
            remove_partial(partial)
    partial.mkdir(exist_ok=True)
    settings_file.write_text(json.dumps(settings, allow_nan=False))

    # one list of items over all levels (finest first), cut into batches of ``batch``: small coarse levels
    # share batches instead of each padding its own. Items are the grid's views, or, for a tiled bundle
    # whose grid is its tile grid (stride = tile size), the distinct tiles of each level's pool: a view is
    # then one tile, so embedding the pool once (background glass is one shared tile) gives every view
    sizes, fetch, expand = _items(bundle, metadata, grids, stride, verify)
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    n_chunks = -(-int(starts[-1]) // batch)

    def chunk_file(chunk):
        return partial / f"{chunk:06d}.npy"

    done = sum(chunk_file(c).is_file() for c in range(n_chunks))
    bar = progress_bar(
        total=n_chunks, initial=done, desc=f"embedding {bundle.name}", unit="batch", disable=not progress
    )
    new = 0
    try:
        for c in range(n_chunks):
            if chunk_file(c).is_file():
                continue
            if max_chunks is not None and new >= max_chunks:
                return None
            index = np.arange(c * batch, min((c + 1) * batch, int(starts[-1])))
            level = np.searchsorted(starts, index, side="right") - 1
            views = np.zeros((batch, tile, tile, 3), np.uint8)
            for k in np.unique(level):
                views[np.flatnonzero(level == k)] = fetch(int(k), index[level == k] - starts[k])
            save_array(chunk_file(c), np.asarray(encoder.embed(views), dtype=np.float32)[: len(index)])
            new += 1
            bar.update(1)
    finally:
        bar.close()

    flat = (
        np.concatenate([np.load(chunk_file(c), allow_pickle=False) for c in range(n_chunks)])
        if n_chunks
        else np.zeros((0, encoder.dim), np.float32)
    )
    raw = [expand(k, flat[starts[k] : starts[k + 1]]) for k in range(len(grids))]
    flat = np.concatenate(raw) if raw else flat
    matrix, mean = _projection(flat, dim, projection, seed)
    if matrix is not None:
        raw = [(emb - mean if mean is not None else emb) @ matrix for emb in raw]
    check_storable(raw, dtype, bundle, encoder)
    written, levels = [], []
    for k, (grid, emb) in enumerate(zip(grids, raw)):
        name = f"features_{k:02d}.npy"
        save_array(bundle / name, emb.reshape(*grid, -1).astype(dtype))
        written.append(name)
        levels.append({"file": name, "grid": list(grid)})
    proj = None
    if matrix is not None:
        proj = {"kind": projection, "file": "features_projection.npy", "input_dim": encoder.dim}
        save_array(bundle / proj["file"], matrix)
        written.append(proj["file"])
        if projection == "random":
            proj["seed"] = seed
        else:
            proj["mean_file"] = "features_projection_mean.npy"
            save_array(bundle / proj["mean_file"], mean)
            written.append(proj["mean_file"])
    features = {
        "encoder": encoder.name,
        "encoder_dim": encoder.dim,
        "image_size": encoder.image_size,
        "dim": int(matrix.shape[1]) if matrix is not None else encoder.dim,
        "stride": stride,
        "dtype": dtype,
        "projection": proj,
        "source": "computed",
        "grid": "cell (gy, gx) of level KK = the view with top-left (gx*stride, gy*stride) px of that level",
        "levels": levels,
        **(encoder.record() if hasattr(encoder, "record") else {}),  # your own: name, version, module:function
        **({"encoder_scale": scale} if scale is not None else {}),  # a built-in encoder's scale against the slide's
    }
    update_metadata(bundle, features, written)
    remove_partial(partial)
    return features


__all__ = ["check_storable", "compute_features"]
