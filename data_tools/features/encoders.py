"""The registered encoders (a leaf module: :mod:`data_tools.features` and your own encoders' checks both read it)."""

# The registered encoders (``--encoder NAME`` of ``features`` and ``c16``): name → (output dim, what it is).
ENCODERS = {
    "pcam-cnn": (64, "histojax's own CNN trained on the PCam training pool at the C16 scale (default of c16; "
                     "weights shipped; docs/encoder-pcam-cnn.md)"),
    "colour-stats": (8, "8 colour statistics of the view (no weights; fast, blind to tumour across slides)"),
    "efficientnet-lite0": (1280, "ImageNet EfficientNet-Lite0 (weights from the 'features' extra)"),
}
