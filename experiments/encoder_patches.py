"""Patch AUC of every registered encoder on the PCam **test pool** (patches no histojax model was trained
on), and each encoder's embedding speed on 128-px views. The model card's figures
(docs/encoder-pcam-cnn.md).

For each encoder, patches are shown at the benchmark's scale (96 px → 48 px, 1.94 µm/px; EfficientNet-Lite0
resizes them to its 224 px), except ``pcam-cnn96``, trained at PCam's own scale, which sees them at 96 px.
Scores: ``pcam-cnn``'s and ``pcam-cnn96``'s own tumour logit (no fitting), and for every encoder a
linear probe (L2 logistic regression) fitted on ``--fit`` training-pool patches and scored on ``--test``
test-pool patches, on PCam's own colours and on a fixed mosaic-like stain (the C16 mosaic's stain jitter and
colour matching). Speed: views/s of ``embed`` on uint8 ``(B, 128, 128, 3)`` after one call compiled it.

    python -m experiments.encoder_patches --patches pcam_train_patches.tar.gz [--fit 2000] [--test 3000]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def embed_all(encoder, images: np.ndarray, batch: int = 256) -> np.ndarray:
    """float32 ``(N, D)`` embeddings of uint8 images, ``batch`` at a time."""
    return np.concatenate([np.asarray(encoder.embed(images[i : i + batch])) for i in range(0, len(images), batch)])


def views_per_second(encoder, batch: int = 512, seconds: float = 3.0, side: int = 128) -> float:
    """Embedding throughput on random uint8 ``(batch, side, side, 3)`` views, compile excluded."""
    x = np.random.default_rng(0).integers(0, 256, (batch, side, side, 3), dtype=np.uint8)
    encoder.embed(x).block_until_ready()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        encoder.embed(x).block_until_ready()
        n += batch
    return n / (time.perf_counter() - t0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--patches", default=None, help="PCam patches (default: the shipped 1,000-patch bank)")
    p.add_argument("--fit", type=int, default=2000, help="training-pool patches the linear probes are fitted on")
    p.add_argument("--test", type=int, default=3000, help="test-pool patches scored")
    p.add_argument("--encoders", nargs="+", default=None, help="default: every registered encoder")
    p.add_argument("--seconds", type=float, default=3.0, help="timed seconds per speed figure")
    p.add_argument("--out", default=None, help="write the figures as JSON here")
    args = p.parse_args(argv)

    from data_tools.datasets.pcam_bank import load_bank, split_pools
    from data_tools.features import ENCODERS
    from data_tools.features.efficientnet import load_encoder
    from data_tools.features.train_pcam_cnn import box_half, stained_copy
    from experiments.c16_sanity import auc, fit_logistic

    train_pool, test_pool = split_pools(load_bank(args.patches))
    rng = np.random.default_rng(0)
    fit_idx = np.sort(rng.choice(len(train_pool), min(args.fit, len(train_pool)), replace=False))
    test_idx = np.sort(rng.choice(len(test_pool), min(args.test, len(test_pool)), replace=False))
    from data_tools.features.encoders import ENCODER_MPP

    fit96, test96 = train_pool.decode(fit_idx), test_pool.decode(test_idx)
    y_fit, y_test = train_pool.labels[fit_idx].astype(np.float64), test_pool.labels[test_idx]
    # every encoder at 48 px (1.94 µm/px) but those trained at PCam's own 0.97 µm/px, which see the 96-px patches
    at48 = (box_half(fit96), {"raw": box_half(test96), "mosaic": stained_copy(box_half(test96), y_test, 99)})
    at96 = (fit96, {"raw": test96, "mosaic": stained_copy(test96, y_test, 99, shift=8)})
    rows = []
    for name in args.encoders or list(ENCODERS):
        try:
            enc = load_encoder(name)
        except Exception as e:  # an optional encoder's weights not installed
            rows.append({"encoder": name, "skipped": f"{type(e).__name__}: {e}"})
            continue
        t0 = time.perf_counter()
        x_fit, variants = at96 if ENCODER_MPP.get(name) == 0.972 else at48
        probe = fit_logistic(embed_all(enc, x_fit), y_fit)
        row = {"encoder": name, "dim": enc.dim}
        for v, x in variants.items():
            z = embed_all(enc, x)
            row[f"probe_auc_{v}"] = round(auc(probe(z), y_test), 4)
            if name in ("pcam-cnn", "pcam-cnn96"):
                row[f"logit_auc_{v}"] = round(auc(np.asarray(enc.logits(x)), y_test), 4)
        row["embed_seconds"] = round(time.perf_counter() - t0, 1)
        row["views_per_s_128px"] = round(views_per_second(enc, seconds=args.seconds, batch=64 if enc.dim > 64 else 512))
        rows.append(row)
        print(json.dumps(row), flush=True)  # json-not-written (printed)
    result = {
        "patches": str(args.patches),
        "fit_patches": len(fit_idx),
        "test_patches": len(test_idx),
        "command": "python -m experiments.encoder_patches " + " ".join(argv if argv is not None else sys.argv[1:]),
        "rows": rows,
    }
    print(
        "\n| encoder | D | own logit AUC (PCam / mosaic colours) | linear-probe AUC (PCam / mosaic) | "
        "128-px views/s |\n|---|---|---|---|---|"
    )
    for r in rows:
        if "skipped" in r:
            print(f"| {r['encoder']} | – | skipped: {r['skipped']} | | |")
            continue
        own = f"{r['logit_auc_raw']:.3f} / {r['logit_auc_mosaic']:.3f}" if "logit_auc_raw" in r else "–"
        print(
            f"| {r['encoder']} | {r['dim']} | {own} | {r['probe_auc_raw']:.3f} / {r['probe_auc_mosaic']:.3f} | "
            f"{r['views_per_s_128px']:,} |"
        )
    if args.out:
        from data_tools.bundle_files.writes import write_json

        write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
