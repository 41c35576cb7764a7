"""The data_tools command line: ``python -m data_tools info SLIDE`` and
``python -m data_tools build SLIDE [--annotations FILE] --out DIR [--levels 3 5 7] [--tile-size 128]
[--region x0,y0,x1,y1 | --region-group NAME] [--region-margin PX] [--storage dense|tiled|auto]``, and
``python -m data_tools synth-large OUT.tif [--size 100000] [--tissue-fraction 0.1]`` (a gigapixel test slide), and
``python -m data_tools c16 --out DIR [--annotations NCRF.tar.gz] [--patches PCAM.tar.gz] [--small]`` (the true-scale
CAMELYON16 benchmark), and ``python -m data_tools dataset SLIDES_DIR --out DIR [--labels CSV] [--jobs N]
[--shard I/N]`` (a folder of real slides becomes a dataset; see docs/your-own-slides.md).

User errors (bad files, existing output) print one line and exit with status 2, no traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from data_tools.cli_output import (
    add_reader_argument,
    finite_float,
    one_line_messages,
    os_error_text,
    positive_float,
    positive_int,
    print_error,
    run_command,
)
from data_tools.errors import HistojaxDataError


def _levels(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: zoom level counts are integers, e.g. 3,5,7") from None
    if any(v < 2 for v in values):
        raise argparse.ArgumentTypeError("zoom level counts must be at least 2")
    return values


def _box(text: str) -> tuple[float, float, float, float]:
    try:
        values = tuple(finite_float(v) for v in text.replace(",", " ").split())
    except argparse.ArgumentTypeError:
        values = ()
    if len(values) != 4:
        raise argparse.ArgumentTypeError("a region is four numbers x0,y0,x1,y1 (level-0 px)")
    return values


def add_arguments(p) -> None:
    """The data commands and their options, on ``p``: ``python -m data_tools <command>`` and
    ``histojax <command>`` (one declaration for both)."""
    sub = p.add_subparsers(dest="command", required=True)
    info = sub.add_parser("info", help="print a slide's pyramid (levels, sizes in px, tiles, compression, µm/px)")
    info.add_argument(
        "slide",
        help="SVS / pyramidal TIFF / OME-TIFF file, DICOM WSI file or folder, MIRAX / SCN / "
        "BIF / VMS / SVSlide / Philips TIFF (OpenSlide), or a bundle folder",
    )
    add_reader_argument(info)
    build = sub.add_parser("build", help="write a slide bundle (levels, tumour masks, tissue mask, metadata)")
    build.add_argument(
        "slide",
        help="SVS / pyramidal TIFF / OME-TIFF file, or DICOM WSI file or folder "
        "(needs the extra: pip install 'histojax[dicom]')",
    )
    build.add_argument("--annotations", help="ASAP XML or QuPath GeoJSON in level-0 px (default: no tumour)")
    build.add_argument("--out", required=True, help="bundle folder to create (written atomically)")
    build.add_argument(
        "--levels",
        type=_levels,
        action="extend",
        metavar="N",
        help="zoom level counts to support (repeatable, or comma-separated): 3 (Easy), 5 (Medium), 7 (Hard); default 3,5,7",
    )
    build.add_argument("--tile-size", type=positive_int, default=128, help="view size in px (default 128)")
    build.add_argument(
        "--magnification-range",
        type=finite_float,
        default=None,
        help="coarsest downsample R (default: largest power of 2 with the slide's shorter side still >= one view)",
    )
    build.add_argument(
        "--label-map",
        help="JSON object mapping annotation group to tumour/exclusion/tissue/ignore, "
        'e.g. \'{"Tumor": "tumour", "_2": "exclusion"}\'',
    )
    where = build.add_mutually_exclusive_group()
    where.add_argument(
        "--region", type=_box, metavar="x0,y0,x1,y1", help="build only this rectangle of the slide (level-0 px)"
    )
    where.add_argument(
        "--region-group",
        metavar="NAME",
        help="build only the bounding box of an annotation group/label, e.g. tissue or tumour",
    )
    build.add_argument(
        "--region-margin",
        type=finite_float,
        default=0.0,
        metavar="PX",
        help="grow the region by this many level-0 px on every side (default 0)",
    )
    build.add_argument(
        "--storage",
        choices=("dense", "tiled", "auto"),
        default="dense",
        help="dense level arrays (default), tiled pools with background tiles shared (gigapixel "
        "slides; built streaming with bounded memory), or auto (tiled above 256 MiB)",
    )
    build.add_argument(
        "--keep-all-tiles", action="store_true", help="tiled: keep every tile (no shared blank background tile)"
    )
    build.add_argument(
        "--band-mb",
        type=positive_float,
        default=None,
        help="tiled: MiB of RGB per band of a level read at a time (default 96)",
    )
    build.add_argument("--overwrite", action="store_true", help="replace an existing bundle")
    build.add_argument(
        "--mpp",
        type=positive_float,
        default=None,
        metavar="UM",
        help="the slide's µm per level-0 px, when its file states none or a wrong one (0.25 at 40x, "
        "0.5 at 20x); recorded in the bundle",
    )
    build.add_argument(
        "--encoder",
        default=None,
        metavar="NAME",
        help="also embed the bundle's feature grid with this encoder (pcam-cnn, colour-stats, "
        "efficientnet-lite0, or module:function): one command instead of build + features",
    )
    build.add_argument(
        "--features",
        action="store_true",
        help="also embed the feature grid with pcam-cnn (the default encoder, as c16 --features)",
    )
    add_reader_argument(build)
    build.add_argument("--quiet", action="store_true", help="no progress bar and no level table: one line")
    synth = sub.add_parser(
        "synth",
        help="make semi-synthetic slides (synthetic pixels, real CAMELYON16 "
        "tumour geometry) and their bundles, with a train/test split",
    )
    synth.add_argument("out_dir", help="output folder (slides/, bundles/, previews/, dataset.json)")
    synth.add_argument("--slides", type=positive_int, default=8, help="number of slides (default 8)")
    synth.add_argument("--size", type=positive_int, default=4096, help="canvas side in level-0 px (default 4096)")
    synth.add_argument("--seed", type=int, default=0)
    synth.add_argument(
        "--negatives",
        type=int,
        default=0,
        help="that many more slides without tumour (label 0, for diagnosis; default 0)",
    )
    synth.add_argument(
        "--tile-size", type=positive_int, default=128, help="view size in px of the bundles (default 128)"
    )
    synth.add_argument(
        "--tissue",
        choices=("synthetic", "camelyon16"),
        default="synthetic",
        help="tissue region: a random blob around the tumour (default) or a CAMELYON16 tissue outline of another slide",
    )
    synth.add_argument(
        "--tumour-xml",
        nargs="+",
        default=None,
        metavar="XML",
        help="ASAP XML tumour annotations to place (default: the bundled CAMELYON16 files)",
    )
    synth.add_argument("--quiet", action="store_true", help="no progress bar")
    large = sub.add_parser(
        "synth-large",
        help="write a gigapixel semi-synthetic pyramidal TIFF (mostly glass; real "
        "CAMELYON16 tissue and tumour outlines, synthetic pixels), tile by tile",
    )
    large.add_argument("out", help="output .tif (a .geojson with tumour and tissue is written beside it)")
    large.add_argument("--size", type=positive_int, default=100_000, help="canvas side in level-0 px (default 100000)")
    large.add_argument(
        "--tissue-fraction",
        type=positive_float,
        default=0.1,
        help="approximate fraction of the canvas covered by tissue (default 0.1)",
    )
    large.add_argument("--seed", type=int, default=0)
    large.add_argument("--quiet", action="store_true", help="no progress bar")
    c16 = sub.add_parser(
        "c16",
        help="make the true-scale CAMELYON16 benchmark: real CAMELYON16 geometry, real PCam "
        "patches arranged by us (not scanned slides); slides, tiled bundles, dataset.json",
    )
    c16.add_argument(
        "--out", required=True, help="dataset folder (slides/, bundles/, dataset.json); an unfinished one is resumed"
    )
    c16.add_argument(
        "--annotations",
        default=None,
        help="folder or .tar.gz of NCRF JSON files (camelyon16_ncrf_train.tar.gz; default: the 6 shipped)",
    )
    c16.add_argument(
        "--patches",
        default=None,
        help="PCam patches: folder with 0/ and 1/, its .tar.gz, or a bank "
        ".npz (default: the shipped 1,000-patch bank); cut by a fixed "
        "rule into a training pool (train slides) and a test pool "
        "(test slides), no patch on both sides",
    )
    c16.add_argument(
        "--test-patches",
        default=None,
        metavar="DIR|TAR",
        help="texture the test slides from this other patch set entirely (e.g. PCam's own valid or "
        "test patches, folder with 0/ and 1/ or its .tar.gz): pixels nothing was trained on",
    )
    c16.add_argument(
        "--small", action="store_true", help="the small variant: 3 tumour + 3 normal slides at downsample 32 (seconds)"
    )
    c16.add_argument(
        "--downsample",
        type=float,
        default=None,
        help="CAMELYON16 level-0 px per output px for the whole set (default 8; --small 32)",
    )
    c16.add_argument("--slides", nargs="+", default=None, metavar="NAME", help="only these slides (e.g. Tumor_001)")
    c16.add_argument("--tumour-slides", type=int, default=None, metavar="N", help="only the first N tumour slides")
    c16.add_argument("--normal-slides", type=int, default=None, metavar="N", help="only the first N normal slides")
    c16.add_argument("--test-fraction", type=float, default=0.25, help="share of slides in the test split (0.25)")
    c16.add_argument(
        "--features",
        action="store_true",
        help="also embed every bundle's feature grid with pcam-cnn (the default encoder)",
    )
    c16.add_argument(
        "--encoder",
        default=None,
        metavar="NAME",
        help="embed every bundle's feature grid with this encoder (pcam-cnn, the default; colour-stats; "
        "efficientnet-lite0, slow on CPU; implies --features)",
    )
    c16.add_argument(
        "--no-pixels",
        action="store_true",
        help="feature-only bundles: after the feature grid, delete the RGB tile pools of every level "
        "but the coarsest (obs_mode='features' only; ~1/10 of the disk; the TIFFs stay)",
    )
    c16.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="slides made in parallel processes (default 1; median 1.4 GB, at most 2.9 GB of memory each, measured at the "
        "full set's scale)",
    )
    c16.add_argument(
        "--shard",
        default=None,
        metavar="I/N",
        help="make only shard I of N (0-based; every N-th chosen slide by name): N jobs of an array "
        "sharing --out build disjoint slides; the last to finish writes dataset.json",
    )
    c16.add_argument(
        "--merge",
        action="store_true",
        help="make nothing: write dataset.json from the slides recorded so far (after a job array)",
    )
    c16.add_argument("--seed", type=int, default=0)
    c16.add_argument(
        "--folds",
        type=int,
        default=None,
        metavar="K",
        help="also write K cross-validation folds of the train slides to dataset.json (stratified by "
        "label, a tumour slide with its tissue donor; fold i = validation): make(..., fold=i)",
    )
    c16.add_argument("--quiet", action="store_true", help="no progress bars")
    from data_tools.datasets.cli import add_subcommand as _add_dataset_command
    from data_tools.features.cli import add_subcommands as _add_feature_commands
    from data_tools.features.train_pcam_cnn import add_arguments as _train_encoder_arguments

    _add_dataset_command(sub, _levels)  # dataset

    _add_feature_commands(sub)  # features, import-features
    _train_encoder_arguments(
        sub.add_parser(
            "train-encoder",
            help="train the pcam-cnn encoder (or --arch pcam-cnn96, at 96 px) on the PCam training pool "
            "(minutes on 2 CPU cores; about an hour for pcam-cnn96)",
        )
    )


def _info(path: str, reader: str = "auto") -> str:
    from data_tools.slide_files.dicom import is_dicom

    if Path(path).is_dir() and not is_dicom(path):
        from data_tools.bundle_files.reading import read_metadata

        meta = read_metadata(path)
        lines = [
            f"bundle {path}: format v{meta.format_version} ({meta.storage}), "
            f"source {meta.source['file']}, "
            f"tile {meta.tile_size} px, magnification range {meta.magnification_range:g}, "
            f"level sets {meta.level_sets}"
        ]
        for k, lv in enumerate(meta.levels):
            lines.append(
                f"  level {k}: {lv.width}×{lv.height} px, downsample {lv.downsample:.4g}, "
                f"tumour {lv['tumour_pixels']} px, "
                f"{lv.device_bytes / 2**20:.1f} MiB on the device"
                + (
                    f" ({lv['pool_tiles']:,} pool tiles for a {lv['grid'][0]}×{lv['grid'][1]} grid, "
                    f"{lv['sat_pool_tiles']:,} SAT tiles; dense would be "
                    f"{lv['dense_device_bytes'] / 2**20:.1f} MiB)"
                    if lv.is_tiled
                    else ""
                )
            )
        return "\n".join(lines)
    from data_tools.slide_files.base import describe
    from data_tools.slide_files.open import open_slide

    with open_slide(path, reader) as slide:
        return describe(slide)


def run(args, parser=None) -> int:
    """Run the parsed data command; returns the exit status (2 for a user error, printed as one line;
    1 when ``dataset`` or ``c16`` built the cohort but some slides failed)."""
    try:
        if args.command == "dataset":
            from data_tools.datasets.cli import run as _run_dataset

            return _run_dataset(args)
        return _command(args) or 0
    except HistojaxDataError as e:
        return print_error(e)
    except json.JSONDecodeError as e:
        return print_error(f"--label-map is not valid JSON: {e}")
    except OSError as e:  # file-system errors outside the project's checks (permissions, full disk, ...)
        where = getattr(args, "out", None) or getattr(args, "out_dir", None)
        if e.filename is None and where:  # e.g. a full disk inside a library's write: name the output at least
            return print_error(f"{where}: {e.strerror or e} (while writing under it)")
        return print_error(os_error_text(e))
    return 0


def main(argv=None, prog: str = "python -m data_tools") -> int:
    """Entry point; returns the process exit status (2 for a user error, printed as one line)."""
    with one_line_messages():
        return run_command(add_arguments, run, argv, prog=prog, doc=__doc__)


def _command(args) -> int | None:
    """Run the parsed command; an exit status when it is not 0 (``c16`` with failed slides: 1)."""
    if args.command == "info":
        print(_info(args.slide, args.reader))
    elif args.command == "build":
        from data_tools.bundle import LEVEL_SETS, build_bundle
        from data_tools.bundle_files.reading import read_metadata

        label_map = json.loads(args.label_map) if args.label_map else None
        if label_map is not None:
            from data_tools.annotations import check_label_map

            check_label_map(label_map)
        encoder = args.encoder or ("pcam-cnn" if args.features else None)
        if encoder is not None:
            from data_tools.features import encoder_record

            encoder_record(encoder)  # an unknown or broken encoder refused before the build
        out = build_bundle(
            args.slide,
            args.out,
            annotations_path=args.annotations,
            level_sets=args.levels or LEVEL_SETS,
            tile_size=args.tile_size,
            magnification_range=args.magnification_range,
            label_map=label_map,
            overwrite=args.overwrite,
            progress=not args.quiet,
            region=args.region if args.region is not None else args.region_group,
            region_margin=args.region_margin,
            storage=args.storage,
            share_background=not args.keep_all_tiles,
            band_bytes=None if args.band_mb is None else int(args.band_mb * 2**20),
            reader=args.reader,
            mpp=args.mpp,
        )
        if encoder is not None:
            from data_tools.features.grid import compute_features

            compute_features(out, encoder_name=encoder, progress=not args.quiet)
        meta = read_metadata(out)
        print(
            f"wrote {out}: {len(meta.levels)} levels"
            + (f", region {meta.region['box']} of the slide" if meta.region else "")
            + (f", {meta.source['mpp']:.4g} µm/px (given)" if args.mpp is not None else "")
            + (f", {meta.features['encoder']} feature grid" if encoder is not None else "")
        )
        if not args.quiet:  # --quiet: the one line above (`info BUNDLE` prints the level table)
            print(_info(str(out)))
    elif args.command == "synth":
        from data_tools.datasets.synth.dataset import make_dataset

        ds = make_dataset(
            args.out_dir,
            n_slides=args.slides,
            size=(args.size, args.size),
            seed=args.seed,
            tile_size=args.tile_size,
            tissue=args.tissue,
            progress=not args.quiet,
            tumour_xmls=args.tumour_xml,
            negatives=args.negatives,
        )
        print(
            f"wrote {Path(args.out_dir) / 'dataset.json'}: {len(ds['train'])} train, {len(ds['test'])} test "
            f"bundles in {ds['seconds']:.0f} s (pixels synthetic, geometry real CAMELYON16)"
        )
        for s in ds["slides"]:
            print(
                f"  {s['name']}: tumour {100 * s['tumour_fraction']:.1f} % of the canvas, "
                f"{s['finest_views_ge50']}/{s['finest_views']} finest views >= 50 % tumour, "
                f"mean RGB tumour {s['tumour_mean_rgb']} vs normal {s['normal_tissue_mean_rgb']}"
            )
    elif args.command == "c16":
        from data_tools.datasets.c16.dataset import make_c16_dataset
        from data_tools.datasets.split import parse_shard

        ds = make_c16_dataset(
            args.out,
            annotations=args.annotations,
            patches=args.patches,
            small=args.small,
            downsample=args.downsample,
            names=args.slides,
            n_tumour=args.tumour_slides,
            n_normal=args.normal_slides,
            seed=args.seed,
            test_fraction=args.test_fraction,
            features=args.encoder or args.features,
            progress=not args.quiet,
            workers=args.jobs,
            no_pixels=args.no_pixels,
            test_patches=args.test_patches,
            shard=parse_shard(args.shard) if args.shard is not None else None,
            merge=args.merge,
            folds=args.folds,
        )
        for name, reason in sorted(ds["failed"].items()):
            print(f"FAILED {name}: {reason}", file=sys.stderr)
        if ds["missing"]:
            print(
                f"{len(ds['run']['built'])} slides built this run; {len(ds['missing'])} still to make by other "
                f"shards or runs ({', '.join(ds['missing'][:4])}{', ...' if len(ds['missing']) > 4 else ''}): "
                "dataset.json is written by the last of them, or by `c16 ... --merge` with the same options"
            )
            return 1 if ds["failed"] else 0
        sc = ds["scale"]
        print(
            f"wrote {Path(args.out) / 'dataset.json'}: {len(ds['train'])} train, {len(ds['test'])} test slides "
            f"at {sc['mpp']:.3g} um/px (CAMELYON16 level 0 / {sc['downsample_from_camelyon16_level0']:g}); "
            f"geometry real CAMELYON16, pixels real PCam patches arranged by histojax (not scanned slides); "
            f"{ds['seconds_this_run']:.0f} s this run"
            + (f"; {len(ds['failed'])} slide(s) FAILED" if ds["failed"] else "")
        )
        if ds["failed"]:
            return 1
    elif args.command == "synth-large":
        from data_tools.datasets.synth.large_slide import make_large_slide

        prov = make_large_slide(
            args.out, size=args.size, tissue_fraction=args.tissue_fraction, seed=args.seed, progress=not args.quiet
        )
        print(
            f"wrote {args.out}: {args.size}×{args.size} px, {prov['tiff_bytes'] / 2**20:.1f} MiB, "
            f"tissue {100 * prov['tissue_fraction']:.1f} %, tumour {100 * prov['tumour_fraction']:.2f} % "
            f"of the canvas, in {prov['seconds']:.0f} s (pixels synthetic, geometry real CAMELYON16)"
        )
    elif args.command == "train-encoder":
        from data_tools.features.train_pcam_cnn import run as _train_encoder

        _train_encoder(args)
    elif args.command in ("features", "import-features"):
        from data_tools.features.cli import run as _run_feature_command

        _run_feature_command(args)


if __name__ == "__main__":
    sys.exit(main())
