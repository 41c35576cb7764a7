"""The slide loaders every head-based tool shares (the head fits, the readers, the budget curve, the diagnosis,
``histojax evaluate``): a dataset's sealed ``dataset.json`` (:func:`read_spec`, fold sides with ``fold``), its
encoder-scale warning (:func:`scale_warning`), and straight from each bundle (no env, :func:`read_bundle`, the checked
loader) the finest level's view-logit map ``(H, W)``, its tissue views ``(H, W)`` (as the reading modes count them:
:func:`histojax.core.seen_views.tissue_views`), the coarser levels' logit maps and the annotation's tumour geometry
(:func:`load_slide`, :func:`load_slides`). Bad input is a :class:`HeadDataError`: one line naming the file.

Also the CAMELYON lesion class of a tumour annotation (:func:`lesion_of`: shapely geometry in, class out) and of a
loaded slide (:func:`lesion_class`), used by the readers' lesion table, the learned head's fit and ``evaluate``'s
per-lesion rows."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from data_tools.bundle_files.format import ANNOTATIONS
from data_tools.bundle_files.reading import load_array, load_feature_levels, read_metadata
from data_tools.bundle_files.safe_files import own_file, stable_read
from data_tools.bundle_files.seals import verify_metadata
from data_tools.datasets.index import read_dataset_json
from data_tools.errors import HistojaxDataError
from data_tools.features import pcam_cnn


class HeadDataError(HistojaxDataError):
    """A dataset or bundle the head tools cannot read (file named, one line)."""


def read_spec(dataset, fold: int | None = None) -> dict:
    """The dataset's ``dataset.json`` (``HeadDataError`` naming it when missing or malformed; a ``BundleError``
    naming it when it does not match its seal, :func:`data_tools.datasets.index.read_dataset_json`). ``fold=i``
    (a dataset built with ``--folds K``): its ``train`` / ``validation`` / ``test`` lists are fold i's sides
    (:func:`histojax.datasets.with_fold`: train = the other folds); no folds or a fold out of range is a
    ``HeadDataError`` naming the file."""
    path = Path(dataset) / "dataset.json"
    try:
        spec = read_dataset_json(dataset)  # its seal checked: an edited label or split is refused, naming the file
    except FileNotFoundError:
        raise HeadDataError(
            path,
            "missing (not a dataset folder: build one with `python -m data_tools c16` or "
            "`python -m data_tools dataset`)",
        ) from None
    except (OSError, json.JSONDecodeError) as e:
        raise HeadDataError(path, f"unreadable ({e})") from None
    if not isinstance(spec, dict) or not isinstance(spec.get("train"), list):
        raise HeadDataError(path, 'has no "train" list of bundles')
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
    return (
        f"{path}: {len(out)} slide(s) are more than {rec.get('tolerance')}x from the {rec.get('encoder_mpp')} "
        f"µm/px {rec.get('encoder')} was trained at, or of unknown scale (e.g. {first}): their features may not "
        "mean what they mean at its scale, nor the head fitted on them"
    )


def warn_scale(dataset, spec: dict | None = None) -> str | None:
    """Print :func:`scale_warning` on stderr as ``warning: ...`` (one line) when the dataset records one; returns
    it."""
    line = scale_warning(dataset, spec)
    if line:
        print(f"warning: {line}", file=sys.stderr, flush=True)
    return line


def spec_label(spec: dict, name: str) -> int | None:
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
    (:mod:`data_tools.bundle_files.reading`): ``metadata.json`` read and its seal checked, every file the bundle's own
    regular file inside it (no symbolic link, no path outside the bundle), its SHA-256 checked (``verify``).
    Returns ``(metadata, {level: (gh, gw, D) feature grid}, stride, tissue (h, w) mask)`` for bundle ``levels``.
    A ``BundleError`` (or :class:`HeadDataError`) naming the bundle's file otherwise; a folder swapped by a
    concurrent rebuild is read again (:func:`data_tools.bundle_files.safe_files.stable_read`)."""
    bundle = Path(bundle)
    levels = [int(lv) for lv in levels]

    def read():
        meta = read_metadata(bundle)
        if verify:
            verify_metadata(bundle, meta)
        feats = meta.get("features") or {}
        if not feats.get("levels"):
            raise HeadDataError(
                bundle / "metadata.json",
                "has no feature grids: compute them with `histojax features "
                f"{bundle} --encoder NAME` or import them with `histojax import-features {bundle} "
                "FILE.h5`",
            )
        if any(not 0 <= lv < len(feats["levels"]) for lv in levels):
            raise HeadDataError(
                bundle / "metadata.json", f"has feature grids of {len(feats['levels'])} levels, not of levels {levels}"
            )
        grids, stride = load_feature_levels(bundle, meta, levels, verify=verify)
        tissue = load_array(bundle, meta.tissue_file, meta, verify)
        return meta, dict(zip(levels, grids)), stride, tissue

    return stable_read(bundle, read)


def finest_views(meta, grid_shape, stride: int, tissue_mask) -> tuple:
    """The finest level's views of a bundle read by :func:`read_bundle` and where each lies on its finest feature
    grid (of ``grid_shape`` ``(gh, gw, ...)``, ``stride`` px apart): ``(tissue (H, W) bool, fy (H,) int, fx (W,)
    int, tile px)``; view ``(y, x)`` reads feature cell ``(fy[y], fx[x])`` (the cell under the view's centre), and
    ``tissue`` marks the views the reading modes count (:func:`histojax.core.seen_views.tissue_views`)."""
    from histojax.core.seen_views import grid as view_grid
    from histojax.core.seen_views import tissue_views

    tile = int(meta["tile_size"])
    width, height = int(meta["levels"][0]["width"]), int(meta["levels"][0]["height"])
    gh, gw = view_grid(width, height, tile, tile)
    fy = np.clip((np.arange(gh) * tile + stride // 2) // stride, 0, grid_shape[0] - 1)
    fx = np.clip((np.arange(gw) * tile + stride // 2) // stride, 0, grid_shape[1] - 1)
    tissue = tissue_views(
        SimpleNamespace(tissue=tissue_mask),
        SimpleNamespace(downsample=[1.0], level_width=[width], level_height=[height]),
        tile,
    )
    return tissue, fy, fx, tile


def load_slide(
    bundle, label: int | None = None, dim: int = pcam_cnn.VIEW_LOGIT, levels=(0,), grid: bool = False
) -> dict:
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
            from histojax.loading import slide_label_from_metadata

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
    out = {
        "name": bundle.name,
        "label": int(label),
        "bundle": bundle,
        "logits": logits,
        "tissue": tissue,
        "coarse": coarse,
        "downsample": downsample,
        "mpp": float((meta.get("source") or {}).get("mpp") or "nan"),
        "tile": tile,
        "stride": stride,
        "tumour": tumour,
        "encoder": feats.get("encoder"),
    }
    if grid:
        if not np.all(np.isfinite(full[tissue])):
            raise HeadDataError(bundle / feats["levels"][0]["file"], "non-finite feature values on tissue views")
        out["features"] = full
    return out


def load_slides(
    dataset, split, spec: dict | None = None, dim: int = pcam_cnn.VIEW_LOGIT, levels=(0,), progress: bool = False
) -> list[dict]:
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
        yield (Path(rel) if Path(rel).is_absolute() else dataset / rel), spec_label(spec, Path(rel).name)
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


# ------------------------------------------------------------------ CAMELYON lesion classes of a loaded slide
ITC_MM, MACRO_MM = 0.2, 2.0  # CAMELYON's thresholds: isolated tumour cells below 0.2 mm, macro-metastases above 2 mm


def longest_diameter_px(geom) -> float:
    """The longest distance between two points of a polygon (px): the diameter of its convex hull."""
    hull = np.asarray(
        geom.convex_hull.exterior.coords if geom.convex_hull.geom_type == "Polygon" else geom.convex_hull.coords,
        np.float64,
    )
    if len(hull) < 2:
        return 0.0
    d = hull[:, None, :] - hull[None, :, :]
    return float(np.sqrt((d**2).sum(-1)).max())


def lesion_of(geom, mpp: float) -> tuple[str, float]:
    """``(class, mm)`` of a tumour geometry in px at ``mpp`` µm/px: its largest connected piece's longest
    diameter, ``ITC`` below 0.2 mm, ``micro`` up to 2 mm, ``macro`` above; ``"unknown"`` when empty."""
    if geom is None or geom.is_empty:
        return "unknown", float("nan")
    parts = list(getattr(geom, "geoms", [geom]))
    mm = max(longest_diameter_px(p) for p in parts) * mpp / 1000.0
    return ("ITC" if mm < ITC_MM else "micro" if mm <= MACRO_MM else "macro"), mm


CLASSES = ("ITC", "micro", "macro")


def lesion_class(slide: dict) -> tuple[str, float]:
    """``(class, largest lesion's longest diameter in mm)`` of a slide: ``"normal"`` for a label-0 slide,
    else ``ITC`` / ``micro`` / ``macro`` by CAMELYON's thresholds (0.2 and 2 mm). Lesions are the connected
    pieces of the tumour annotation; a tumour slide without polygons is ``"unknown"``."""
    if not slide["label"]:
        return "normal", 0.0
    return lesion_of(slide.get("tumour"), slide["mpp"])
