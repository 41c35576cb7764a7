"""How well can a slide be diagnosed from pcam-cnn's view logits, reading everything? And which slides
does it miss? The ceiling of every reader and agent on a ``data_tools c16`` (or ``histojax dataset``)
dataset embedded with ``pcam-cnn``.

For each slide of the train and test splits, its feature grid at each bundle level (level 0 = the
finest; a cell = the view of ``stride`` px at that level) is pooled into one slide score per
statistic: the largest view logit (``top1``), the mean of the ``k`` largest (``top3``, ``top10``),
and the number of views above 2.0 (``n>2``), of pcam-cnn's ``mean l`` (entry 62, the view's logit)
and ``max l`` (entry 63, its most tumour-like cell). Prints the slide AUC of each on both splits, then
the test tumour slides by the best train-split statistic with their tumour area (µm² from the
bundle's annotation area and mpp), so the misses can be read off by size.

``--probe``: also train a small MLP on the finest views' 64-d embeddings to predict "the view holds
tumour" (≥ ``--probe-positive`` of its area, from the annotation polygons; tumour-free views as
negatives) on the train split minus a validation share held back as ``c16_reference.py`` does
(:func:`baselines.validation.split_train`, seed 0), and score slides by its max over views. Reported on validation and test beside the plain maximum.

    python -m experiments.c16_slide_ceiling --dataset DIR [--levels 0 1 2 3] [--probe] [--json OUT.json]

``--lesions ANNOTATIONS``: the CAMELYON lesion class (largest lesion's longest diameter: isolated tumour cells
< 0.2 mm, micrometastasis 0.2–2 mm, macrometastasis > 2 mm) of every tumour slide of the NCRF annotations a
``data_tools c16`` set is built from, by the set's split, from the geometry alone (no slide built)::

    python -m experiments.c16_slide_ceiling --lesions camelyon16_ncrf_train.tar.gz
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from baselines.validation import split_train
from data_tools.errors import HistojaxDataError
from data_tools.features import pcam_cnn, pcam_cnn96
from data_tools.metrics import auc_interval, format_auc, json_safe, roc_auc
from experiments import read_dataset

STATS = ("top1", "top3", "top10", "n>2")
ENTRIES = {"mean l": pcam_cnn.VIEW_LOGIT, "max l": pcam_cnn.MAX_CELL_LOGIT}


class CeilingError(HistojaxDataError):
    """A dataset this benchmark cannot read (named file, one line)."""


def slide_grids(dataset: Path, split: str, meta: dict | None = None) -> list[dict]:
    """``[{name, label, bundle, mpp, tumour_area_px, grids: {level: (gh, gw, D) float32}}]`` of ``split``
    (``meta``: the dataset's ``dataset.json``, read when not given)."""
    meta = meta or read_dataset(dataset, (split,))
    out = []
    for rel in meta[split]:
        bundle = dataset / rel
        name = Path(rel).name
        m = json.loads((bundle / "metadata.json").read_text())
        feats = m.get("features") or {}
        if feats.get("encoder") not in (pcam_cnn.NAME, pcam_cnn96.NAME):  # the family: the same entries
            raise CeilingError(
                bundle / "metadata.json",
                f"features are {feats.get('encoder')!r}, not pcam-cnn; "
                f"run `python -m data_tools features {bundle} --encoder pcam-cnn`",
            )
        grids = {k: np.load(bundle / lv["file"]).astype(np.float32) for k, lv in enumerate(feats["levels"])}
        out.append(
            {
                "name": name,
                "label": int(meta["labels"][name]),
                "bundle": bundle,
                "mpp": float(m["source"].get("mpp") or float("nan")),
                "tumour_area_px": float(m["annotations"].get("tumour_area_px") or 0.0),
                "stride": int(feats["stride"]),
                "grids": grids,
            }
        )
    return out


def pool(grid: np.ndarray, entry: int, stat: str) -> float:
    """One slide score from a ``(gh, gw, D)`` feature grid: ``stat`` of entry ``entry`` over its views."""
    v = np.sort(grid[..., entry].ravel())[::-1]
    if stat == "n>2":
        return float((v > 2.0).sum())
    return float(v[: int(stat[3:])].mean())


def pooled_aucs(slides: list[dict], levels) -> dict:
    """``{(level, entry name, stat): AUC}`` over ``slides``."""
    y = [s["label"] for s in slides]
    return {
        (lv, e, st): roc_auc([pool(s["grids"][lv], i, st) for s in slides], y)
        for lv in levels
        for e, i in ENTRIES.items()
        for st in STATS
    }


def view_tumour_fraction(bundle: Path, shape: tuple[int, int], stride: int) -> np.ndarray:
    """``(gh, gw)`` share of each finest-level ``stride``-px cell inside the bundle's tumour polygons."""
    import shapely

    from data_tools.annotations import load_annotations

    gh, gw = shape
    ann = load_annotations(bundle / "annotations.geojson")
    tumour = ann.tumour
    if tumour is None or tumour.is_empty:
        return np.zeros(shape, np.float32)
    ys, xs = np.mgrid[0:gh, 0:gw]
    boxes = shapely.box(xs.ravel() * stride, ys.ravel() * stride, (xs.ravel() + 1) * stride, (ys.ravel() + 1) * stride)
    hit = shapely.intersects(boxes, tumour)
    frac = np.zeros(boxes.shape, np.float64)
    frac[hit] = shapely.area(shapely.intersection(boxes[hit], tumour)) / stride**2
    return frac.reshape(shape).astype(np.float32)


def probe(
    train: list[dict],
    val: list[dict],
    test: list[dict],
    positive: float = 0.25,
    hidden: int = 32,
    epochs: int = 6,
    seed: int = 0,
) -> dict:
    """Train an MLP view classifier on ``train``'s finest views (labels from the polygons) and return the
    slide AUC of its max over views on ``val`` and ``test`` (and of the plain ``mean l`` maximum)."""
    import jax
    import jax.numpy as jnp
    import optax

    rng = np.random.default_rng(seed)
    xs, ys = [], []
    for s in train:
        g = s["grids"][0]
        frac = (
            view_tumour_fraction(s["bundle"], g.shape[:2], s["stride"]).ravel()
            if s["label"]
            else np.zeros(g.shape[0] * g.shape[1], np.float32)
        )
        xs.append(g.reshape(-1, g.shape[-1]))
        ys.append(frac)
    x, y = np.concatenate(xs), np.concatenate(ys)
    tissue = np.abs(x).sum(1) > 0
    mu, sd = x[tissue].mean(0), x[tissue].std(0) + 1e-3
    pos = np.flatnonzero(y >= positive)
    neg = np.flatnonzero((y == 0) & tissue)
    neg = rng.choice(neg, min(len(neg), 400_000), replace=False)
    idx = np.concatenate([pos, neg])
    xb, yb = ((x[idx] - mu) / sd).astype(np.float32), (y[idx] >= positive).astype(np.float32)
    w_pos = len(neg) / max(1, len(pos))
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    d = x.shape[1]
    params = {
        "w1": jax.random.normal(k1, (d, hidden)) / np.sqrt(d),
        "b1": jnp.zeros(hidden),
        "w2": jax.random.normal(k2, (hidden,)) / np.sqrt(hidden),
        "b2": jnp.zeros(()),
    }

    def logit(p, v):
        return jax.nn.relu(v @ p["w1"] + p["b1"]) @ p["w2"] + p["b2"]

    def loss(p, v, t):
        w = jnp.where(t > 0, w_pos, 1.0)
        return (w * optax.sigmoid_binary_cross_entropy(logit(p, v), t)).sum() / w.sum()

    opt = optax.adamw(1e-3, weight_decay=1e-4)
    state = opt.init(params)

    @jax.jit
    def update(p, st, v, t):
        g = jax.grad(loss)(p, v, t)
        u, st = opt.update(g, st, p)
        return optax.apply_updates(p, u), st

    for _ in range(epochs):
        perm = rng.permutation(len(xb))
        for i in range(0, len(perm) - 4095, 4096):
            b = perm[i : i + 4096]
            params, state = update(params, state, xb[b], yb[b])

    def slide_max(s):
        g = s["grids"][0].reshape(-1, d)
        g = g[np.abs(g).sum(1) > 0]
        return float(jnp.max(logit(params, jnp.asarray((g - mu) / sd))))

    out = {"positive_views": int(len(pos)), "negative_views": int(len(neg)), "hidden": hidden, "epochs": epochs}
    for name, part in (("validation", val), ("test", test)):
        labels = [s["label"] for s in part]
        out[name] = {
            "probe max": roc_auc([slide_max(s) for s in part], labels),
            "mean l max": roc_auc([pool(s["grids"][0], pcam_cnn.VIEW_LOGIT, "top1") for s in part], labels),
        }
    return out


def lesion_census(annotations, test_fraction: float = 0.25, seed: int = 0) -> list[dict]:
    """CAMELYON lesion class of every tumour slide of an NCRF annotation source (``data_tools c16
    --annotations``), on the side of the split ``data_tools c16`` gives it with ``test_fraction`` and ``seed``
    (the split of the whole set, which any subset keeps): ``[{slide, split, class, diameter_mm, area_mm2}]``.
    Geometry only (no slide is built): tumour = the NCRF positive polygons minus the negative ones, at
    CAMELYON16 level 0 (0.243 µm/px)."""
    import shapely

    from baselines.reading.slides import lesion_of
    from data_tools.datasets.c16.layout import C16_MPP, OWN_TISSUE, donor_for
    from data_tools.datasets.split import grouped_split
    from data_tools.ncrf import read_ncrf

    every = read_ncrf(annotations)
    tumours = [n for n in every if every[n].is_tumour_slide]
    normals = [n for n in every if not every[n].is_tumour_slide]
    donors = {n: donor_for(n, tumours, normals) for n in tumours if n not in OWN_TISSUE and normals}
    _, test = grouped_split(list(every), donors, test_fraction, seed)
    rows = []
    for n in tumours:
        geom = shapely.difference(every[n].positive, every[n].negative)
        cls, mm = lesion_of(geom, C16_MPP)
        rows.append(
            {
                "slide": n,
                "split": "test" if n in set(test) else "train",
                "class": cls,
                "diameter_mm": mm,
                "area_mm2": float(geom.area) * C16_MPP**2 / 1e6,
            }
        )
    return rows


def print_census(rows: list[dict]) -> None:
    """Per split, how many tumour slides of each CAMELYON class."""
    print("| split | tumour slides | ITC (< 0.2 mm) | micro (0.2–2 mm) | macro (> 2 mm) |\n|---|---|---|---|---|")
    for split in ("train", "test"):
        mine = [r for r in rows if r["split"] == split]
        print(
            f"| {split} | {len(mine)} | "
            + " | ".join(str(sum(r["class"] == c for r in mine)) for c in ("ITC", "micro", "macro"))
            + " |"
        )


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--dataset", type=Path, help="a pcam-cnn dataset (required unless --lesions only)")
    p.add_argument(
        "--lesions",
        metavar="ANNOTATIONS",
        default=None,
        help="print the CAMELYON lesion classes of every tumour slide of this NCRF source (as given to "
        "`data_tools c16 --annotations`) by split, from the geometry alone, and stop unless --dataset",
    )
    p.add_argument("--levels", type=int, nargs="+", default=[0, 1, 2, 3], help="bundle levels (0 = finest)")
    p.add_argument("--probe", action="store_true", help="also train the MLP view probe (a minute on 2 cores)")
    p.add_argument("--probe-positive", type=float, default=0.25)
    p.add_argument("--val-fraction", type=float, default=0.2)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    if args.lesions:
        try:
            census = lesion_census(args.lesions)
        except (OSError, ValueError, HistojaxDataError) as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print_census(census)
        print("| test tumour slide | class | largest lesion (mm) | tumour area (mm²) |\n|---|---|---|---|")
        for r in sorted((r for r in census if r["split"] == "test"), key=lambda r: r["diameter_mm"]):
            print(f"| {r['slide']} | {r['class']} | {r['diameter_mm']:.3f} | {r['area_mm2']:.3f} |")
        if args.json and not args.dataset:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(json_safe({"lesions": census}), indent=1, default=float, allow_nan=False))
        if not args.dataset:
            return 0
    if not args.dataset:
        print("error: --dataset is required (or --lesions ANNOTATIONS alone)", file=sys.stderr)
        return 2
    try:
        spec = read_dataset(args.dataset, ("train", "test"))  # its lists checked: one line naming it
        train, test = slide_grids(args.dataset, "train", spec), slide_grids(args.dataset, "test", spec)
    except (OSError, KeyError, ValueError, HistojaxDataError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    levels = [lv for lv in args.levels if all(lv in s["grids"] for s in train + test)]
    a_train, a_test = pooled_aucs(train, levels), pooled_aucs(test, levels)
    print(f"slide AUC of pooled pcam-cnn view logits ({len(train)} train, {len(test)} test slides)")
    n_test = (sum(s["label"] for s in test), sum(1 - s["label"] for s in test))  # the interval's tumour, normal slides
    print(
        "| level | entry | statistic | train AUC | test AUC [95 % interval over the test slides] |\n"
        "|---|---|---|---|---|"
    )
    for key in a_train:
        print(
            f"| {key[0]} | {key[1]} | {key[2]} | {a_train[key]:.3f} | "
            f"{format_auc(a_test[key], *auc_interval(a_test[key], *n_test))} |"
        )
    best = max(a_train, key=lambda k: a_train[k])
    lv, entry, stat = best
    normal_top = max(pool(s["grids"][lv], ENTRIES[entry], stat) for s in test if s["label"] == 0)
    shown = format_auc(a_test[best], *auc_interval(a_test[best], *n_test))
    print(f"\nbest on train: level {lv}, {entry}, {stat} (test {shown}); highest test normal slide: {normal_top:.2f}")
    print("| test tumour slide | score | tumour area (mm²) | above every normal |\n|---|---|---|---|")
    rows = []
    for s in sorted((s for s in test if s["label"] == 1), key=lambda s: s["tumour_area_px"]):
        score = pool(s["grids"][lv], ENTRIES[entry], stat)
        area = s["tumour_area_px"] * s["mpp"] ** 2 / 1e6
        rows.append({"slide": s["name"], "score": score, "tumour_area_mm2": area, "above_normals": score > normal_top})
        print(f"| {s['name']} | {score:.2f} | {area:.3f} | {'yes' if score > normal_top else 'no'} |")
    result = {
        "pooled": [
            {
                "level": k[0],
                "entry": k[1],
                "stat": k[2],
                "train_auc": a_train[k],
                "test_auc": a_test[k],
                **dict(zip(("test_auc_low", "test_auc_high"), auc_interval(a_test[k], *n_test))),
            }
            for k in a_train
        ],
        "best_on_train": {"level": lv, "entry": entry, "stat": stat, "test_auc": a_test[best]},
        "test_tumour_slides": rows,
    }
    if args.probe:
        _, held = split_train(spec, args.val_fraction, 0)  # per class, tissue donors with their tumour slide
        held = {Path(h).name for h in held}
        kept, val = [s for s in train if s["name"] not in held], [s for s in train if s["name"] in held]
        result["probe"] = probe(kept, val, test, positive=args.probe_positive)
        pr = result["probe"]
        n_val = (sum(s["label"] for s in val), sum(1 - s["label"] for s in val))

        def shown(auc: float, n) -> str:  # "0.849 [0.741, 0.936]": the AUC and its 95 % interval over the slides
            return format_auc(auc, *auc_interval(auc, *n))[4:]

        print(
            f"\nMLP view probe (trained on {len(kept)} slides' finest views: {pr['positive_views']} tumour, "
            f"{pr['negative_views']} tumour-free): validation AUC {shown(pr['validation']['probe max'], n_val)} "
            f"(plain mean-l max {shown(pr['validation']['mean l max'], n_val)}), test "
            f"{shown(pr['test']['probe max'], n_test)} ({shown(pr['test']['mean l max'], n_test)})"
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(json_safe(result), indent=1, default=float, allow_nan=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
