"""The registered encoders (a leaf module: :mod:`data_tools.features` and your own encoders' checks both read it)."""

# The registered encoders (``--encoder NAME`` of ``features`` and ``c16``): name → (output dim, what it is).
ENCODERS = {
    "pcam-cnn": (64, "histojax's own CNN trained on the PCam training pool at the C16 scale (default of c16; "
                     "weights shipped; docs/encoder-pcam-cnn.md)"),
    "colour-stats": (8, "8 colour statistics of the view (no weights; fast, blind to tumour across slides)"),
    "efficientnet-lite0": (1280, "ImageNet EfficientNet-Lite0 (weights from the 'features' extra)"),
}

ENCODER_MPP = {"pcam-cnn": 1.944}
"""µm per input px each built-in encoder was trained at (pcam-cnn: CAMELYON16 level 0 / 8, PCam's scale)."""
SCALE_TOLERANCE = 1.5
"""A slide whose µm/px differs from its encoder's by more than this factor (either way) is warned about."""


def encoder_scale(encoder: str, slide_mpp) -> dict | None:
    """How a slide's scale ``slide_mpp`` (µm/px, None or not positive: unknown) sits against the scale the built-in
    ``encoder`` was trained at (:data:`ENCODER_MPP`): ``{"encoder_mpp", "slide_mpp", "factor", "tolerance", "ok",
    "warning"}`` (``warning``: one sentence, or None when within :data:`SCALE_TOLERANCE`); None for an encoder
    without a training scale (colour statistics, ImageNet models, your own)."""
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
    if ok:
        warning = None
    elif known:
        warning = (f"the slide is at {mpp:.3g} µm/px, {factor:.2g}x from the {want} µm/px {encoder} was trained at "
                   f"(tolerance {SCALE_TOLERANCE}x): its features may not mean what they mean at its own scale")
    else:
        warning = (f"the slide's µm/px is unknown; {encoder} was trained at {want} µm/px: its features may not mean "
                   "what they mean at its own scale")
    return {"encoder_mpp": want, "slide_mpp": mpp if known else None, "factor": round(factor, 3) if known else None,
            "tolerance": SCALE_TOLERANCE, "ok": bool(ok), "warning": warning}


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
            warnings_.append(f"the slides mix scales: {hi} is {known[hi]:.3g} µm/px, {lo} {known[lo]:.3g} µm/px "
                             f"(more than {SCALE_TOLERANCE}x apart): one encoder sees them at different scales")
    want = ENCODER_MPP.get(str(encoder))
    if want is None:
        return None, warnings_
    out = {n: known.get(n) for n in mpps if not encoder_scale(encoder, known.get(n))["ok"]}
    if out:
        name = next(iter(out))
        first = f"{name} at {out[name]:.3g} µm/px" if out[name] else f"{name} of unknown µm/px"
        warnings_.append(f"{len(out)} of {len(mpps)} slides are more than {SCALE_TOLERANCE}x from the {want} µm/px "
                         f"{encoder} was trained at, or of unknown scale (e.g. {first}): their features may not mean "
                         "what they mean at its scale")
    return {"encoder": encoder, "encoder_mpp": want, "tolerance": SCALE_TOLERANCE, "slides_out_of_scale": out}, warnings_

