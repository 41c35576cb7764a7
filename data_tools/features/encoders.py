"""The registered encoders (a leaf module: :mod:`data_tools.features` and your own encoders' checks both read it)."""

# The registered encoders (``--encoder NAME`` of ``features`` and ``c16``): name → (output dim, what it is).
ENCODERS = {
    "pcam-cnn": (
        64,
        "histojax's own CNN trained on the PCam training pool at the C16 scale (default of c16; "
        "weights shipped; docs/encoder-pcam-cnn.md)",
    ),
    "pcam-cnn96": (
        64,
        "the pcam-cnn family at PCam's native scale (96-px patches, 0.97 µm/px: c16 --downsample 4; "
        "weights shipped; docs/encoder-pcam-cnn96.md)",
    ),
    "colour-stats": (8, "8 colour statistics of the view (no weights; fast, blind to tumour across slides)"),
    "efficientnet-lite0": (1280, "ImageNet EfficientNet-Lite0 (weights from the 'features' extra)"),
}

ENCODER_MPP = {"pcam-cnn": 1.944, "pcam-cnn96": 0.972}
"""µm per input px each built-in encoder was trained at (pcam-cnn: CAMELYON16 level 0 / 8, PCam's patches halved;
pcam-cnn96: level 0 / 4, PCam's own scale)."""
SCALE_TOLERANCE = 1.5
"""A slide whose µm/px differs from its encoder's by more than this factor (either way) is warned about."""


def level_on_scale(slide_mpp: float, encoder_mpp: float, downsamples) -> tuple[int, float] | None:
    """``(k, downsample)`` of the level (``downsamples``: level-0 px per level px, finest first) whose µm/px
    (``slide_mpp × downsample``) is closest to ``encoder_mpp`` and within :data:`SCALE_TOLERANCE` of it; None when
    no level is."""
    best = None
    for k, d in enumerate(downsamples or ()):
        factor = max(slide_mpp * d / encoder_mpp, encoder_mpp / (slide_mpp * d))
        if factor <= SCALE_TOLERANCE and (best is None or factor < best[0]):
            best = (factor, k, float(d))
    return None if best is None else best[1:]


def encoder_scale(encoder: str, slide_mpp, downsamples=None, remedy: str | None = None) -> dict | None:
    """How a slide's scale ``slide_mpp`` (µm/px, None or not positive: unknown) sits against the scale the built-in
    ``encoder`` was trained at (:data:`ENCODER_MPP`): ``{"encoder_mpp", "slide_mpp", "factor", "tolerance", "ok",
    "warning", "level_on_scale"}`` (``warning``: one sentence, or None when within :data:`SCALE_TOLERANCE`); None for
    an encoder without a training scale (colour statistics, ImageNet models, your own). ``downsamples``: the bundle's
    levels (finest first); when level 0 is off scale but one of them is on it (:func:`level_on_scale`), the warning
    names that level and says to use its features, and ``level_on_scale`` is its index (else None). ``remedy``: what
    the warning offers instead of ``--mpp`` (a command without that option, e.g. ``c16``, whose µm/px is known)."""
    want = ENCODER_MPP.get(str(encoder))
    if want is None:
        return None
    try:
        mpp = float(slide_mpp)
    except (TypeError, ValueError):
        mpp = float("nan")
    known = mpp > 0 and mpp == mpp and mpp != float("inf")
    factor = max(mpp / want, want / mpp) if known else None
    ok = known and factor <= SCALE_TOLERANCE
    on_scale = level_on_scale(mpp, want, downsamples) if known and not ok else None
    if ok:
        warning = None
    elif on_scale is not None:
        k, d = on_scale
        warning = (
            f"the slide's level 0 is at {mpp:.3g} µm/px, {factor:.2g}x from the {want} µm/px {encoder} was "
            f"trained at (tolerance {SCALE_TOLERANCE}x), but its level {k} (downsample {d:.3g}) is at "
            f"{mpp * d:.3g} µm/px, on that scale: use the features of level {k} (and the coarser ones within "
            f"{SCALE_TOLERANCE}x), not those of the finer levels; "
            + (remedy or "if the file's µm/px is wrong, give the true one with --mpp")
        )
    elif known:
        warning = (
            f"the slide is at {mpp:.3g} µm/px, {factor:.2g}x from the {want} µm/px {encoder} was trained at "
            f"(tolerance {SCALE_TOLERANCE}x): its features may not mean what they mean at its own scale; "
            + (remedy or "if the file's µm/px is wrong, give the true one with --mpp")
        )
    else:
        warning = (
            f"the slide's µm/px is unknown; {encoder} was trained at {want} µm/px: its features may not mean "
            "what they mean at its own scale; " + (remedy or "give the slide's µm/px with --mpp")
        )
    return {
        "encoder_mpp": want,
        "slide_mpp": mpp if known else None,
        "factor": round(factor, 3) if known else None,
        "tolerance": SCALE_TOLERANCE,
        "ok": bool(ok),
        "warning": warning,
        "level_on_scale": None if on_scale is None else on_scale[0],
    }


def dataset_scale(encoder: str | None, mpps: dict) -> tuple[dict | None, list[str]]:
    """``(record, warnings)`` of a dataset's slide scales ``mpps`` (name → µm/px or None): ``warnings`` one
    sentence each — slides whose µm/px differ by more than :data:`SCALE_TOLERANCE` between them (a mixed dataset),
    and slides far from (or of unknown scale for) a built-in ``encoder``'s training scale (:func:`encoder_scale`);
    ``record`` (for ``dataset.json``'s ``encoder_scale``; None for an encoder without a training scale): the
    encoder's µm/px, the tolerance, and the slides out of it (name → µm/px or None)."""
    warnings_ = []
    known = {n: float(m) for n, m in mpps.items() if isinstance(m, (int, float)) and m and m > 0}
    if len(known) > 1:
        lo, hi = min(known, key=known.get), max(known, key=known.get)
        if known[hi] > known[lo] * SCALE_TOLERANCE:
            warnings_.append(
                f"the slides mix scales: {hi} is {known[hi]:.3g} µm/px, {lo} {known[lo]:.3g} µm/px "
                f"(more than {SCALE_TOLERANCE}x apart): one encoder sees them at different scales"
            )
    want = ENCODER_MPP.get(str(encoder))
    if want is None:
        return None, warnings_
    out = {n: known.get(n) for n in mpps if not encoder_scale(encoder, known.get(n))["ok"]}
    if out:
        name = next(iter(out))
        mpp = out[name]
        first = (
            f"{name} of unknown µm/px"
            if not mpp
            else f"{name} at {mpp:.3g} µm/px"
            if mpp * SCALE_TOLERANCE > want
            else f"{name} at {mpp:.3g} µm/px, whose levels near downsample {want / mpp:.3g} are on that scale: "
            "use their features"
        )
        warnings_.append(
            f"{len(out)} of {len(mpps)} slides are more than {SCALE_TOLERANCE}x from the {want} µm/px "
            f"{encoder} was trained at, or of unknown scale (e.g. {first}): their features may not mean "
            "what they mean at its scale; where a file states no or a wrong µm/px, give it with --mpp"
        )
    return {
        "encoder": encoder,
        "encoder_mpp": want,
        "tolerance": SCALE_TOLERANCE,
        "slides_out_of_scale": out,
    }, warnings_
