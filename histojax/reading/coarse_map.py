"""The coarse map of a navigating mode with ``coarse_map=True`` (``action_mode="discrete:map"`` /
``"continuous:map"``): one feature entry of a coarse level (``map_feature``), or a slide head's per-view score of
the coarse level's feature vectors (``map_head``: e.g. a learned attention-MIL head's instance logit, any
encoder), laid out on the 16 × 16 blocks of the visited map (:mod:`histojax.core.seen_views`), so that a navigator
sees where on the slide to go, as a cell-set reader sees its cells' coarse features.

Block ``(by, bx)`` holds the largest value of feature entry ``feature`` (e.g. the view logit of the
``pcam-cnn`` encoder, entry 62) over the level-``level`` views under the block's finest tissue views:
finest view ``(fy, fx)`` of block ``(fy·16 // gh, fx·16 // gw)`` takes the level-``level`` view that
shares its centre (the feature-grid cell nearest that view's top-left corner, as
:func:`histojax.core.modes.base.view_features` reads it). A block without tissue holds the slide's lowest value. The
map is built once per slide on the host; it carries nothing from the finest level but the tissue mask
(which comes from the slide's thumbnail).
"""

from __future__ import annotations

import numpy as np

from histojax.core.seen_views import VISITED_MAP, level_geometry, per_slide, tissue_views
from histojax.reading import heads as slide_heads


def level_index(level: int, n_levels: int) -> int:
    """Level ``level`` (negative: counted from the finest, ``-1`` = finest) as ``0 .. n_levels - 1``;
    ``ValueError`` outside the levels."""
    z = int(level) + n_levels if int(level) < 0 else int(level)
    if not 0 <= z < n_levels:
        raise ValueError(f"map_level={level} is not one of the {n_levels} levels (0 = coarsest, -1 = finest)")
    return z


def slide_map(slide, bundle, tile_size: int, feature: int | None, level: int, head=None) -> np.ndarray:
    """``(16, 16)`` float32 coarse map of one slide (single-slide ``SlideArrays``; ``level`` in
    ``0 .. n_levels - 1``): see the module doc. ``head``: a loaded slide head whose per-view scores
    (``view_logits`` of the level's ``(N, D)`` feature vectors) the map shows instead of entry ``feature``."""
    ds, _, _ = level_geometry(slide)
    f, t = len(ds) - 1, tile_size
    tissue = tissue_views(bundle, slide, t)
    gh, gw = tissue.shape
    fy, fx = np.divmod(np.arange(gh * gw), gw)
    stride = int(np.asarray(slide.feature_stride))
    lw, lh = int(np.asarray(slide.feature_grid_width)[level]), int(np.asarray(slide.feature_grid_height)[level])
    start = int(np.asarray(slide.feature_offset)[level])
    if head is not None:
        values = np.asarray(
            head.view_logits(np.asarray(slide.features[start : start + lw * lh], np.float32)), np.float32
        )
    else:
        values = np.asarray(slide.features[start : start + lw * lh, feature], np.float32)
    # the level-`level` view sharing the finest view's centre (px of level `level`), then its grid cell
    scale = ds[f] / ds[level]
    x = np.floor((fx * t + t / 2.0) * scale - t / 2.0).astype(np.int64)
    y = np.floor((fy * t + t / 2.0) * scale - t / 2.0).astype(np.int64)
    gx = np.clip((x + stride // 2) // stride, 0, lw - 1)
    gy = np.clip((y + stride // 2) // stride, 0, lh - 1)
    per_view = values[gy * lw + gx]
    on = tissue.reshape(-1)
    floor = float(per_view[on].min()) if on.any() else float(values.min())
    block = (fy * VISITED_MAP // gh) * VISITED_MAP + fx * VISITED_MAP // gw
    out = np.full(VISITED_MAP * VISITED_MAP, -np.inf, np.float32)
    np.maximum.at(out, block[on], per_view[on])
    return np.where(np.isfinite(out), out, floor).reshape(VISITED_MAP, VISITED_MAP).astype(np.float32)


def coarse_maps(env, params, bundles, feature: int | None, level: int = -3, head=None) -> np.ndarray:
    """``(S, 16, 16)`` float32: :func:`slide_map` of every slide of a dataset (host side, once). ``feature``:
    the feature entry (``ValueError`` outside the slides' features); or ``head``: a slide head (its folder, read
    by :func:`histojax.reading.heads.load`, or a loaded head) whose per-view scores the map shows (``ValueError``,
    one line, when its feature length is not the slides'); ``level``: the level read (default ``-3``, two levels
    above the finest; clipped to the coarsest)."""
    features = getattr(params.slide, "features", None)
    if features is None:
        raise ValueError(
            "a coarse map needs the slides' feature grids: make the env with obs_mode='features' "
            "(or compute them: python -m data_tools features BUNDLE)"
        )
    dim = int(np.shape(features)[-1])
    if head is not None:
        head = slide_heads.load(head) if isinstance(head, str) or hasattr(head, "__fspath__") else head
        want = getattr(head, "features_dim", None)
        if want is not None and int(want) != dim:
            raise ValueError(f"map_head: a head of {want}-d features; these slides' features have {dim} entries")
    elif feature is None or not 0 <= int(feature) < dim:
        first = getattr(bundles[0], "path", None) if len(bundles) else None
        encoder = (
            ((getattr(bundles[0], "metadata", None) or {}).get("features") or {}).get("encoder") if first else None
        )
        where = f"{first}/metadata.json: its {encoder or 'unnamed'} feature grid has" if first else "these slides have"
        raise ValueError(
            f"map_feature={feature}: {where} {dim} entries (0..{dim - 1}), no entry {feature}; a coarse "
            f"map of entry {feature} needs features that hold it (entry 62 is pcam-cnn's view logit: "
            "build the dataset with --encoder pcam-cnn)"
        )
    n = int(env.n_levels)
    z = level_index(max(int(level), -n) if int(level) < 0 else int(level), n)
    return np.stack(
        [
            slide_map(slide, bundle, env.tile_size, None if head is not None else int(feature), z, head)
            for slide, bundle in per_slide(params, bundles)
        ]
    )
