"""Feature-space observations: a frozen ImageNet encoder (EfficientNet-Lite0 in Flax, weights read from
a PyTorch file by a restricted unpickler), the feature grid of a bundle (``python -m data_tools
features``), and import of CLAM/TRIDENT patch features (``python -m data_tools import-features``).

Modules: ``torch_weights`` (safe ``.pth`` reader), ``efficientnet`` (model, ``load_encoder``,
``classify``), ``store`` (grid geometry, atomic writes, loading), ``grid`` (``compute_features``),
``hdf5`` (``import_features``), ``cli``. jax/flax are imported only by ``efficientnet`` and ``grid``.
"""

# The registered encoders (``--encoder NAME`` of ``features`` and ``c16``): name → (output dim, what it is).
ENCODERS = {
    "pcam-cnn": (64, "histojax's own CNN trained on the PCam training pool at the C16 scale (default of c16; "
                     "weights shipped; docs/encoder-pcam-cnn.md)"),
    "colour-stats": (8, "8 colour statistics of the view (no weights; fast, blind to tumour across slides)"),
    "efficientnet-lite0": (1280, "ImageNet EfficientNet-Lite0 (weights from the 'features' extra)"),
}

