"""Adapters: the histojax environment for each audience, one module each.

=====================================  ==========================================  =====================
audience                               module                                      older import path
=====================================  ==========================================  =====================
gymnax, PureJaxRL, rejax (pure JAX)    :mod:`histojax.adapters.jax` —              ``histojax.wrappers``
                                       ``LogWrapper``, ``GymnaxV0Wrapper``,
                                       ``Wrapper``
Gymnasium (numpy; Tianshou, ...)       :mod:`histojax.adapters.gymnasium` —        ``histojax.gymnasium_bridge``
                                       ``GymnasiumEnv``, ``GymnasiumVectorEnv``,
                                       ``gymnasium.make("histojax/<id>")``
Stable-Baselines3                      :mod:`histojax.adapters.sb3` —              ``histojax.sb3``
                                       ``SB3VecEnv``, ``make_sb3_vec_env``
HistoGym code (gym 0.21 API)           :mod:`histojax.adapters.histogym` —         ``histojax.compat``
                                       ``HistoEnv(img_path, xml_path, ...)``
=====================================  ==========================================  =====================

The older paths keep working (``histojax.gymnasium_bridge``, ``histojax.sb3`` and ``histojax.compat``
are these very modules; ``histojax.wrappers`` re-exports the pure-JAX one). Every bridge takes its
spaces from the env and converts them with :mod:`histojax.spaces` (``to_gymnasium``, ``to_numpy``);
none declares a space of its own. Only :mod:`histojax.adapters.jax` is imported with histojax: the
others need their optional extras (``pip install 'histojax[gymnasium]'`` / ``'histojax[sb3]'``).
"""
