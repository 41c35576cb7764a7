"""Which slides ``make`` loads: dataset folders, their splits and folds, slide labels, and the C16 ids' default
dataset.

A dataset folder (built by ``python -m data_tools synth``, ``histojax dataset`` or ``histojax c16``) holds a sealed
``dataset.json`` with its ``"train"`` / ``"test"`` lists of bundles, optionally ``"labels"`` and ``"folds"``
(:func:`dataset_slides`, :func:`with_fold`, :func:`fold_slides`, :func:`dataset_labels`); :func:`check_dataset`
refuses one older than an id needs, naming the command that rebuilds it; :func:`resolve_slides` turns ``make``'s
``slide`` / ``slides`` / ``dataset`` / ``split`` / ``fold`` into the bundle paths it loads. ``make`` and the
registration of ids are :mod:`histojax.registry`'s; this module does not import it.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from data_tools.datasets.index import read_dataset_json
from data_tools.errors import BundleError

C16_DATASET_VARIABLE = "HISTOJAX_C16_DATASET"


def c16_dataset(spec: dict) -> Path:
    """The default dataset of the C16 ids: ``$HISTOJAX_C16_DATASET``, else ``cache_dir()/c16``; a clear
    error naming the command when neither holds a ``dataset.json``."""
    import os

    from histojax.sample import cache_dir

    given = os.environ.get(C16_DATASET_VARIABLE)
    folder = Path(given) if given else cache_dir() / "c16"
    if not (folder / "dataset.json").is_file():
        embed = spec.get("dataset_encoder") is not None  # the -v1 ids observe pcam-cnn features: build them too
        raise BundleError(
            folder,
            "no C16 dataset here (no dataset.json): the HistoJAX-C16-* ids need one. Make the "
            f"small one with `python -m data_tools c16 --small{' --features' * embed} --out DIR` "
            f"({'a minute' if embed else 'seconds'}) or the full one with "
            "`python -m data_tools c16 --annotations camelyon16_ncrf_train.tar.gz --patches "
            f"pcam_train_patches.tar.gz{' --no-pixels' * embed} --out DIR`, then pass make(id, dataset=DIR) "
            f"or set {C16_DATASET_VARIABLE}=DIR",
        )
    return folder


def _c16_rebuild_command(folder, ds: dict) -> str:
    """The ``data_tools c16`` command that rebuilds ``folder`` with the options its ``dataset.json`` records
    (``--small`` or the sources and scale, split seed, held-out patches, subset, pixels or not), with features."""
    import shlex

    opts = (
        ["--small"]
        if ds.get("variant") == "small"
        else [
            "--annotations",
            str(ds.get("annotations")),
            "--patches",
            str(ds.get("patches")),
            "--downsample",
            str((ds.get("scale") or {}).get("downsample_from_camelyon16_level0", 8.0)),
        ]
    )
    test = (ds.get("patch_pools") or {}).get("test") or {}
    opts += ["--test-patches", str(test.get("source"))] if test.get("other_patch_set") else []
    opts += ["--slides", *sorted(ds.get("labels") or {})] if ds.get("variant") == "subset" else []
    opts += ["--seed", str(ds["seed"])] if ds.get("seed", 0) != 0 else []
    opts += ["--test-fraction", str(ds["test_fraction"])] if ds.get("test_fraction", 0.25) != 0.25 else []
    opts += ["--features"] if ds.get("pixels_kept", True) else ["--no-pixels"]
    return shlex.join(["python", "-m", "data_tools", "c16", "--out", str(folder), *opts])


def check_dataset(folder, spec: dict, env_id: str) -> None:
    """Refuse a dataset older than the id needs (``dataset_format`` / ``dataset_encoder`` of its spec), naming
    the dataset, what it lacks, and the command that rebuilds it. The format (disjoint patch pools) concerns
    the ``c16`` mosaics only; a cohort of scanned slides (``histojax dataset``) needs only the encoder."""
    want_format, want_encoder = spec.get("dataset_format"), spec.get("dataset_encoder")
    if want_format is None and want_encoder is None:
        return
    index = Path(folder) / "dataset.json"
    try:
        ds = read_dataset_json(folder)  # its seal checked (an edited dataset.json refused)
    except (OSError, json.JSONDecodeError):
        return  # dataset_slides reports a missing or malformed index
    mosaic = str(ds.get("kind", "")).startswith("histojax true-scale CAMELYON16")
    if mosaic:
        fix = (
            f"rebuild it with `{_c16_rebuild_command(folder, ds)}` (its recorded options; the encoder is "
            f"pcam-cnn by default), or use the -v0 id"
        )
    else:  # a cohort of scanned slides (`histojax dataset`): no patch pools to share, only the encoder matters
        fix = (
            f"rebuild it with `histojax dataset SLIDES_DIR --out {folder} --encoder {want_encoder} ...` (same "
            f"options), or use the -v0 id"
        )
    if want_format is not None and mosaic and int(ds.get("format", 1)) < want_format:
        raise BundleError(
            index,
            f"{env_id} needs a dataset of format >= {want_format} (train and test slides "
            f"textured from disjoint PCam patch pools); this one is format {ds.get('format', 1)}: {fix}",
        )
    # any recorded encoder's grids (pcam-cnn by default; your own with --encoder module:function), not none
    if want_encoder is not None and spec.get("obs_mode", "pixels") == "features" and not ds.get("encoder"):
        raise BundleError(
            index,
            f"{env_id} observes {want_encoder} features, and this dataset records no feature "
            f"grids (built without --features): {fix}",
        )


def tumour_slide_weights(arrays: list, paths: list, weights=None) -> list[float] | None:
    """``weights`` (default uniform) with the slides that have no tumour annotated set to 0; ``None``
    for one slide with tumour; ``ValueError`` when no slide has tumour."""
    has_tumour = [int(a.slide_label) == 1 for a in arrays]
    if not any(has_tumour):
        raise ValueError(
            f"detection needs a slide with tumour annotated; none of the {len(paths)} slides has any "
            f"({', '.join(Path(p).name for p in paths[:4])}{', ...' if len(paths) > 4 else ''})"
        )
    if len(arrays) == 1:
        return weights
    base = [1.0] * len(arrays) if weights is None else [float(w) for w in weights]
    return [w if t else 0.0 for w, t in zip(base, has_tumour)]


def resolve_slides(
    env_id: str, registered, spec: dict, slide, slides, dataset, split: str, fold: int | None = None
) -> list:
    """``slides`` / ``dataset`` / ``slide`` / the id's registered slide or dataset (``registered``: the
    ``slide`` of its :class:`histojax.registry.EnvSpec`, a path, a list or a recipe) / the sample slide, as a
    non-empty list of bundle paths. ``spec``: the id's settings as ``make`` resolved them; ``env_id`` names it in
    refusals."""
    if dataset is None and slide is None and slides is None and registered is c16_dataset:
        dataset = c16_dataset(spec)
    if fold is not None and dataset is None:
        raise ValueError(
            f"fold={fold!r} picks a fold of a dataset built with --folds K: give dataset=DIR (or an id "
            "whose slides are a dataset)"
        )
    if dataset is not None:
        check_dataset(dataset, spec, env_id)
        slides = dataset_slides(dataset, split, fold)
    if slides is not None and slide is not None:
        raise ValueError("give either slide= or slides=/dataset=, not both")
    if slides is None:
        if slide is None and registered is not None:
            recipe = registered
            slide = recipe({**spec, "split": split}) if callable(recipe) else recipe
        if isinstance(slide, (list, tuple)):  # a registered dataset (e.g. a multi-slide scenario)
            slides, slide = list(slide), None
    if slides is None:
        if slide is None:
            from histojax.sample import sample_bundle

            slide = sample_bundle(tile_size=spec.get("tile_size", 128))
        slides = [slide]
    if not slides:
        raise ValueError("slides= is empty")
    return list(slides)


def dataset_slides(folder, split: str = "train", fold: int | None = None) -> list[Path]:
    """Bundle paths of ``split`` (``"train"``, ``"test"`` or ``"all"``) in ``FOLDER/dataset.json``.

    ``fold=i`` (a dataset built with ``--folds K``, :func:`fold_slides`): ``"train"`` is every fold but ``i``,
    ``"validation"`` is fold ``i``, and so is ``"test"`` where the folds cover every slide (k-fold cross
    validation); where they cut the train side of a fixed test set, ``"test"`` with a fold is refused."""
    folder = Path(folder)
    index = folder / "dataset.json"
    try:
        spec = read_dataset_json(folder)  # its seal checked: an edited label or split is refused, naming the file
    except FileNotFoundError:
        if (folder / "plan.json").is_file():  # a `histojax dataset` build that has not written dataset.json yet
            locks = sorted(p.name for p in (folder / "bundles").glob(".*.dataset-lock"))
            raise BundleError(
                folder,
                "no dataset.json yet: the dataset is being built by `histojax dataset` ("
                + (
                    f"{len(locks)} slide lock(s) held, e.g. bundles/{locks[0]}"
                    if locks
                    else "plan.json written, not every slide recorded"
                )
                + "); wait for the run, or finish it "
                f"with `histojax dataset --merge --out {folder}`",
            ) from None
        raise BundleError(
            folder,
            "not a dataset folder (no dataset.json); make one with `python -m data_tools synth` or pass slides=[...]",
        ) from None
    except json.JSONDecodeError as e:
        raise BundleError(index, f"malformed JSON ({e})") from None
    if fold is not None:
        return fold_slides(folder, spec, split, fold)
    if split == "all":
        names = list(spec.get("train", [])) + list(spec.get("test", []))
    elif split in ("train", "test"):
        names = spec.get(split)
    else:
        raise ValueError(f"split must be 'train', 'test' or 'all', got {split!r}")
    if isinstance(names, list) and not names and spec.get("variant") == "subset":
        raise BundleError(
            index,
            f"the {split!r} split of this subset is empty: a subset keeps the whole set's split, "
            f"and none of its slides is on the {split} side; build some with `python -m data_tools c16 "
            f"--slides NAME ...` on the same --out (see the 'test' / 'train' lists of the full set)",
        )
    if not isinstance(names, list) or not names:
        raise BundleError(index, f"no {split!r} list of bundles")
    return [folder / n for n in names]


def with_fold(spec: dict, fold, index="dataset.json") -> dict:
    """``spec`` (a ``dataset.json``, read) with fold ``fold``'s sides: ``"train"`` = the bundles of every other
    fold, ``"validation"`` = fold ``fold``'s, and ``"test"`` = fold ``fold``'s too where the folds cover every slide
    (``pool == "all"``); where they cut the train side of a fixed test set, ``"test"`` is dropped (the fixed set has
    no folds). How the head fits and reader commands take ``--fold i``. ``BundleError`` naming ``index`` (one line)
    for a dataset without folds or a fold out of range."""
    folds = spec.get("folds")
    if not isinstance(folds, dict) or not isinstance(folds.get("lists"), list):
        raise BundleError(
            index,
            f"fold={fold!r}: this dataset has no folds; build it with `histojax dataset ... "
            "--folds K` (or `c16 --folds K`), or drop fold",
        )
    k = len(folds["lists"])
    if isinstance(fold, bool) or not isinstance(fold, (int, np.integer)) or not 0 <= int(fold) < k:
        raise BundleError(index, f"fold={fold!r} is out of range: this dataset has {k} folds (0 to {k - 1})")
    fold = int(fold)
    out = {key: v for key, v in spec.items() if key != "test"}
    out["train"] = [n for i, lst in enumerate(folds["lists"]) if i != fold for n in lst]
    out["validation"] = list(folds["lists"][fold])
    if folds.get("pool") == "all":
        out["test"] = list(folds["lists"][fold])
    out["fold"] = fold
    return out


def fold_slides(folder, spec: dict, split: str, fold) -> list[Path]:
    """The bundle paths of fold ``fold``'s side ``split`` of the dataset ``spec`` (``FOLDER/dataset.json`` read):
    ``"train"`` = the slides of every other fold; ``"validation"`` (or ``"val"``) = fold ``fold``'s slides, and
    ``"test"`` too when the folds cover every slide (``pool == "all"``). One-line refusals: a dataset without folds,
    a fold out of range, ``"test"`` on folds cut from the train side of a fixed test set, another split."""
    index = Path(folder) / "dataset.json"
    sides = with_fold(spec, fold, index)
    if split in ("train", "validation", "val") or (split == "test" and spec["folds"].get("pool") == "all"):
        names = sides["validation" if split == "val" else split]
    elif split == "test":
        raise BundleError(
            index,
            f"fold={fold}: this dataset's folds cut its train side (its test set is fixed): fold "
            f"{fold}'s held-out slides are split='validation'; the test set is split='test' without fold",
        )
    else:
        raise ValueError(f"with fold=, split must be 'train', 'validation' or 'test', got {split!r}")
    if not names:
        raise BundleError(index, f"fold {fold}'s {split!r} side holds no built slide")
    return [Path(folder) / n for n in names]


def dataset_labels(folder) -> dict[str, int] | None:
    """The ``"labels"`` (bundle name → 0/1) of ``FOLDER/dataset.json``, or None when it has none."""
    try:
        labels = read_dataset_json(folder).get("labels")  # its seal checked
    except (OSError, json.JSONDecodeError, AttributeError):
        return None
    return {str(k): int(v) for k, v in labels.items()} if isinstance(labels, dict) and labels else None


def label_of(bundle, labels) -> int:
    """The slide label of ``bundle`` from a dict or CSV (``slide,label``), keyed by bundle folder
    name or source file stem."""
    if not isinstance(labels, dict):
        with open(labels, newline="") as f:
            rows = list(csv.DictReader(f))
        try:
            labels = {r["slide"]: int(r["label"]) for r in rows}
        except (KeyError, ValueError):
            raise BundleError(labels, "a labels CSV needs columns slide,label with label 0 or 1") from None
    for key in (Path(bundle.path).name, Path(bundle.metadata.source["file"]).stem):
        if key in labels:
            return int(labels[key])
    raise BundleError(bundle.path, "no label for this slide in labels= (keyed by bundle folder name or slide stem)")
