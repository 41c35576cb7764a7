"""The older import path of the pure-JAX wrappers, which live in :mod:`histojax.adapters.jax`
(``LogWrapper``, ``GymnaxV0Wrapper``, ``Wrapper``); the Gymnasium bridges ``GymnasiumEnv`` and
``GymnasiumVectorEnv`` of :mod:`histojax.adapters.gymnasium` load from here on first use (gymnasium
is optional). Where each audience's adapter lives: :mod:`histojax.adapters`."""
from histojax.adapters.jax import GymnaxV0Wrapper, LogEnvState, LogWrapper, Wrapper, vmap_reset  # noqa: F401

_GYMNASIUM = ("GymnasiumEnv", "GymnasiumVectorEnv")


def __getattr__(name):
    """``GymnasiumEnv`` and ``GymnasiumVectorEnv`` load on first use (gymnasium is optional)."""
    if name in _GYMNASIUM:
        from histojax.adapters import gymnasium

        return getattr(gymnasium, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["GymnaxV0Wrapper", "LogEnvState", "LogWrapper", "Wrapper", "vmap_reset", *_GYMNASIUM]
