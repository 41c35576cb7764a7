"""Device bytes of a ``data_tools c16`` dataset in pixel mode and in feature mode (the feature-only
layout: tumour tables + feature grids, no pixels), computed from the bundles' metadata (nothing is
loaded). Feature grids not yet computed are counted at ``--dim`` (default 1280, EfficientNet-Lite0)
``float16`` with stride = view size, as ``python -m data_tools features`` writes them.
``--extrapolate N`` also scales the per-slide mean to ``N`` slides (e.g. 239 for the full set when
only a subset was built).

    python benchmarks/c16_device_bytes.py --dataset DIR [--dim 1280] [--extrapolate 239]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from data_tools.bundle_files.format import level_grids, select_levels, slide_device_bytes
from data_tools.bundle_files.reading import read_metadata


def feature_grid_bytes(meta: dict, chosen: list[int], dim: int, itemsize: int = 2) -> int:
    """Bytes of the (possibly not yet computed) feature grids of levels ``chosen`` at ``dim`` dims."""
    grids = level_grids(meta, meta.tile_size)
    return sum(grids[k][0] * grids[k][1] for k in chosen) * dim * itemsize


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("--dim", type=int, default=1280)
    p.add_argument("--extrapolate", type=int, default=None, metavar="N")
    args = p.parse_args(argv)
    folder = Path(args.dataset)
    ds = json.loads((folder / "dataset.json").read_text())
    metas = [read_metadata(folder / b) for b in ds["train"] + ds["test"]]
    gib = 2**30
    print(f"{folder}: {len(metas)} slides at {ds['scale']['mpp']:.3g} um/px")
    for n in (3, 5, 7):
        pix = [slide_device_bytes(m, select_levels(m, n), pixels=True) for m in metas]
        tab = [slide_device_bytes(m, select_levels(m, n), pixels=False) for m in metas]
        feat = [feature_grid_bytes(m, select_levels(m, n), args.dim) for m in metas]
        line = (
            f"{n} levels: pixel mode {sum(pix) / gib:.2f} GiB; feature mode {(sum(tab) + sum(feat)) / gib:.2f} GiB "
            f"(tumour tables {sum(tab) / gib:.3f} GiB + {args.dim}-d float16 feature grids {sum(feat) / gib:.2f} GiB)"
        )
        if args.extrapolate:
            f = args.extrapolate / len(metas)
            line += (
                f"; x{f:.1f} to {args.extrapolate} slides: pixel {f * sum(pix) / gib:.1f} GiB, "
                f"feature {f * (sum(tab) + sum(feat)) / gib:.1f} GiB"
            )
        print(line)
    print(
        f"largest slide, 7 levels, pixel mode: {max(slide_device_bytes(m, select_levels(m, 7)) for m in metas) / gib:.2f}"
        f" GiB; pixel pools above 2**31 px (6 GiB RGB) cannot be indexed with int32 in one env"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
