"""Feature-space observations: a frozen ImageNet encoder (EfficientNet-Lite0 in Flax, weights read from
a PyTorch file by a restricted unpickler), the feature grid of a bundle (``python -m data_tools
features``), and import of CLAM/TRIDENT patch features (``python -m data_tools import-features``).

Modules: ``torch_weights`` (safe ``.pth`` reader), ``efficientnet`` (model, ``load_encoder``,
``classify``), ``store`` (grid geometry, atomic writes, loading), ``grid`` (``compute_features``),
``hdf5`` (``import_features``), ``cli``. jax/flax are imported only by ``efficientnet`` and ``grid``.
"""

from data_tools.features.encoders import ENCODERS


def encoder_record(spec: str) -> dict:
    """What ``dataset.json`` records of ``--encoder spec``: ``{"encoder": NAME}`` for a built-in encoder; for your
    own (``module:function``, :mod:`data_tools.features.custom`) its name, version and spec, after a probe call
    that refuses a broken one. An unknown name raises HistojaxDataError listing the choices."""
    from data_tools.errors import HistojaxDataError
    from data_tools.features.custom import is_custom, load_custom_encoder

    if is_custom(spec):
        return load_custom_encoder(spec).record()
    if spec not in ENCODERS:
        raise HistojaxDataError(
            None,
            f"--encoder {spec!r}: use one of {', '.join(ENCODERS)}, or your own as "
            "module:function (docs/your-own-slides.md#your-own-encoder)",
        )
    return {"encoder": spec}


def encoder_name(spec: str | None) -> str | None:
    """The name a bundle's feature grid records for ``--encoder spec`` (None for None)."""
    return None if spec is None else encoder_record(spec)["encoder"]
