"""Adapters: the histojax environment for each audience, one module each.

=====================================  ==========================================
audience                               module
=====================================  ==========================================
gymnax, PureJaxRL, rejax (pure JAX)    :mod:`histojax.adapters.jax` —
                                       ``LogWrapper``, ``GymnaxV0Wrapper``,
                                       ``Wrapper``
Gymnasium (numpy; Tianshou, ...)       :mod:`histojax.adapters.gymnasium` —
                                       ``GymnasiumEnv``, ``GymnasiumVectorEnv``,
                                       ``gymnasium.make("histojax/<id>")``
Stable-Baselines3                      :mod:`histojax.adapters.sb3` —
                                       ``SB3VecEnv``, ``make_sb3_vec_env``
HistoGym code (gym 0.21 API)           :mod:`histojax.adapters.histogym` —
                                       ``HistoEnv(img_path, xml_path, ...)``
=====================================  ==========================================

Each name has one import path, the module above. Every bridge takes its
spaces from the env and converts them with :mod:`histojax.core.spaces` (``to_gymnasium``, ``to_numpy``);
none declares a space of its own. Only :mod:`histojax.adapters.jax` is imported with histojax: the
others need their optional extras (``pip install 'histojax[gymnasium]'`` / ``'histojax[sb3]'``).
"""
