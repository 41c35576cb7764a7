"""A synthetic labelled set of many slides, and an untrained learned attention-MIL head for it, for the reader
speed benchmarks: how a reader's training cost grows with the number of training slides
(:mod:`benchmarks.learned_reader_speed` at two slide counts)::

    python -m benchmarks.synthetic_reading_set --out DIR --slides 200 [--size 1280] [--dim 64]

One template slide (pink tissue on glass, 32-px views, 3 levels: downsamples 16, 4, 1) is built once into a bundle
and copied once per slide; each copy gets its own feature grid (``dim``-d, imported as a TRIDENT-style ``.h5``):
standard normal noise with a raised entry on a rectangle of "tumour" views on half the slides. At ``--size 1280``
a slide has 40 × 40 finest views and 10 × 10 cells at level 1 (``glimpse:1``), about the C16 set's mean of valid
cells a slide (105). Writes ``DIR/dataset.json`` (``train``: ``slides`` slides, ``test``: 2, ``labels``),
``DIR/bundles/``, and ``DIR/head`` (a learned head of the published one's size, 32 units, 16 attention units,
random parameters: its reward costs what a fitted head's does). Only numbers made here; no third-party data.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

TILE = 32


def _template(root: Path, size: int) -> Path:
    import tifffile

    from data_tools.bundle import build_bundle

    image = np.full((size, size, 3), 245, np.uint8)
    image[TILE : size - TILE, TILE : size - TILE] = [230, 160, 200]  # tissue, a one-view margin of glass
    tifffile.imwrite(root / "template.tif", image, photometric="rgb")
    return build_bundle(root / "template.tif", root / "template", level_sets=(3,), tile_size=TILE, progress=False)


def build(out, slides: int, size: int = 1280, dim: int = 64, seed: int = 0) -> Path:
    """Build ``slides`` training slides (and 2 test slides) of ``size`` × ``size`` px under ``out`` with ``dim``-d
    features, and the head ``out/head``; returns ``out``. Refuses an ``out`` that already holds a dataset.json."""
    import h5py
    import jax

    from data_tools.features.hdf5 import import_features
    from histojax.reading.heads.learned import LearnedHead, init_params

    out = Path(out)
    if (out / "dataset.json").exists():
        raise FileExistsError(f"{out}: already holds a dataset.json")
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    g = size // TILE
    ys, xs = np.meshgrid(np.arange(g), np.arange(g), indexing="ij")
    coords = np.stack([xs.ravel() * TILE, ys.ravel() * TILE], 1)
    spec = {"kind": "synthetic reader-speed set", "train": [], "test": [], "labels": {}}
    with tempfile.TemporaryDirectory(dir=out) as tmp:
        template = _template(Path(tmp), size)
        for i in range(slides + 2):
            split, label = ("train" if i < slides else "test"), i % 2
            name = f"s{i:04d}_{'tumour' if label else 'normal'}"
            bundle = out / "bundles" / name
            shutil.copytree(template, bundle)
            z = rng.normal(size=(g * g, dim)).astype(np.float32)
            if label:
                h, w = rng.integers(2, 6, 2)
                y0, x0 = rng.integers(1, g - 1 - h), rng.integers(1, g - 1 - w)
                m = np.zeros((g, g), bool)
                m[y0 : y0 + h, x0 : x0 + w] = True
                z[:, 0] += 3.0 * m.ravel()
            h5 = Path(tmp) / f"{name}.h5"
            with h5py.File(h5, "w") as f:
                f.create_dataset("features", data=z)
                c = f.create_dataset("coords", data=coords)
                c.attrs["patch_size"] = TILE
                c.attrs["patch_level"] = 0
            import_features(bundle, h5, dtype="float32")
            h5.unlink()
            spec[split].append(f"bundles/{name}")
            spec["labels"][name] = label
    head = LearnedHead(
        params=init_params(jax.random.PRNGKey(seed), dim, 32, 16, 1),
        features_dim=dim,
        hidden=32,
        attention=16,
        encoder="imported:s0000_normal.h5",
    )
    head.save(out / "head")
    (out / "dataset.json").write_text(json.dumps(spec, indent=1) + "\n")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.synthetic_reading_set",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--slides", type=int, default=200, help="training slides (default 200)")
    p.add_argument("--size", type=int, default=1280, help="slide side in px, a multiple of 128 (default 1280)")
    p.add_argument("--dim", type=int, default=64, help="feature entries (default 64)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.slides < 1 or args.size < 256 or args.size % 128:
        print(f"error: {args.out}: --slides must be >= 1 and --size a multiple of 128, >= 256", file=sys.stderr)
        return 2
    try:
        build(args.out, args.slides, args.size, args.dim, args.seed)
    except FileExistsError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: {args.slides} training slides, head {args.out / 'head'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
