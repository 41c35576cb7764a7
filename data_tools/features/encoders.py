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

