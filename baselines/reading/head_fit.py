"""Fit the slide head (:mod:`histojax.reading.heads.logit`) of a dataset: ``python -m baselines.reading.head_fit --dataset DIR --out DIR``.

Candidates: neighbourhood sides ``--ks`` (default 1 2 3 4 5 views; 1 = the plain view logit), pooled by
the maximum or the mean of the 3 largest (``--minus-median``: also each minus the read views' median
logit; see :func:`candidates` for why that is off by default). Each is
calibrated (1-D logistic regression of the slide labels on its statistic, reading everything) on the
training split minus a validation share (:func:`baselines.validation.split_train`: per class, a tumour
slide with its tissue donor; ``--val-fraction`` 0.2, ``--seed`` 0) and scored by its AUC on that
validation share; the best one (ties: the higher training AUC, then the simplest, in the order listed) is re-calibrated on the
whole training split and saved to ``--out`` (``config.json`` records every candidate's validation AUC).
The test split is never read. ``config.json`` records what the head was fitted on
(:data:`baselines.reading.provenance.RECORD`: the dataset's seal, split, fold, fitting and validation slides).
**Refused** (one line naming ``dataset.json``, nothing saved): a validation share with fewer than
:data:`baselines.validation.MIN_VALIDATION_PER_CLASS` slides of a class (before any slide is read), fewer than
:data:`MIN_SLIDES_PER_CLASS` training slides of a class after the validation share, a chosen head whose
validation AUC is below 0.5 or whose calibration slope is not positive (:func:`check_head`).

Also the data loading every head-based tool shares: :func:`load_slides` reads, straight from each
bundle (no env), the finest level's view-logit map ``(H, W)``, its tissue views ``(H, W)`` (as the
reading modes count them: :func:`histojax.core.seen_views.tissue_views`), the coarser levels' logit maps and
the annotation's tumour geometry.
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from data_tools.metrics import auc_interval, format_auc, json_number, json_safe, roc_auc, small_split_warning
from data_tools.bundle_format import (ANNOTATIONS, load_array, load_feature_levels, own_file, read_dataset_json,
                                      read_metadata, stable_read, verify_metadata)
from data_tools.cli_output import command_main, print_error
from data_tools.errors import HistojaxDataError
from data_tools.features import pcam_cnn

TOPS = (1, 3)
MIN_SLIDES_PER_CLASS = 5
"""Fewest training slides of each class (after the validation share is held back) a head fit accepts."""


class HeadDataError(HistojaxDataError):
    """A dataset or bundle the head tools cannot read (file named, one line)."""


def read_spec(dataset, fold: int | None = None) -> dict:
    """The dataset's ``dataset.json`` (``HeadDataError`` naming it when missing or malformed; a ``BundleError``
    naming it when it does not match its seal, :func:`data_tools.bundle_format.read_dataset_json`). ``fold=i``
    (a dataset built with ``--folds K``): its ``train`` / ``validation`` / ``test`` lists are fold i's sides
    (:func:`histojax.datasets.with_fold`: train = the other folds); no folds or a fold out of range is a
    ``HeadDataError`` naming the file."""
    path = Path(dataset) / "dataset.json"
    try:
        spec = read_dataset_json(dataset)  # its seal checked: an edited label or split is refused, naming the file
    except FileNotFoundError:
        raise HeadDataError(path, "missing (not a dataset folder: build one with `python -m data_tools c16` or "
                                  "`python -m data_tools dataset`)") from None
    except (OSError, json.JSONDecodeError) as e:
        raise HeadDataError(path, f"unreadable ({e})") from None
    if not isinstance(spec, dict) or not isinstance(spec.get("train"), list):
        raise HeadDataError(path, "has no \"train\" list of bundles")
    if fold is not None:
        from histojax.datasets import with_fold

        try:
            spec = with_fold(spec, fold, path)
        except HistojaxDataError as e:
            raise HeadDataError(path, e.problem) from None
    return spec


def scale_warning(dataset, spec: dict | None = None) -> str | None:
    """The encoder-scale warning ``dataset.json`` records (``encoder_scale``, written by ``histojax dataset`` /
    ``c16``: slides more than its ``tolerance`` (1.5×) from the µm/px a built-in encoder was trained at, or of
    unknown scale), as one line naming the file, for every tool that reads the dataset to repeat (the head fits,
    ``histojax evaluate``); None when it records none. ``spec``: the dataset.json already read (default: read here;
    unreadable: None, the tool's own reading says why)."""
    path = Path(dataset) / "dataset.json"
    if spec is None:
        try:
            spec = json.loads(path.read_text())
        except (OSError, ValueError):
            return None
    rec = spec.get("encoder_scale") if isinstance(spec, dict) else None
    out = rec.get("slides_out_of_scale") if isinstance(rec, dict) else None
    if not isinstance(out, dict) or not out:
        return None
    name, mpp = next(iter(out.items()))
    first = f"{name} at {float(mpp):.3g} µm/px" if isinstance(mpp, (int, float)) else f"{name} of unknown µm/px"
    return (f"{path}: {len(out)} slide(s) are more than {rec.get('tolerance')}x from the {rec.get('encoder_mpp')} "
            f"µm/px {rec.get('encoder')} was trained at, or of unknown scale (e.g. {first}): their features may not "
            "mean what they mean at its scale, nor the head fitted on them")


def warn_scale(dataset, spec: dict | None = None) -> str | None:
    """Print :func:`scale_warning` on stderr as ``warning: ...`` (one line) when the dataset records one; returns
    it."""
    line = scale_warning(dataset, spec)
    if line:
        print(f"warning: {line}", file=sys.stderr, flush=True)
    return line


def _label(spec: dict, name: str) -> int | None:
    """The slide label as the env reads it: ``dataset.json``'s ``"labels"`` (by bundle name) when it has them,
    else None (the bundle's own metadata decides: :func:`load_slide`)."""
    labels = spec.get("labels")
    if isinstance(labels, dict) and labels:
        for key, value in labels.items():
            if Path(key).name == name:
                return int(value)
    return None


def read_bundle(bundle, levels=(0,), verify: bool = True) -> tuple:
    """The arrays every head tool reads from one bundle (:func:`load_slide` here and
    :func:`baselines.reading.learned_head_fit.load_views`), through the checked loader ``histojax.make`` uses
    (:mod:`data_tools.bundle_format`): ``metadata.json`` read and its seal checked, every file the bundle's own
    regular file inside it (no symbolic link, no path outside the bundle), its SHA-256 checked (``verify``).
    Returns ``(metadata, {level: (gh, gw, D) feature grid}, stride, tissue (h, w) mask)`` for bundle ``levels``.
    A ``BundleError`` (or :class:`HeadDataError`) naming the bundle's file otherwise; a folder swapped by a
    concurrent rebuild is read again (:func:`data_tools.bundle_format.stable_read`)."""
    bundle = Path(bundle)
    levels = [int(lv) for lv in levels]

    def read():
        meta = read_metadata(bundle)
        if verify:
            verify_metadata(bundle, meta)
        feats = meta.get("features") or {}
        if not feats.get("levels"):
            raise HeadDataError(bundle / "metadata.json", "has no feature grids: compute them with `histojax features "
                                f"{bundle} --encoder NAME` or import them with `histojax import-features {bundle} "
                                "FILE.h5`")
        if any(not 0 <= lv < len(feats["levels"]) for lv in levels):
            raise HeadDataError(bundle / "metadata.json", f"has feature grids of {len(feats['levels'])} levels, "
                                                          f"not of levels {levels}")
        grids, stride = load_feature_levels(bundle, meta, levels, verify=verify)
        tissue = load_array(bundle, meta.tissue_file, meta, verify)
        return meta, dict(zip(levels, grids)), stride, tissue

    return stable_read(bundle, read)


def finest_views(meta, grid_shape, stride: int, tissue_mask) -> tuple:
    """The finest level's views of a bundle read by :func:`read_bundle` and where each lies on its finest feature
    grid (of ``grid_shape`` ``(gh, gw, ...)``, ``stride`` px apart): ``(tissue (H, W) bool, fy (H,) int, fx (W,)
    int, tile px)``; view ``(y, x)`` reads feature cell ``(fy[y], fx[x])`` (the cell under the view's centre), and
    ``tissue`` marks the views the reading modes count (:func:`histojax.core.seen_views.tissue_views`)."""
    from histojax.core.seen_views import grid as view_grid, tissue_views

    tile = int(meta["tile_size"])
    width, height = int(meta["levels"][0]["width"]), int(meta["levels"][0]["height"])
    gh, gw = view_grid(width, height, tile, tile)
    fy = np.clip((np.arange(gh) * tile + stride // 2) // stride, 0, grid_shape[0] - 1)
    fx = np.clip((np.arange(gw) * tile + stride // 2) // stride, 0, grid_shape[1] - 1)
    tissue = tissue_views(SimpleNamespace(tissue=tissue_mask),
                          SimpleNamespace(downsample=[1.0], level_width=[width], level_height=[height]), tile)
    return tissue, fy, fx, tile


def load_slide(bundle, label: int | None = None, dim: int = pcam_cnn.VIEW_LOGIT, levels=(0,),
               grid: bool = False) -> dict:
    """One bundle's arrays, read through :func:`read_bundle` (the checked loader): ``logits (H, W)`` float32
    (entry ``dim`` of the finest level's views), ``tissue (H, W)`` bool, ``coarse {level: (h, w) float32}`` for
    each bundle level in ``levels`` > 0 (cell ``(cy, cx)`` of level ``L`` covers finest views
    ``[cy·2^L, (cy+1)·2^L)`` when the levels halve), ``downsample {level: float}``, ``mpp`` (µm per finest px),
    ``tile`` (view side, px), ``tumour`` (shapely geometry in finest px, or None), ``name``, ``label``
    (``label``, or when None the bundle's own: tumour annotated or not, as the env reads it), ``bundle``; with
    ``grid`` also ``features (H, W, D)`` float16 (the finest grid, one row per finest view)."""
    from data_tools.annotations import load_annotations

    bundle = Path(bundle)
    meta_file = bundle / "metadata.json"
    try:
        meta, grids, stride, tissue_mask = read_bundle(bundle, sorted({0, *levels}))
        if label is None:
            from histojax.core.slide import slide_label_from_metadata

            label = int(slide_label_from_metadata(meta))
        feats = meta["features"]
        if not 0 <= dim < int(feats.get("dim", 0)):
            raise HeadDataError(meta_file, f"features have {feats.get('dim')} entries, no entry {dim}")
        fg = grids[0]
        tissue, fy, fx, tile = finest_views(meta, fg.shape, stride, tissue_mask)
        logits = np.asarray(fg[:, :, dim], np.float32)[fy[:, None], fx[None, :]]
        full = np.asarray(fg, np.float16)[fy[:, None], fx[None, :]] if grid else None
        coarse, downsample = {}, {}
        for lv in levels:
            if lv == 0:
                continue
            coarse[lv] = np.asarray(grids[lv][:, :, dim], np.float32)
            downsample[lv] = float(meta["levels"][lv]["downsample"])
        tumour = None
        if label and os.path.lexists(bundle / ANNOTATIONS):  # a link there is refused by own_file
            tumour = load_annotations(own_file(bundle, ANNOTATIONS, "annotations")).tumour
    except HistojaxDataError:
        raise
    except FileNotFoundError as e:
        raise HeadDataError(e.filename, "missing (an incomplete bundle? rebuild it)") from None
    except (OSError, KeyError, IndexError, TypeError, ValueError, json.JSONDecodeError) as e:
        raise HeadDataError(bundle, f"unreadable bundle ({type(e).__name__}: {e})") from None
    if not np.all(np.isfinite(logits[tissue])):
        raise HeadDataError(bundle / feats["levels"][0]["file"], "non-finite feature values on tissue views")
    out = {"name": bundle.name, "label": int(label), "bundle": bundle, "logits": logits, "tissue": tissue,
           "coarse": coarse, "downsample": downsample, "mpp": float((meta.get("source") or {}).get("mpp") or "nan"),
           "tile": tile, "stride": stride, "tumour": tumour, "encoder": feats.get("encoder")}
    if grid:
        if not np.all(np.isfinite(full[tissue])):
            raise HeadDataError(bundle / feats["levels"][0]["file"], "non-finite feature values on tissue views")
        out["features"] = full
    return out


def load_slides(dataset, split, spec: dict | None = None, dim: int = pcam_cnn.VIEW_LOGIT, levels=(0,),
                progress: bool = False) -> list[dict]:
    """:func:`load_slide` of every bundle of ``split`` (``"train"``, ``"test"``, or a list of entries of
    ``dataset.json``'s lists)."""
    spec = spec or read_spec(Path(dataset))
    return [load_slide(bundle, label, dim, levels) for bundle, label in split_bundles(dataset, split, spec, progress)]


def split_bundles(dataset, split, spec: dict, progress: bool = False):
    """The bundles of ``split`` (a split name of ``dataset.json``, or a list of its entries) with their label
    table's label (``None``: the bundle's own), one ``(bundle folder, label)`` at a time; says every 20 slides
    on stderr when ``progress``. A split ``dataset.json`` does not have is one line naming the file."""
    dataset = Path(dataset)
    entries = spec.get(split) if isinstance(split, str) else list(split)
    if entries is None:
        raise HeadDataError(dataset / "dataset.json", f"has no {split!r} split")
    for i, rel in enumerate(entries):
        yield (Path(rel) if Path(rel).is_absolute() else dataset / rel), _label(spec, Path(rel).name)
        if progress and (i + 1) % 20 == 0:
            print(f"  loaded {i + 1}/{len(entries)} slides", file=sys.stderr, flush=True)


def padded(arrays: list[np.ndarray], fill=0, shape: tuple[int, int] | None = None) -> np.ndarray:
    """``(B, Hmax, Wmax)`` stack of 2-D arrays padded with ``fill`` at the bottom / right (to ``shape`` when
    given: one compiled program for several sets of slides)."""
    h, w = shape or (max(a.shape[0] for a in arrays), max(a.shape[1] for a in arrays))
    out = np.full((len(arrays), h, w), fill, dtype=arrays[0].dtype)
    for i, a in enumerate(arrays):
        out[i, : a.shape[0], : a.shape[1]] = a
    return out


def statistics(head, slides: list[dict], masks: list[np.ndarray] | None = None,
               shape: tuple[int, int] | None = None) -> np.ndarray:
    """The head's pooled statistic ``(B,)`` of each slide over ``masks`` (default its tissue views)."""
    from histojax.reading.heads.logit import statistic_batch

    masks = [s["tissue"] for s in slides] if masks is None else masks
    return np.asarray(statistic_batch(head, padded([s["logits"] for s in slides], 0.0, shape),
                                      padded(list(masks), False, shape)))


def grid_shape(slides: list[dict]) -> tuple[int, int]:
    """The largest finest grid ``(H, W)`` of ``slides``."""
    return max(s["logits"].shape[0] for s in slides), max(s["logits"].shape[1] for s in slides)


def logistic_fit(x, y, steps: int = 3000) -> tuple[float, float]:
    """``(a, b)`` minimising the mean log loss of ``sigmoid(a · x + b)`` against 0/1 ``y`` (convex, 2 parameters;
    a small L2 penalty keeps ``a`` finite when the classes separate)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    mu, sd = x.mean(), x.std() + 1e-9
    z, w, c = (x - mu) / sd, 0.0, 0.0
    for _ in range(steps):
        p = 1.0 / (1.0 + np.exp(-np.clip(w * z + c, -60, 60)))
        w -= 0.5 * (float(np.mean((p - y) * z)) + 1e-3 * w)
        c -= 0.5 * float(np.mean(p - y))
    return w / sd, c - w * mu / sd


def candidates(ks=(1, 2, 3, 4, 5), dim: int = pcam_cnn.VIEW_LOGIT, encoder: str | None = pcam_cnn.NAME,
               minus_median: bool = False) -> list:
    """The candidate heads (uncalibrated), simplest first: for each ``k``, top-1 then top-3 (each also with the
    read views' median subtracted when ``minus_median``: off by default, because the median of what was read
    depends on where a reader looked — a reader that reads only hot cells has a hot median — so such a head
    scores a good reader's reads lower than a random reader's)."""
    from histojax.reading.heads.logit import SlideHead

    return [SlideHead(dim=dim, k=int(k), top=t, minus_median=m, encoder=encoder)
            for k in ks for t in TOPS for m in ((False, True) if minus_median else (False,))]


def calibrated(head, slides: list[dict], shape: tuple[int, int] | None = None):
    """``head`` with ``(a, b)`` fitted on ``slides`` (reading everything) and the prior log odds."""
    import jax.numpy as jnp

    labels = np.asarray([s["label"] for s in slides])
    a, b = logistic_fit(statistics(head, slides, shape=shape), labels)
    p = np.clip(labels.mean(), 1e-3, 1 - 1e-3)
    return head.replace(a=jnp.float32(a), b=jnp.float32(b), prior_logit=jnp.float32(np.log(p / (1 - p))))


def choose(train: list[dict], val: list[dict], cands) -> tuple[object, list[dict]]:
    """Calibrate each candidate on ``train``, score it on ``val``; returns the best (highest validation AUC,
    ties to the higher training AUC, then to the earliest) and the table ``[{name, k, top, minus_median, train_auc, validation_auc}]``."""
    y_tr, y_va = [s["label"] for s in train], [s["label"] for s in val]
    shape = grid_shape(train + val)
    table, best, best_key = [], None, (-1.0, -1.0)
    for c in cands:
        h = calibrated(c, train, shape)
        auc_va = round(roc_auc(statistics(h, val, shape=shape), y_va), 4)
        auc_tr = round(roc_auc(statistics(h, train, shape=shape), y_tr), 4)
        low, high = auc_interval(auc_va, int(np.sum(y_va)), len(y_va) - int(np.sum(y_va)))
        table.append({"name": c.name, "k": c.k, "top": c.top, "minus_median": c.minus_median,
                      "train_auc": auc_tr, "validation_auc": auc_va, "validation_auc_low": json_number(low),
                      "validation_auc_high": json_number(high)})
        if (auc_va, auc_tr) > best_key:
            best, best_key = c, (auc_va, auc_tr)
    if best is None:
        raise ValueError(f"the validation share ({len(val)} slides, labels {sorted(set(y_va))}) needs tumour and "
                         "normal slides to choose a head: use a larger --val-fraction or another --seed")
    return best, table


def check_classes(dataset, train: list[dict], least: int = MIN_SLIDES_PER_CLASS) -> None:
    """Refuse (:class:`HeadDataError` naming ``dataset.json``) fewer than ``least`` training slides of either
    class once the validation share is held back."""
    for cls, what in ((1, "tumour"), (0, "normal")):
        n = sum(int(s["label"] == cls) for s in train)
        if n < least:
            raise HeadDataError(Path(dataset) / "dataset.json", f"{n} {what} training slides after the validation "
                                f"share is held back; a slide head needs at least {least} of each class "
                                "(MIN_SLIDES_PER_CLASS)")


def check_head(dataset, validation_auc: float, slope: float) -> None:
    """Refuse (:class:`HeadDataError` naming ``dataset.json``; nothing is saved) a chosen head whose validation AUC
    is below 0.5 (it ranks tumour below normal: e.g. a feature entry that is no tumour logit) or whose calibration
    slope is negative (a higher statistic would mean less tumour)."""
    where = Path(dataset) / "dataset.json"
    if not validation_auc >= 0.5:
        raise HeadDataError(where, f"the chosen head's validation AUC is {validation_auc:.3f} (< 0.5: it ranks tumour "
                                   "below normal; is the feature entry a tumour logit? fit a learned head on any "
                                   "features: python -m baselines.reading.learned_head_fit); nothing saved")
    if not slope > 0:
        raise HeadDataError(where, f"the chosen head's calibration slope is {slope:.3f} (not > 0: more evidence "
                                   "would mean less tumour); nothing saved")


def fit(dataset, out=None, val_fraction: float = 0.2, seed: int = 0, ks=(1, 2, 3, 4, 5),
        dim: int = pcam_cnn.VIEW_LOGIT, progress: bool = False, minus_median: bool = False, fold: int | None = None):
    """Choose and fit the head of ``dataset`` (see the module doc); saved to ``out`` when given. ``fold=i``: on
    fold i's train side (the other folds) of a dataset built with ``--folds K``.
    Returns ``(head, table of candidates)``."""
    import datetime

    import jax

    from baselines.reading.provenance import RECORD, fit_record
    from baselines.validation import check_validation_share, split_train
    from histojax.reading.heads.files import check_writable

    if out is not None:
        check_writable(out)  # a folder that cannot be written: refused before any slide is read
    spec = read_spec(dataset, fold)
    warn_scale(dataset, spec)  # the encoder-scale warning dataset.json records, repeated
    classes = {_label(spec, Path(e).name) for e in spec["train"]}
    if len(classes) == 1 and None not in classes:  # labels from dataset.json: one class, refused before loading
        kind = "tumour" if classes.pop() else "normal"
        where = f"fold {fold}'s train side" if fold is not None else "the train split"
        raise HeadDataError(Path(dataset) / "dataset.json", f"{where} holds only {kind} slides ({len(spec['train'])}): "
                                                            "a head is fitted on tumour and normal slides; give a "
                                                            "dataset whose training slides hold both")
    kept, held = split_train(spec, val_fraction, seed)
    check_validation_share(spec, held, Path(dataset) / "dataset.json", val_fraction, fold)  # before any slide is read
    train = load_slides(dataset, spec["train"], spec, dim, progress=progress)
    by_name = {s["name"]: s for s in train}
    tr = [by_name[Path(n).name] for n in kept]
    va = [by_name[Path(n).name] for n in held]
    check_classes(dataset, tr)
    encoders = {s["encoder"] for s in train}
    encoder = encoders.pop() if len(encoders) == 1 else None
    best, table = choose(tr, va, candidates(ks, dim, encoder, minus_median))
    head = calibrated(best, train, grid_shape(train))
    chosen = next(r for r in table if r["name"] == best.name)
    check_head(dataset, chosen["validation_auc"], float(head.a))
    n_tumour = int(sum(s["label"] for s in va))
    if (warning := small_split_warning(n_tumour, len(va) - n_tumour, "the validation share"
                                       + (f" of fold {fold}" if fold is not None else ""))) is not None:
        print(warning, file=sys.stderr)  # the candidate was chosen on it (after the refusals: those stay one line)
    info = {"fitted_on": {"dataset": str(Path(dataset).resolve()), "split": "train", "slides": len(train),
                          "tumour_slides": int(sum(s["label"] for s in train)), **({"fold": fold} if fold is not None
                                                                                  else {})},
            "chosen_on": {"validation_fraction": val_fraction, "seed": seed, "train_slides": len(tr),
                          "validation_slides": len(va), "validation_auc": chosen["validation_auc"]},
            # re-calibrated on the whole train side: every train slide is a fitting slide, the share validated too
            RECORD: fit_record(dataset, spec, fold, spec["train"], held),
            "candidates": table, "date": datetime.date.today().isoformat(), "jax": jax.__version__}
    head = head.replace(info=json.dumps(json_safe(info), allow_nan=False))
    if out is not None:
        head.save(out)
    return head, table


def add_arguments(p) -> None:
    """The options of ``python -m baselines.reading.head_fit``."""
    p.add_argument("--dataset", required=True, help="dataset folder (dataset.json with a train split; feature grids)")
    p.add_argument("--out", required=True, help="folder to save the head in (config.json, params.json)")
    p.add_argument("--val-fraction", type=float, default=0.2, help="share of training slides held back to choose "
                                                                    "among the candidates (default 0.2)")
    p.add_argument("--seed", type=int, default=0, help="seed of the validation split (default 0)")
    p.add_argument("--fold", type=int, default=None, metavar="I",
                   help="a dataset built with --folds K: fit on fold I's train side (the other K - 1 folds)")
    p.add_argument("--ks", type=int, nargs="+", default=[1, 2, 3, 4, 5], help="neighbourhood sides to try (views)")
    p.add_argument("--minus-median", action="store_true",
                   help="also try each candidate minus the read views' median logit (off by default: it depends on "
                        "where a reader looked)")
    p.add_argument("--dim", type=int, default=pcam_cnn.VIEW_LOGIT,
                   help=f"feature entry holding the view tumour logit (default {pcam_cnn.VIEW_LOGIT}: pcam-cnn's)")


def run(args, parser=None) -> int:
    """Fit, save and print the candidates' table."""
    if any(k < 1 for k in args.ks):
        return print_error(f"--ks: neighbourhood sides must be ≥ 1, got {args.ks}")
    t0 = time.perf_counter()
    try:
        head, table = fit(args.dataset, args.out, args.val_fraction, args.seed, args.ks, args.dim, progress=True,
                          minus_median=args.minus_median, fold=args.fold)
    except (HistojaxDataError, ValueError) as e:
        return print_error(e)
    print("| candidate | train AUC | validation AUC [95 % interval over the validation slides] |\n|---|---|---|")
    for r in table:
        low, high = (float("nan") if v is None else v
                     for v in (r.get("validation_auc_low"), r.get("validation_auc_high")))
        print(f"| {r['name']} | {r['train_auc']:.3f} | {format_auc(r['validation_auc'], low, high)} |")
    print(f"chosen: {head.name} (slide logit = {float(head.a):.3f} · s + {float(head.b):.3f}); saved to {args.out} "
          f"in {time.perf_counter() - t0:.0f} s")
    return 0


main = command_main(add_arguments, run, "python -m baselines.reading.head_fit", __doc__)


if __name__ == "__main__":
    raise SystemExit(main())
