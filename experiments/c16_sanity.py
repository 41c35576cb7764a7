"""Does colour give the answer away? The sanity figure of the true-scale CAMELYON16 benchmark.

AUC of a linear classifier (L2 logistic regression) separating finest-level views with tumour ≥ 50 %
from tumour-free tissue views (≥ 50 % inside the slide's tissue polygon: fat and loose tissue count,
as in PCam's normal class), on the slides of a ``data_tools c16`` dataset
(2-fold cross-validation grouped by slide: trained on the views of half the slides, tested on the
other half, and back), and the same on real PCam patches (tumour / no tumour folders; random
2-fold split). Two inputs: the mean RGB of the view (3 numbers) and EfficientNet-Lite0 embeddings
(1280-d, ImageNet weights, at 224 px) of a sample of views. Prints both; the issue asks for mean-RGB
AUC ≤ 0.80 on our slides (real PCam: ~0.79) and clearly more with EfficientNet features.

    python -m experiments.c16_sanity --dataset DIR [--patches pcam_train_patches.tar.gz] [--per-class 300]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from scipy.stats import rankdata

from experiments import read_dataset

T = 128


def auc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve (Mann–Whitney, ties averaged)."""
    r = rankdata(scores)
    pos = labels == 1
    n1, n0 = int(pos.sum()), int((~pos).sum())
    return float((r[pos].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def fit_logistic(x: np.ndarray, y: np.ndarray, l2: float = 1.0):
    """L2 logistic regression on standardised ``x``; returns ``predict(x) -> scores``."""
    mu, sd = x.mean(0), x.std(0) + 1e-6
    z = (x - mu) / sd
    d = z.shape[1]

    def loss(w):
        s = z @ w[:d] + w[d]
        p = 1 / (1 + np.exp(-s))
        nll = np.logaddexp(0, s) - y * s
        g = z.T @ (p - y) / len(y)
        return nll.mean() + 0.5 * l2 * w[:d] @ w[:d] / len(y), np.concatenate(
            [g + l2 * w[:d] / len(y), [np.mean(p - y)]]
        )

    w = minimize(loss, np.zeros(d + 1), jac=True, method="L-BFGS-B").x
    return lambda xx: ((xx - mu) / sd) @ w[:d] + w[d]


def cv_auc(x, y, groups, folds: int = 2, seed: int = 0) -> float:
    """Mean AUC over ``folds`` folds split by ``groups`` (or at random when ``groups`` is None)."""
    rng = np.random.default_rng(seed)
    if groups is None:
        fold = rng.permutation(len(y)) % folds
    else:
        names = sorted(set(groups))
        tumour_groups = [g for g in names if y[np.asarray(groups) == g].any()]
        others = [g for g in names if g not in tumour_groups]
        order = list(rng.permutation(tumour_groups)) + list(rng.permutation(others))
        of = {g: i % folds for i, g in enumerate(order)}
        fold = np.array([of[g] for g in groups])
    scores = []
    for f in range(folds):
        tr, te = fold != f, fold == f
        if len(set(y[tr])) < 2 or len(set(y[te])) < 2:
            continue
        scores.append(auc(fit_logistic(x[tr], y[tr])(x[te]), y[te]))
    return float(np.mean(scores))


def dataset_views(folder: Path, per_class: int, seed: int = 0, min_tissue: float = 0.5):
    """Views ``(n, T, T, 3)``, labels and slide names: grid-aligned finest-level views with tumour ≥ 50 %
    and tumour-free views at least ``min_tissue`` inside the tissue polygon, at most ``per_class`` per
    slide and class."""
    import shapely

    from data_tools.annotations import load_annotations
    from data_tools.bundle import load_bundle

    ds = read_dataset(folder, ("slides",))
    rng = np.random.default_rng(seed)
    views, labels, groups = [], [], []
    for rec in ds["slides"]:
        b = load_bundle(folder / rec["bundle"], verify=False, levels=[0])
        pix, tum = b.pixels[0], b.tumour[0]
        t = T
        counts = np.asarray(tum.pool[:, t, t]).astype(np.int64)[tum.index]
        kept = pix.index > 0
        gh, gw = counts.shape
        pos = np.argwhere(counts >= 0.5 * t * t)
        tissue = load_annotations(folder / rec["tiff"].replace(".tif", ".geojson")).tissue
        ty_, tx_ = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
        boxes = shapely.box(tx_ * t, ty_ * t, tx_ * t + t, ty_ * t + t)
        inside = shapely.area(shapely.intersection(boxes, tissue)) / (t * t)
        neg = np.argwhere((counts == 0) & kept & (inside >= min_tissue))
        picks = []
        if len(pos):
            picks += [(p, 1) for p in pos[rng.permutation(len(pos))[:per_class]]]
        for i in rng.permutation(len(neg)):
            if sum(lab == 0 for _, lab in picks) >= per_class:
                break
            picks.append((neg[i], 0))
        for (ty, tx), lab in picks:
            views.append(pix.crop(ty * t, ty * t + t, tx * t, tx * t + t))
            labels.append(lab)
            groups.append(rec["name"])
    return np.stack(views), np.array(labels), groups


def tiff_views(folder: Path, split: str, per_class: int, seed: int = 0, min_tissue: float = 0.5, slides=None):
    """Like :func:`dataset_views`, for the slides of ``split`` (``"train"``, ``"test"`` or ``"all"``), read from
    the dataset's TIFFs (level 0, grid-aligned 128-px views) and GeoJSON polygons, so it works on
    feature-only datasets: views ≥ 50 % tumour (label 1) and tumour-free views ≥ ``min_tissue`` inside
    the tissue (label 0), at most ``per_class`` per slide and class. Returns ``(views, labels, slide names)``."""
    import shapely

    from data_tools.annotations import load_annotations
    from data_tools.slide_files.open import open_slide

    ds = read_dataset(folder, ("train", "test", "slides") if split == "all" else (split, "slides"))
    wanted = {Path(b).name for b in (ds["train"] + ds["test"] if split == "all" else ds[split])}
    rng = np.random.default_rng(seed)
    views, labels, groups = [], [], []
    for rec in ds["slides"]:
        if rec["name"] not in wanted or (slides is not None and rec["name"] not in slides):
            continue
        ann = load_annotations(folder / rec["tiff"].replace(".tif", ".geojson"))
        with open_slide(folder / rec["tiff"]) as slide:
            w, h = slide.dimensions
            gh, gw = h // T, w // T
            ty_, tx_ = np.meshgrid(np.arange(gh), np.arange(gw), indexing="ij")
            boxes = shapely.box(tx_ * T, ty_ * T, tx_ * T + T, ty_ * T + T)
            picks = []
            if ann.tumour is not None and not ann.tumour.is_empty:
                near = shapely.intersects(boxes, ann.tumour)
                frac = np.zeros((gh, gw))
                frac[near] = shapely.area(shapely.intersection(boxes[near], ann.tumour)) / T**2
                pos = np.argwhere(frac >= 0.5)
                picks += [(p, 1) for p in pos[rng.permutation(len(pos))[:per_class]]]
                free = ~near
            else:
                free = np.ones((gh, gw), bool)
            cand = np.argwhere(free & shapely.intersects(boxes, ann.tissue))
            n0 = 0
            for i in rng.permutation(len(cand)):
                if n0 >= per_class:
                    break
                ty, tx = cand[i]
                if shapely.area(shapely.intersection(boxes[ty, tx], ann.tissue)) / T**2 >= min_tissue:
                    picks.append(((ty, tx), 0))
                    n0 += 1
            for (ty, tx), lab in picks:
                views.append(np.asarray(slide.read_region(0, int(tx) * T, int(ty) * T, T, T))[..., :3])
                labels.append(lab)
                groups.append(rec["name"])
    return np.stack(views), np.array(labels), groups


def loso_auc(x: np.ndarray, y: np.ndarray, groups) -> float:
    """AUC of out-of-slide scores: each slide's views scored by a logistic regression fitted on every
    other slide's views (leave one slide out), all scores pooled into one AUC."""
    groups = np.asarray(groups)
    scores = np.full(len(y), np.nan)
    for g in sorted(set(groups)):
        te = groups == g
        if len(set(y[~te])) < 2:
            continue
        scores[te] = fit_logistic(x[~te], y[~te].astype(np.float64))(x[te])
    ok = np.isfinite(scores)
    return auc(scores[ok], y[ok])


def encoder_table(views: np.ndarray, y: np.ndarray, groups, encoders, seed: int = 0) -> list[dict]:
    """Per input (mean RGB and each encoder's embedding): linear AUC pooled (2-fold over views at random) and
    leave-one-slide-out; for ``pcam-cnn`` also the AUC of its own tumour logit (nothing fitted)."""
    from data_tools.features.efficientnet import load_encoder

    inputs = {"mean RGB (3)": views.reshape(len(views), -1, 3).mean(1)}
    own = {}
    for name in encoders:
        enc = load_encoder(name)
        emb = np.concatenate([np.asarray(enc.embed(views[i : i + 256]), np.float32) for i in range(0, len(views), 256)])
        inputs[f"{name} ({enc.dim})"] = emb
        if name == "pcam-cnn":
            own[f"{name} ({enc.dim})"] = auc(emb[:, -2], y)
    return [
        {
            "input": k,
            "pooled_auc": round(cv_auc(x, y, None, seed=seed), 3),
            "loso_auc": round(loso_auc(x, y, groups), 3),
            "own_logit_auc": round(own[k], 3) if k in own else None,
        }
        for k, x in inputs.items()
    ]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", required=True, help="a data_tools c16 dataset folder")
    p.add_argument(
        "--patches", default=None, help="real PCam patches (folder/.tar.gz/bank .npz; default: shipped bank)"
    )
    p.add_argument("--per-class", type=int, default=300, help="views per slide and class (default 300)")
    p.add_argument(
        "--min-tissue",
        type=float,
        default=0.5,
        help="a tumour-free view counts as tissue with at least this fraction inside the tissue polygon (0.5)",
    )
    p.add_argument(
        "--embed",
        type=int,
        default=600,
        help="views (and patches) per class embedded by EfficientNet-Lite0 (default 600; 0 skips it)",
    )
    p.add_argument(
        "--split",
        default=None,
        choices=("train", "test", "all"),
        help="read the views of this split from the TIFFs (works on feature-only datasets) and print the "
        "table of mean RGB and --encoders, pooled and leave-one-slide-out",
    )
    p.add_argument("--encoders", nargs="+", default=["colour-stats", "pcam-cnn"])
    p.add_argument("--out", default=None, help="with --split: write the table as JSON here")
    args = p.parse_args(argv)
    if args.split:
        t0 = time.perf_counter()
        views, y, groups = tiff_views(Path(args.dataset), args.split, args.per_class, min_tissue=args.min_tissue)
        rows = encoder_table(views, y, groups, args.encoders)
        head = (
            f"{args.split} split of {args.dataset}: {int(y.sum())} tumour views (>= 50 %), {int((y == 0).sum())} "
            f"tumour-free tissue views, {len(set(groups))} slides ({time.perf_counter() - t0:.0f} s)"
        )
        print(
            head + "\n\n| input | linear AUC, pooled (2-fold over views) | linear AUC, leave one slide out | "
            "own tumour logit AUC |\n|---|---|---|---|"
        )
        for r in rows:
            print(
                f"| {r['input']} | {r['pooled_auc']:.3f} | {r['loso_auc']:.3f} | "
                f"{'–' if r['own_logit_auc'] is None else format(r['own_logit_auc'], '.3f')} |"
            )
        if args.out:
            from data_tools.bundle_files.writes import write_json

            write_json(
                args.out,
                {
                    "summary": head,
                    "rows": rows,
                    "per_class": args.per_class,
                    "command": "python -m experiments.c16_sanity " + " ".join(argv or []),
                },
            )
        return 0
    from data_tools.datasets.pcam_bank import load_bank

    t0 = time.perf_counter()
    views, y, groups = dataset_views(Path(args.dataset), args.per_class, min_tissue=args.min_tissue)
    bank = load_bank(args.patches)
    patches = bank.decode(np.arange(len(bank)))
    py = bank.labels.astype(int)
    rgb_ours = views.reshape(len(views), -1, 3).mean(1)
    rgb_pcam = patches.reshape(len(patches), -1, 3).mean(1)
    print(
        f"dataset {args.dataset}: {int(y.sum())} tumour views (≥ 50 %), {int((y == 0).sum())} tumour-free tissue "
        f"views from {len(set(groups))} slides; PCam: {len(py)} patches ({bank.source})"
    )
    print(
        f"mean RGB + logistic regression, AUC: our slides {cv_auc(rgb_ours, y, groups):.3f} (2-fold by slide), "
        f"real PCam patches {cv_auc(rgb_pcam, py, None):.3f} (2-fold random)"
    )
    if args.embed:
        from data_tools.features.efficientnet import load_encoder

        enc = load_encoder(image_size=224)
        rng = np.random.default_rng(1)

        def embed(images):
            out = []
            for i in range(0, len(images), 64):
                batch = images[i : i + 64]
                pad = np.concatenate([batch, np.zeros((64 - len(batch),) + batch.shape[1:], np.uint8)])
                out.append(np.asarray(enc.embed(pad), np.float32)[: len(batch)])
            return np.concatenate(out)

        def sample(labels, n):
            return np.sort(np.concatenate([rng.permutation(np.flatnonzero(labels == c))[:n] for c in (0, 1)]))

        si, pi = sample(y, args.embed), sample(py, args.embed)
        e_ours, e_pcam = embed(views[si]), embed(patches[pi])
        print(
            f"EfficientNet-Lite0 (1280-d) + logistic regression, AUC: our slides "
            f"{cv_auc(e_ours, y[si], [groups[i] for i in si]):.3f} ({len(si)} views), real PCam "
            f"{cv_auc(e_pcam, py[pi], None):.3f} ({len(pi)} patches)"
        )
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


def run_main(argv=None) -> int:
    """:func:`main`, a dataset it cannot read (a malformed or incomplete ``dataset.json``, a bundle, an annotation)
    one line naming the file, exit 2."""
    from data_tools.cli_output import print_error
    from data_tools.errors import HistojaxDataError

    try:
        return main(argv)
    except HistojaxDataError as e:
        return print_error(e)


if __name__ == "__main__":
    raise SystemExit(run_main())
