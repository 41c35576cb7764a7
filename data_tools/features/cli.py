"""``python -m data_tools features`` and ``import-features`` (wired into :mod:`data_tools.__main__`)."""

from __future__ import annotations

import time
from pathlib import Path

from data_tools.errors import HistojaxDataError
from data_tools.features import ENCODERS, encoder_record

COMMANDS = ("features", "import-features")


def add_subcommands(sub) -> None:
    """Add the two sub-commands to the ``data_tools`` argument parser."""
    f = sub.add_parser(
        "features",
        help="embed every view of a bundle's feature grid with a frozen encoder "
        "(or --check IMAGE: print the encoder's top-5 ImageNet classes)",
    )
    f.add_argument("bundle", nargs="?", help="bundle folder (features_KK.npy are added to it)")
    f.add_argument(
        "--check",
        metavar="IMAGE",
        help="self-check: classify an image file (or skimage:NAME, e.g. "
        "skimage:chelsea) and print the top-5 ImageNet labels",
    )
    f.add_argument(
        "--encoder",
        default="efficientnet-lite0",
        metavar="NAME|MODULE:FUNCTION",
        help=f"encoder: one of {', '.join(ENCODERS)} (default efficientnet-lite0; pcam-cnn: histojax's "
        "PCam-trained CNN, 64-d, for views at the C16 scale; colour-stats: 8 cheap colour statistics, "
        "no weights), or your own callable uint8 (N, H, W, 3) -> float32 (N, D) as module:function "
        "(its name / version attributes are recorded)",
    )
    f.add_argument("--dim", type=int, default=None, help="reduce the 1280-d embeddings to D dimensions")
    f.add_argument(
        "--projection",
        choices=("random", "pca"),
        default="random",
        help="with --dim: seeded Gaussian random projection (default) or PCA of this slide's embeddings",
    )
    f.add_argument("--seed", type=int, default=0, help="seed of the random projection (default 0)")
    f.add_argument("--stride", type=int, default=None, help="grid step in px of each level (default: the tile size)")
    f.add_argument("--batch", type=int, default=64, help="views per encoder call (default 64)")
    f.add_argument(
        "--image-size",
        type=int,
        default=224,
        help="encoder input size; views are resized to it (default 224, the training size; 0 = as is)",
    )
    f.add_argument("--dtype", choices=("float16", "float32"), default="float16", help="stored dtype (default float16)")
    f.add_argument(
        "--mpp",
        type=float,
        default=None,
        metavar="UM",
        help="the slide's µm per level-0 px, when the bundle records none or a wrong one (0.25 at 40x, 0.5 "
        "at 20x): recorded in the bundle (metadata source.mpp, each level's mpp) before the grid",
    )
    f.add_argument("--quiet", action="store_true", help="no progress bar")

    i = sub.add_parser(
        "import-features", help="map CLAM/TRIDENT patch features (HDF5: coords, features) onto a bundle's feature grid"
    )
    i.add_argument("bundle", help="bundle folder")
    i.add_argument("h5", help="HDF5 file with coords (N, 2) level-0 px top-left and features (N, D)")
    i.add_argument(
        "--patch-size",
        type=int,
        default=None,
        help="patch side in px of pyramid level L (default: the file's patch_size attribute)",
    )
    i.add_argument(
        "--patch-level",
        "--level",
        dest="level",
        type=int,
        default=None,
        help="pyramid level L the patches were cut at (default: the file's patch_level attribute, else 0; "
        "--level is the old spelling)",
    )
    i.add_argument(
        "--downsample",
        type=float,
        default=None,
        help="level-0 px per px of level L (default: the file's downsample attribute; 1 for L = 0)",
    )
    i.add_argument("--stride", type=int, default=None, help="grid step in px of each level (default: the tile size)")
    i.add_argument("--dtype", choices=("float16", "float32"), default="float16", help="stored dtype (default float16)")


def _read_image(spec: str):
    import numpy as np

    if spec.startswith("skimage:"):
        import skimage.data

        name = spec.split(":", 1)[1]
        if not hasattr(skimage.data, name):
            raise HistojaxDataError(None, f"skimage.data has no image {name!r}")
        return np.asarray(getattr(skimage.data, name)())
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(spec) as im:
            return np.asarray(im.convert("RGB"))
    except (OSError, UnidentifiedImageError) as e:
        raise HistojaxDataError(spec, f"not a readable image ({e})") from None


def run(args) -> None:
    """Run one of :data:`COMMANDS`; raises ``HistojaxDataError`` on bad input."""
    if args.command == "import-features":
        from data_tools.features.hdf5 import import_features

        info = import_features(
            args.bundle,
            args.h5,
            patch_size=args.patch_size,
            level=args.level,
            downsample=args.downsample,
            stride=args.stride,
            dtype=args.dtype,
        )
        print(
            f"imported {info['import']['n_patches']} patches × {info['dim']} features from {args.h5} "
            f"(patch {info['import']['extent_level0']:g} level-0 px) into {args.bundle}"
        )
        for k, lv in enumerate(info["levels"]):
            gh, gw = lv["grid"]
            print(f"  level {k}: grid {gh}×{gw}, {lv['covered']} of {gh * gw} views covered")
        return
    encoder_record(args.encoder)  # an unknown name, or your own encoder refused, before anything is read
    if args.check:
        from data_tools.features.efficientnet import classify, load_encoder

        encoder = load_encoder(args.encoder)
        for rank, (index, name, prob) in enumerate(classify(_read_image(args.check), encoder=encoder), 1):
            print(f"{rank}. {name} (class {index}) {prob:.3f}")
        return
    if not args.bundle:
        raise HistojaxDataError(None, "features needs a BUNDLE folder (or --check IMAGE)")
    from data_tools.features.grid import compute_features

    if args.mpp is not None:  # the scale the encoder-scale check and the bundle's readers then use
        from data_tools.bundle import set_mpp

        set_mpp(Path(args.bundle), args.mpp)

    start = time.perf_counter()
    info = compute_features(
        Path(args.bundle),
        encoder_name=args.encoder,
        dim=args.dim,
        projection=args.projection,
        seed=args.seed,
        stride=args.stride,
        batch=args.batch,
        image_size=args.image_size or None,
        dtype=args.dtype,
        progress=not args.quiet,
    )
    views = sum(lv["grid"][0] * lv["grid"][1] for lv in info["levels"])
    print(
        f"wrote the {info['encoder']} feature grid of {args.bundle}: {views} views, dim {info['dim']}, "
        f"stride {info['stride']} px, {len(info['levels'])} levels in {time.perf_counter() - start:.1f} s"
    )


__all__ = ["COMMANDS", "add_subcommands", "run"]
