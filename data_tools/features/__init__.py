"""Feature-space observations: a frozen ImageNet encoder (EfficientNet-Lite0 in Flax, weights read from
a PyTorch file by a restricted unpickler), the feature grid of a bundle (``python -m data_tools
features``), and import of CLAM/TRIDENT patch features (``python -m data_tools import-features``).

Modules: ``torch_weights`` (safe ``.pth`` reader), ``efficientnet`` (model, ``load_encoder``,
``classify``), ``store`` (grid geometry, atomic writes, loading), ``grid`` (``compute_features``),
``hdf5`` (``import_features``), ``cli``. jax/flax are imported only by ``efficientnet`` and ``grid``.
"""
