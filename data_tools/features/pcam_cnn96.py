"""``pcam-cnn96``: the ``pcam-cnn`` family (:mod:`data_tools.features.pcam_cnn`) at PCam's native scale,
0.972 µm/px (CAMELYON16 level 0 / 4): a PCam patch is read at its distributed 96 px, an env view of 128 px
covers 124 µm. Weights shipped beside this file (``pcam_cnn96.msgpack``, report ``pcam_cnn96.json``).

Model card: docs/encoder-pcam-cnn96.md. Training command: ``python -m data_tools train-encoder --arch
pcam-cnn96`` (:mod:`data_tools.features.train_pcam_cnn`, the same machinery as ``pcam-cnn``).

Input: RGB uint8 ``(B, H, W, 3)``, any size ≥ 32 px, at 0.972 µm/px; preprocessing as ``pcam-cnn``.
Architecture: ``LAYERS`` (each conv followed by BatchNorm and ReLU): a 4×4 convolution of stride 4 (24
channels), a 3×3 of stride 2 (48), a 3×3 (64), a 3×3 of stride 2 (96), a 3×3 (96) and a 1×1 (64): one cell per
16 × 16 input px (15.6 µm, the physical cell of ``pcam-cnn``), receptive field 76 px (74 µm); then the same
heads and pooling: ``embed`` → float32 ``(B, 64)`` = ``[mean f (31), max f (31), mean l, max l]``, ``logits`` →
float32 ``(B,)`` = ``mean l``.
"""

from __future__ import annotations

from pathlib import Path

from data_tools.features import pcam_cnn

NAME = "pcam-cnn96"
LAYERS = ((24, 4, 4), (48, 3, 2), (64, 3, 1), (96, 3, 2), (96, 3, 1), (64, 1, 1))
SCALE_MPP = 0.972  # µm per input px (PCam's own scale; CAMELYON16 level 0 / 4)
PATCH_PX = 96  # a PCam patch as distributed
DIM = pcam_cnn.DIM
WEIGHTS = Path(__file__).with_name("pcam_cnn96.msgpack")
ARCH = pcam_cnn.Arch(NAME, LAYERS, SCALE_MPP, PATCH_PX, WEIGHTS)
pcam_cnn.ARCHS[NAME] = ARCH

__all__ = ["ARCH", "DIM", "LAYERS", "NAME", "PATCH_PX", "SCALE_MPP", "WEIGHTS"]
