"""The patch names that texture each side of a built C16 dataset, as a small record for the tests.

Reads every ``slides/NAME.provenance.json`` of the dataset (``patch_names`` per label, ``patch_pool``)
and writes ``OUT`` (``.npz``): for each side, the sorted ``label/name`` keys of every patch used.
``tests/data_pipeline/test_c16.py`` checks the full set's record (``tests/data/c16_full_patch_names.npz``, made by
this script on the full set built in docs/c16-benchmark.md): no patch on both sides, each side's
patches in its pool by the rule recorded in ``dataset.json``.

    python -m experiments.c16_patch_record --dataset c16-full --out tests/data/c16_full_patch_names.npz
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def patch_record(folder: Path) -> dict[str, np.ndarray]:
    """``{"train": keys, "test": keys, "slides_train": n, "slides_test": n}`` with keys ``"label/name"``."""
    ds = json.loads((folder / "dataset.json").read_text())
    out, counts = {}, {}
    for side in ("train", "test"):
        keys = set()
        for bundle in ds[side]:
            prov = json.loads((folder / "slides" / f"{Path(bundle).name}.provenance.json").read_text())
            if prov.get("patch_pool") != side:
                raise SystemExit(f"{bundle}: textured from the {prov.get('patch_pool')!r} pool, not {side!r}")
            keys |= {f"{lab}/{n}" for lab, names in prov["patch_names"].items() for n in names}
        out[side] = np.array(sorted(keys))
        counts[side] = len(ds[side])
    out["slides"] = np.array([counts["train"], counts["test"]])
    out["pool_rule"] = np.array(json.dumps(ds["patch_pools"]["rule"]))  # json-not-written (an npz entry)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    rec = patch_record(Path(args.dataset))
    np.savez_compressed(args.out, **rec)
    print(
        f"wrote {args.out}: {len(rec['train'])} patches on {rec['slides'][0]} train slides, {len(rec['test'])} on "
        f"{rec['slides'][1]} test slides, {len(set(rec['train']) & set(rec['test']))} on both"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
