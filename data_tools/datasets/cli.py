"""``histojax dataset SLIDES_DIR --out DIR`` (also ``python -m data_tools dataset``): a folder of real
slides becomes a dataset (see :mod:`data_tools.datasets.build`). Exit status 0 when every slide of
this run built, 1 when some failed (listed, one line each; the rest are in ``dataset.json``; a failed
rebuild keeps the previous bundle), 2 for a user error (one line: also a test split that failures left
without any slide or tumour slide, another tool's ``plan.json`` or a ``dataset.json`` histojax did not
write)."""

from __future__ import annotations

import json
from pathlib import Path

from data_tools.cli_output import finite_float, positive_int, seed_int


def add_subcommand(sub, levels_type) -> None:
    """The ``dataset`` parser on the data commands' subparsers ``sub``."""
    p = sub.add_parser(
        "dataset",
        help="a folder of real slides (SVS / TIFF / OME-TIFF / DICOM, CAMELYON16 as "
        "downloaded) with annotations and labels becomes a dataset: bundles, split, "
        "dataset.json; restartable, --jobs, --shard I/N",
    )
    p.add_argument("slides_dir", nargs="?", help="folder of slides, searched recursively (not needed with --merge)")
    p.add_argument(
        "--out", required=True, help="dataset folder (bundles/, records/, dataset.json); an unfinished one is resumed"
    )
    p.add_argument(
        "--labels",
        help="CSV of slide,label[,split] (header optional; labels 0/1 or Tumor/Normal; "
        "default: annotated → tumour, else normal; CAMELYON16: its folders and "
        "testing/reference.csv)",
    )
    p.add_argument(
        "--annotations",
        help="another folder of annotations (ASAP XML, GeoJSON, NCRF JSON) matched "
        "by slide name (default: those found among the slides)",
    )
    p.add_argument(
        "--allow-unmatched-annotations",
        action="store_true",
        help="ignore annotations naming no slide here (only part of a cohort downloaded)",
    )
    p.add_argument(
        "--levels", type=levels_type, action="extend", metavar="N", help="zoom level counts (as build; default 3,5,7)"
    )
    p.add_argument("--tile-size", type=positive_int, default=128, help="view size in px (default 128)")
    p.add_argument(
        "--magnification-range",
        type=finite_float,
        default=None,
        help="coarsest downsample for every slide (default: each slide's own; the slides must then share their µm/px)",
    )
    p.add_argument(
        "--mpp",
        type=float,
        default=None,
        metavar="UM",
        help="every slide's µm per level-0 px, for files that state none or a wrong one (0.25 at 40x, 0.5 "
        "at 20x; one scanner's slides); recorded in each bundle and dataset.json",
    )
    p.add_argument(
        "--storage",
        choices=("dense", "tiled", "auto"),
        default="auto",
        help="as build (default auto: tiled above 256 MiB, as gigapixel slides need)",
    )
    p.add_argument("--label-map", help="JSON object mapping annotation group to tumour/exclusion/tissue/ignore")
    feats = p.add_mutually_exclusive_group()
    feats.add_argument(
        "--encoder",
        default=None,
        help="embed every bundle's feature grid: pcam-cnn (what the "
        "HistoJAX-C16-*-v1 ids observe), colour-stats or "
        "efficientnet-lite0",
    )
    feats.add_argument(
        "--features-from",
        metavar="DIR",
        help="import CLAM / TRIDENT features: NAME.h5 (features (N, D), coords (N, 2) level-0 px) "
        "anywhere under DIR, matched by slide name",
    )
    p.add_argument(
        "--patch-size",
        type=positive_int,
        default=None,
        help="--features-from: patch side in px of --patch-level (default: the files' attributes)",
    )
    p.add_argument("--patch-level", type=int, default=None, help="--features-from: pyramid level of the patches")
    p.add_argument(
        "--no-pixels",
        action="store_true",
        help="feature-only bundles (as c16): delete the RGB pools of every level but the coarsest",
    )
    p.add_argument(
        "--test-fraction",
        type=float,
        default=0.25,
        help="share of each label in the seeded test split (default 0.25; ignored when the layout or "
        "the label table gives the split)",
    )
    p.add_argument("--seed", type=seed_int, default=0, help="seed of the split and the folds (default 0)")
    p.add_argument(
        "--folds",
        type=int,
        default=None,
        metavar="K",
        help="also write K cross-validation folds to dataset.json: stratified by label, seeded, the slides "
        "of one patient in one fold (a patient column in --labels, or TCGA barcodes); over every slide "
        "(fold i = test), or over the train side when the split is given (fold i = validation); "
        "make(..., fold=i), --fold i",
    )
    p.add_argument("--jobs", type=positive_int, default=1, help="slides built in parallel processes (default 1)")
    p.add_argument(
        "--shard",
        metavar="I/N",
        default=None,
        help="build only shard I of N (0 <= I < N; every N-th slide by sorted name), e.g. "
        "$SLURM_ARRAY_TASK_ID/$SLURM_ARRAY_TASK_COUNT; the last shard to finish writes dataset.json",
    )
    p.add_argument("--merge", action="store_true", help="only write dataset.json from the shards' records")
    p.add_argument(
        "--restart",
        action="store_true",
        help="accept new options or slides for an existing --out (finished slides with unchanged settings are kept)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    from data_tools.cli_output import add_reader_argument

    add_reader_argument(p)


def run(args) -> int:
    """Run the parsed ``dataset`` command; returns 0, or 1 when some slides failed (user errors raise)."""
    from data_tools.datasets.build import build_dataset, merge_dataset
    from data_tools.datasets.split import parse_shard
    from data_tools.errors import HistojaxDataError

    out = Path(args.out)
    if args.merge:
        dataset, missing, failed = merge_dataset(out)
        if dataset is None:
            raise HistojaxDataError(
                out,
                f"{len(missing)} slide(s) not built yet (e.g. {', '.join(missing[:4])}); run the missing shards first",
            )
        return _report(out, dataset, failed, {})
    if args.slides_dir is None:
        raise HistojaxDataError(None, "give the folder of slides (or --merge)")
    label_map = json.loads(args.label_map) if args.label_map else None
    if label_map is not None:
        from data_tools.annotations import check_label_map

        check_label_map(label_map)
    summary = build_dataset(
        args.slides_dir,
        out,
        labels=args.labels,
        annotations=args.annotations,
        levels=args.levels or (3, 5, 7),
        tile_size=args.tile_size,
        magnification_range=args.magnification_range,
        storage=args.storage,
        label_map=label_map,
        encoder=args.encoder,
        features_from=args.features_from,
        patch_size=args.patch_size,
        patch_level=args.patch_level,
        no_pixels=args.no_pixels,
        test_fraction=args.test_fraction,
        seed=args.seed,
        jobs=args.jobs,
        shard=parse_shard(args.shard) if args.shard is not None else None,
        restart=args.restart,
        allow_unmatched=args.allow_unmatched_annotations,
        progress=not args.quiet,
        reader=args.reader,
        folds=args.folds,
        mpp=args.mpp,
    )
    s = summary
    print(
        f"{'shard ' + '/'.join(map(str, s['shard'])) + ': ' if s['shard'] else ''}{len(s['built'])} built, "
        f"{len(s['resumed'])} already done, {len(s['failed'])} failed"
        + (f", {len(s['busy'])} being built by another process" if s["busy"] else "")
        + f" of {s['n_mine']} slides in {s['seconds']:.0f} s"
        + (
            f" ({s['slides_per_minute']:.2f} slides/min, peak {s['peak_rss_bytes_per_job'] / 2**20:.0f} MiB per job)"
            if s["slides_per_minute"]
            else ""
        )
    )
    if s["dataset"] is None:
        print(
            f"dataset.json not written yet: {len(s['missing'])} slide(s) of other shards or processes remain "
            "(the last shard writes it, or run with --merge)"
        )
        for name, reason in s["failed"].items():
            print(f"  failed {name}: {reason}")
        return 1 if s["failed"] else 0
    return _report(out, s["dataset"], s["failed_all"], s)


def _report(out: Path, dataset: dict, failed: dict, summary: dict) -> int:
    print(
        f"wrote {out / 'dataset.json'}: {len(dataset['train'])} train, {len(dataset['test'])} test slides "
        f"({sum(dataset['labels'].values())} tumour, "
        f"{len(dataset['labels']) - sum(dataset['labels'].values())} normal)"
        + (f"; {len(failed)} failed and left out:" if failed else "")
    )
    for name, reason in failed.items():
        print(f"  failed {name}: {reason}")
    kept = dataset.get("kept_after_failed_rebuild") or {}
    for name, reason in kept.items():
        print(f"  rebuild of {name} failed, its previous bundle is kept: {reason}")
    if "one patient on one side" in str(dataset.get("split_rule")):  # patients of several slides kept together
        print(f"split by patient ({dataset.get('split_grouped_by')}): no patient in both train and test")
    folds = dataset.get("folds")
    if folds:
        print(
            f"{folds['k']} folds over the {'slides' if folds['pool'] == 'all' else 'train side'}: "
            + ", ".join(str(len(lst)) for lst in folds["lists"])
            + " slides ("
            + folds["grouped_by"]
            + ")"
        )
    labels = {Path(str(k)).name: v for k, v in (dataset.get("labels") or {}).items()}
    for line in one_class_fold_lines(dataset, labels, failed):
        print(line)
    for side in ("train", "test"):
        classes = {labels.get(Path(str(e)).name) for e in dataset[side]} - {None}
        if dataset[side] and len(classes) == 1:
            print(
                f"note: the {side} split holds only {'tumour' if classes.pop() else 'normal'} slides "
                f"({len(dataset[side])}" + ("; others failed" if failed else "") + "): its AUC is undefined, and "
                "anything that scores AUC on it refuses it; give more slides, --test-fraction or a split column"
            )
        if not dataset[side]:
            print(
                f"note: the {side} split is empty (split rule: {dataset.get('split_rule')}"
                + (f"; {len(failed)} slide(s) failed to build and were left out" if failed else "")
                + "): no policy can be "
                + ("trained" if side == "train" else "scored")
                + " on it; give more slides, --test-fraction or a "
                "split column"
            )
    for line in small_split_lines(dataset, labels):
        print(line)
    return 1 if failed or kept else 0


def one_class_fold_lines(dataset: dict, labels: dict, failed: dict) -> list[str]:
    """A warning line for each fold of ``dataset.json`` whose slides (those built) hold one class or none: its
    held-out AUC is undefined and every command scoring it refuses it. Names the fold, its counts and, when slides
    failed, that they are why (the folds were dealt before the build, with every class in every fold)."""
    lines = []
    for i, lst in enumerate((dataset.get("folds") or {}).get("lists") or []):
        got = [labels.get(Path(str(e)).name) for e in lst]
        n_t, n_n = sum(v == 1 for v in got), sum(v == 0 for v in got)
        if n_t and n_n:
            continue
        lines.append(
            f"warning: fold {i} holds {n_t} tumour and {n_n} normal slides"
            + (f" after {len(failed)} failed slide(s) were left out" if failed else "")
            + f": its AUC is undefined and --fold {i} / --all-folds refuse it; "
            + (
                "rebuild the failed slides (or drop them from the label table and build again with --restart) so "
                "every fold holds both classes"
                if failed
                else "give fewer --folds or more slides of each class"
            )
        )
    return lines


def small_split_lines(dataset: dict, labels: dict) -> list[str]:
    """The small-split warnings of a written ``dataset.json`` (:func:`data_tools.metrics.small_split_warning`): one
    line for the test split and one for the folds (their smallest held-out fold), when either class there has too
    few slides to rank heads or readers; a one-class or empty split has its own note above."""
    from data_tools.metrics import small_split_warning

    def counts(entries) -> tuple[int, int]:
        y = [labels.get(Path(str(e)).name) for e in entries]
        return sum(v == 1 for v in y), sum(v == 0 for v in y)

    out = []
    tumour, normal = counts(dataset.get("test") or [])
    if tumour and normal and (w := small_split_warning(tumour, normal, "the test split")):
        out.append(w)
    folds = dataset.get("folds") or {}
    if folds.get("lists"):
        sizes = [counts(lst) for lst in folds["lists"]]
        i = min(range(len(sizes)), key=lambda k: min(sizes[k]))
        if min(sizes[i]) and (
            w := small_split_warning(*sizes[i], f"fold {i}, the smallest of the {folds['k']} folds,")
        ):
            out.append(
                w.replace(
                    "Use k folds (dataset --folds K, then --all-folds)",
                    "Report the mean over folds (--all-folds) with the interval of the pooled slides",
                )
            )
    return out


__all__ = ["add_subcommand", "run"]
