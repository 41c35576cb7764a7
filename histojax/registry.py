"""Environment ids → scenarios, and ``make``.

Scenarios (all on the same magnification range of the slide; more levels = smaller zoom steps):

==================  ========  ======================  ===================
id                  levels    max_steps_in_episode    zoom per level (R=16)
==================  ========  ======================  ===================
HistoJAX-Easy-v0    3         100                     4×
HistoJAX-Medium-v0  5         200                     2×
HistoJAX-Hard-v0    7         300                     1.59×
==================  ========  ======================  ===================

The true-scale CAMELYON16 benchmark (``docs/c16-benchmark.md``; geometry real CAMELYON16, pixels real
PCam patches arranged by us, not scanned slides) needs a dataset made by ``python -m data_tools c16``:
``make("HistoJAX-C16-Hard-v0", dataset=DIR, split="train" | "test")`` (or ``$HISTOJAX_C16_DATASET``).

=========================  ========  =====  ==============================================
id                         levels    steps  task
=========================  ========  =====  ==============================================
HistoJAX-C16-Easy-v0       3         100    detection (find a view ≥ 50 % tumour; tumour slides)
HistoJAX-C16-Medium-v0     5         200    detection
HistoJAX-C16-Hard-v0       7         300    detection
HistoJAX-C16-Diagnosis-v0  5         200    classification: declare tumour / no tumour
=========================  ========  =====  ==============================================

``-v1``: pcam-cnn features observed by default, datasets of format 2. ``-v2``: as ``-v1``, and the reading
modes' observations carry only what a step changes (``step_obs=True``; :meth:`HistoEnv.episode_tables`).
"""
from __future__ import annotations

import csv
import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from data_tools.bundle_format import read_dataset_json
from data_tools.errors import BundleError
from histojax.core.modes import factory
from histojax.core.env import EnvParams, HistoEnv
from histojax.make_options import DATASET, MODE, PARAMS, STATIC, MakeOptions
from histojax.core.modes.base import Navigation
from histojax.core.slide import DEFAULT_MAX_DEVICE_BYTES, check_alike, load_slide, stack_slides, start_cdf

# the names of make's options by where they go, derived from the one typed set (histojax.make_options.MakeOptions):
# static HistoEnv settings, EnvParams fields, the action mode's prepare settings (histojax.core.modes.base),
# and how make draws a dataset's slides (``tumour_slides_only``: reset draws only slides with tumour annotated;
# ``dataset_format`` / ``dataset_encoder``: the least ``dataset.json`` "format" and the feature encoder a dataset
# must have for this id, an older dataset refused naming the command that rebuilds it)
STATIC_FIELDS = MakeOptions.names(STATIC)
PARAM_FIELDS = MakeOptions.names(PARAMS)
MODE_SETTINGS = MakeOptions.names(MODE)
DATASET_FIELDS = MakeOptions.names(DATASET)
if set(PARAM_FIELDS) != {f.name for f in dataclasses.fields(EnvParams)} - {"slide", "mode_data"}:
    raise AssertionError("MakeOptions' params options must be the EnvParams fields")


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """The one registration record of an environment id, for built-in ids and scenario files alike.

    ``settings`` holds static settings (``STATIC_FIELDS``: ``n_levels``, ``obs_mode``, ``reward``, …),
    ``EnvParams`` defaults (``PARAM_FIELDS``: ``max_steps_in_episode``, …) and dataset settings
    (``DATASET_FIELDS``), spelled as the env spells them. ``slide`` is the id's default slide when ``make`` gets none: a bundle path, a list of
    them (a dataset), or a recipe ``f(settings) -> path(s)`` (e.g. builds into the cache on first use);
    ``None`` means the embedded sample slide. ``scenario`` is the :class:`histojax.scenarios.Scenario`
    it was registered from, if any."""

    id: str
    settings: dict
    slide: object = None
    scenario: object = None

    def __post_init__(self):
        unknown = set(self.settings) - set(MakeOptions.names(STATIC, PARAMS, DATASET))
        if unknown:
            raise TypeError(f"unknown scenario settings {sorted(unknown)}")

    @property
    def options(self) -> MakeOptions:
        """``settings`` as the typed :class:`~histojax.make_options.MakeOptions`."""
        return MakeOptions(**self.settings)


_REGISTRY: dict[str, EnvSpec] = {}


def register(env_id: str, slide=None, **settings) -> EnvSpec:
    """Register an id: ``settings`` are :class:`EnvSpec` settings (static ones such as ``n_levels``,
    ``reward``, and ``EnvParams`` defaults such as ``max_steps_in_episode``); ``slide`` as in
    :class:`EnvSpec`. Returns the record. (:func:`histojax.scenarios.register_scenario` registers a
    scenario file through :func:`register_spec` with the same record.)"""
    return register_spec(EnvSpec(id=env_id, settings=dict(settings), slide=slide))


def register_spec(spec: EnvSpec) -> EnvSpec:
    """Register (or replace) the record ``spec`` under ``spec.id``; returns it."""
    _REGISTRY[spec.id] = spec
    return spec


def spec_of(env_id: str) -> EnvSpec:
    """The registration record of ``env_id`` (ValueError naming the registered ids when unknown)."""
    if env_id not in _REGISTRY:
        raise ValueError(f"unknown environment id {env_id!r}; registered: {', '.join(_REGISTRY)}")
    return _REGISTRY[env_id]


def registered_envs() -> tuple[str, ...]:
    """All registered environment ids."""
    return tuple(_REGISTRY)


register("HistoJAX-Easy-v0", n_levels=3, max_steps_in_episode=100)
register("HistoJAX-Medium-v0", n_levels=5, max_steps_in_episode=200)
register("HistoJAX-Hard-v0", n_levels=7, max_steps_in_episode=300)


C16_DATASET_VARIABLE = "HISTOJAX_C16_DATASET"


def _c16_dataset(spec: dict) -> Path:
    """The default dataset of the C16 ids: ``$HISTOJAX_C16_DATASET``, else ``cache_dir()/c16``; a clear
    error naming the command when neither holds a ``dataset.json``."""
    import os

    from histojax.sample import cache_dir

    given = os.environ.get(C16_DATASET_VARIABLE)
    folder = Path(given) if given else cache_dir() / "c16"
    if not (folder / "dataset.json").is_file():
        embed = spec.get("dataset_encoder") is not None  # the -v1 ids observe pcam-cnn features: build them too
        raise BundleError(folder, "no C16 dataset here (no dataset.json): the HistoJAX-C16-* ids need one. Make the "
                          f"small one with `python -m data_tools c16 --small{' --features' * embed} --out DIR` "
                          f"({'a minute' if embed else 'seconds'}) or the full one with "
                          "`python -m data_tools c16 --annotations camelyon16_ncrf_train.tar.gz --patches "
                          f"pcam_train_patches.tar.gz{' --no-pixels' * embed} --out DIR`, then pass make(id, dataset=DIR) "
                          f"or set {C16_DATASET_VARIABLE}=DIR")
    return folder


# v0: any C16 dataset (the observation is whatever the caller picks; pixels by default).
# v1: datasets of format 2 (train and test slides textured from disjoint PCam patch pools) embedded with the
# PCam-trained encoder ``pcam-cnn``, observed through it by default (obs_mode="features"); an older dataset is
# refused with the command that rebuilds it (it keeps loading under v0).
C16_V1 = dict(dataset_format=2, dataset_encoder="pcam-cnn", obs_mode="features")
for _name, _levels, _steps in (("Easy", 3, 100), ("Medium", 5, 200), ("Hard", 7, 300)):
    register(f"HistoJAX-C16-{_name}-v0", slide=_c16_dataset, n_levels=_levels, max_steps_in_episode=_steps,
             tumour_slides_only=True)
    register(f"HistoJAX-C16-{_name}-v1", slide=_c16_dataset, n_levels=_levels, max_steps_in_episode=_steps,
             tumour_slides_only=True, **C16_V1)
register("HistoJAX-C16-Diagnosis-v0", slide=_c16_dataset, n_levels=5, max_steps_in_episode=200, task="classification")
register("HistoJAX-C16-Diagnosis-v1", slide=_c16_dataset, n_levels=5, max_steps_in_episode=200, task="classification",
         **C16_V1)
# v2: v1's datasets and defaults; the reading modes observe per step only what changed (step_obs=True: for
# glimpse the cells read, their summaries in K slots, the read bits, the budget left and the slide index; the
# slides' cell tables come once from env.episode_tables). Navigation observes the same as under v1. The v1 ids
# keep v1's observation, so policies trained on them (the c16-v1 published readers) still load and run.
for _name, _levels, _steps in (("Easy", 3, 100), ("Medium", 5, 200), ("Hard", 7, 300)):
    register(f"HistoJAX-C16-{_name}-v2", slide=_c16_dataset, n_levels=_levels, max_steps_in_episode=_steps,
             tumour_slides_only=True, step_obs=True, **C16_V1)
register("HistoJAX-C16-Diagnosis-v2", slide=_c16_dataset, n_levels=5, max_steps_in_episode=200, task="classification",
         step_obs=True, **C16_V1)


def _reading_dataset(spec: dict):
    """The reading ids have no default slides: one clear error asking for ``dataset=``."""
    raise ValueError("HistoJAX-Reading-v0 reads a dataset of your own: make('HistoJAX-Reading-v0', dataset=DIR) with "
                     "DIR from `histojax dataset`, `histojax c16` or imported .h5 features (any encoder)")


# Reading on any dataset (any encoder's feature grids, imported .h5 included): the cell-set reader's -v2
# observation (step_obs) on a classification task, five zoom levels (n_levels= for bundles built with fewer)
READING_ID = "HistoJAX-Reading-v0"
register(READING_ID, slide=_reading_dataset, n_levels=5, max_steps_in_episode=200, task="classification",
         step_obs=True, obs_mode="features")


def _c16_rebuild_command(folder, ds: dict) -> str:
    """The ``data_tools c16`` command that rebuilds ``folder`` with the options its ``dataset.json`` records
    (``--small`` or the sources and scale, split seed, held-out patches, subset, pixels or not), with features."""
    import shlex

    opts = ["--small"] if ds.get("variant") == "small" else [
        "--annotations", str(ds.get("annotations")), "--patches", str(ds.get("patches")),
        "--downsample", str((ds.get("scale") or {}).get("downsample_from_camelyon16_level0", 8.0))]
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
        fix = (f"rebuild it with `{_c16_rebuild_command(folder, ds)}` (its recorded options; the encoder is "
               f"pcam-cnn by default), or use the -v0 id")
    else:  # a cohort of scanned slides (`histojax dataset`): no patch pools to share, only the encoder matters
        fix = (f"rebuild it with `histojax dataset SLIDES_DIR --out {folder} --encoder {want_encoder} ...` (same "
               f"options), or use the -v0 id")
    if want_format is not None and mosaic and int(ds.get("format", 1)) < want_format:
        raise BundleError(index, f"{env_id} needs a dataset of format >= {want_format} (train and test slides "
                          f"textured from disjoint PCam patch pools); this one is format {ds.get('format', 1)}: {fix}")
    # any recorded encoder's grids (pcam-cnn by default; your own with --encoder module:function), not none
    if want_encoder is not None and spec.get("obs_mode", "pixels") == "features" and not ds.get("encoder"):
        raise BundleError(index, f"{env_id} observes {want_encoder} features, and this dataset records no feature "
                          f"grids (built without --features): {fix}")


def make(env_id: str, slide=None, verify: bool = True, max_device_bytes: int = DEFAULT_MAX_DEVICE_BYTES,
         slides=None, slide_weights=None, dataset=None, split: str = "train", labels=None, fold: int | None = None,
         **overrides):
    """Make ``(env, params)`` for a registered id.

    ``slide``: a bundle folder (``python -m data_tools build``) or ``None`` for the id's registered
    slide (``register(..., slide=...)``, e.g. a scenario's recipe) or else the embedded sample slide
    (bundles are built on first use). ``overrides``: the options of :class:`histojax.make_options.MakeOptions`,
    any static setting (``action_mode``, ``obs_mode``, ``with_position``, ``reward``, ``auto_reset``,
    ``augment``; ``tile_size`` only for the sample slide, where it selects another cached bundle) or ``EnvParams`` field
    (``max_steps_in_episode``, ``stride``, ``success_threshold``, ``step_cost``,
    ``success_bonus``, ``histogym_scale``, ``dense_weight``, ``random_start``, ``start_level``), or the reading
    settings of :mod:`histojax.core.seen_views`: ``read_budget`` (fraction of finest-level tissue views, for
    ``action_mode="glimpse"`` / ``"zoom_select"``, or with tracking) and ``track_reading=True`` (the
    pan/zoom modes then report ``fraction_read`` and ``fields_of_view`` in ``info``), and for ``glimpse``,
    ``glimpse_grid=(H, W)``, the padded cell grid (default: the largest of the slides loaded; the
    trainers record it so that a glimpse policy runs on other slides).
    The slide's arrays are put on the device once and returned inside ``params``; a slide
    needing more than ``max_device_bytes`` (default 4 GiB) is refused with a clear error. It bounds the
    arrays put on the device, not the process's host memory (on the CPU backend, where they are host
    memory, ``make`` peaks at about 1.6× them; see :func:`histojax.core.slide.load_slide`).
    ``verify`` checks every array's SHA-256 against the bundle metadata.

    Datasets: ``slides=[bundle, ...]`` (any sizes, same tile size) or ``dataset=FOLDER`` holding a
    ``dataset.json`` with ``"train"`` / ``"test"`` lists of bundle paths (``split`` picks one; e.g.
    ``python -m data_tools synth``) give one env over all of them (``fold=i`` on a dataset built with
    ``--folds K``: fold ``i``'s sides, see :func:`dataset_slides`): ``reset`` draws a slide
    (uniformly, or by ``slide_weights``). ``max_device_bytes`` then bounds the whole dataset.
    ``labels`` (a dict bundle-name → 0/1 or a CSV file with columns ``slide,label``) overrides the
    slide labels of ``task="classification"`` (default: the ``"labels"`` of the dataset's ``dataset.json``
    when it has them, e.g. ``data_tools dataset --labels`` or CAMELYON16's ``reference.csv``, else 1 when
    the bundle has tumour annotated).
    """
    given = MakeOptions.of(overrides, where=f"make({env_id!r})")  # TypeError naming an unknown setting
    options = given.over(spec_of(env_id).options)
    mode_settings = given.given(MODE)  # only as given: a registered id holds no mode settings
    spec = options.given(STATIC, PARAMS, DATASET)
    _check_start_level(factory.action_mode(spec.get("action_mode", "discrete")), spec.get("start_level", 0),
                       f"make({env_id!r})")
    slides = _resolve_slides(env_id, spec, slide, slides, dataset, split, fold)
    if labels is None and dataset is not None and spec.get("task", "detection") == "classification":
        labels = dataset_labels(dataset)  # a label table's or CAMELYON16's labels, not just "annotated"
    feature_obs = factory.obs_mode(spec.get("obs_mode", "pixels")).needs_features
    features = True if feature_obs or factory.action_mode(spec.get("action_mode", "discrete")).needs_features else None
    check_alike(slides, features=features)  # bundles that cannot make one dataset, named before any array is read
    loaded, budget = [], max_device_bytes
    for path in slides:  # obs_mode="features": the feature-only layout, no pixels on the device
        arrays, bundle = load_slide(path, spec["n_levels"], verify=verify, max_device_bytes=budget, features=features,
                                    pixels=not feature_obs)
        budget -= sum(int(a.nbytes) for a in jax.tree.leaves(arrays))
        loaded.append((arrays, bundle))
    tile_sizes = {b.tile_size for _, b in loaded}
    if len(tile_sizes) != 1:
        raise ValueError(f"the slides were built with different tile sizes {sorted(tile_sizes)}; rebuild them alike")
    tile_size = tile_sizes.pop()
    if spec.get("tile_size", tile_size) != tile_size:
        raise ValueError(f"bundle {slides[0]} was built with tile size {tile_size}; rebuild it with "
                         f"--tile-size {spec['tile_size']} or drop the override")
    if labels is not None:
        loaded = [(a.replace(slide_label=jnp.int32(_label_of(b, labels))), b) for a, b in loaded]
    if spec.get("tumour_slides_only") and spec.get("task", "detection") == "detection":
        slide_weights = _tumour_slide_weights([a for a, _ in loaded], slides, slide_weights)
    if len(loaded) == 1 and slide_weights is None:
        arrays = loaded[0][0]
    else:
        arrays = stack_slides([a for a, _ in loaded], weights=slide_weights, consume=True)  # per-slide copies freed
    arrays = arrays.replace(start_cdf=jnp.asarray(start_cdf(arrays.start_logits)))  # once, not at every reset
    static = {**options.given(STATIC), "tile_size": tile_size}
    validate_params(options.given(PARAMS), tile_size, where=f"make({env_id!r})")
    params = EnvParams(slide=arrays, **options.given(PARAMS))
    bundles = tuple(b for _, b in loaded)
    env = HistoEnv(name=env_id, _default_params=params, _bundle=bundles[0], _bundles=bundles, **static)
    mode_data = env.action.prepare(env, params, bundles, **mode_settings)  # per-slide tables of a reading mode, once
    if mode_data is not None:
        params = params.replace(mode_data=mode_data)
        env = dataclasses.replace(env, _default_params=params)
    return env, params


def _tumour_slide_weights(arrays: list, paths: list, weights=None) -> list[float] | None:
    """``weights`` (default uniform) with the slides that have no tumour annotated set to 0; ``None``
    for one slide with tumour; ``ValueError`` when no slide has tumour."""
    has_tumour = [int(a.slide_label) == 1 for a in arrays]
    if not any(has_tumour):
        raise ValueError(f"detection needs a slide with tumour annotated; none of the {len(paths)} slides has any "
                         f"({', '.join(Path(p).name for p in paths[:4])}{', ...' if len(paths) > 4 else ''})")
    if len(arrays) == 1:
        return weights
    base = [1.0] * len(arrays) if weights is None else [float(w) for w in weights]
    return [w if t else 0.0 for w, t in zip(base, has_tumour)]


def slide_paths(env_id: str, slide=None, slides=None, dataset=None, split: str = "train", fold: int | None = None,
                **overrides) -> list:
    """The bundle paths ``make`` would load for these arguments (one for a single slide)."""
    return _resolve_slides(env_id, {**spec_of(env_id).settings, **overrides}, slide, slides, dataset, split, fold)


def _resolve_slides(env_id: str, spec: dict, slide, slides, dataset, split: str, fold: int | None = None) -> list:
    """``slides`` / ``dataset`` / ``slide`` / the id's registered slide or dataset / the sample slide,
    as a non-empty list of bundle paths."""
    if dataset is None and slide is None and slides is None and spec_of(env_id).slide is _c16_dataset:
        dataset = _c16_dataset(spec)
    if fold is not None and dataset is None:
        raise ValueError(f"fold={fold!r} picks a fold of a dataset built with --folds K: give dataset=DIR (or an id "
                         "whose slides are a dataset)")
    if dataset is not None:
        check_dataset(dataset, spec, env_id)
        slides = dataset_slides(dataset, split, fold)
    if slides is not None and slide is not None:
        raise ValueError("give either slide= or slides=/dataset=, not both")
    if slides is None:
        if slide is None and spec_of(env_id).slide is not None:
            recipe = spec_of(env_id).slide
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


MAX_STRIDE_PX = 2**30  # a move of stride × tile_size px plus a position (< 2**30 px) stays inside int32


def validate_params(values: dict, tile_size: int, where: str = "make") -> None:
    """Check ``EnvParams`` values given to ``make`` (Python or array scalars; arrays element-wise):
    ``stride`` finite with ``1 <= stride × tile_size <= 2**30`` px (moves cannot wrap int32),
    ``max_steps_in_episode`` an integer in ``[1, 2**31 - 2]``, ``success_threshold`` in ``(0, 1]``,
    rewards (``step_cost``, ``success_bonus``, ``histogym_scale``, ``dense_weight``, ``diagnosis_reward``)
    finite, ``random_start`` a bool, ``start_level`` a whole number. Raises ValueError naming the field."""
    def bad(field, value, rule):
        raise ValueError(f"{where}: {field}={value!r} {rule}")

    def numbers(field):
        try:
            return np.asarray(values[field], dtype=np.float64)
        except (TypeError, ValueError):
            bad(field, values[field], "is not a number")

    for field in values:
        if field == "random_start":
            v = np.asarray(values[field])
            if v.dtype != bool and not (np.issubdtype(v.dtype, np.integer) and np.isin(v, (0, 1)).all()):
                bad(field, values[field], "must be True or False")
            continue
        v = numbers(field)
        if not np.isfinite(v).all():
            bad(field, values[field], "must be finite")
        if field == "stride" and not ((v * tile_size >= 1).all() and (v * tile_size <= MAX_STRIDE_PX).all()):
            bad(field, values[field], f"must be > 0 view widths with 1 <= stride × tile_size ({tile_size}) <= 2**30 px "
                "(a move of stride × tile_size px must stay inside int32)")
        if field == "max_steps_in_episode" and not ((v == np.round(v)).all() and (v >= 1).all()
                                                    and (v <= 2**31 - 2).all()):
            bad(field, values[field], "must be a whole number of steps in [1, 2**31 - 2]")
        if field == "start_level" and not ((v == np.round(v)).all() and (np.abs(v) <= 2**31 - 1).all()):
            bad(field, values[field], "must be a whole level number (0 = coarsest, -1 = finest)")
        if field == "success_threshold" and not ((v > 0).all() and (v <= 1).all()):
            bad(field, values[field], "must be a tumour fraction in (0, 1]")


def check_params(env, params, where: str = "params") -> None:
    """Host-side check of an ``EnvParams`` changed after ``make`` (e.g. ``params.replace(stride=...)``, or a
    vmapped batch of them) against the rules of :func:`validate_params`, for ``env``'s tile size: raises
    ``ValueError`` naming the field instead of letting a move wrap int32, a NaN freeze the view or a
    negative step limit truncate every step. Called by the trainers, ``evaluate`` and the Gymnasium
    adapters; inside ``jit`` use :func:`histojax.debug.checked`, which makes the same checks with
    ``checkify``."""
    values = {k: getattr(params, k) for k in PARAM_FIELDS}
    if any(isinstance(v, jax.core.Tracer) for v in values.values()):
        raise TypeError(f"{where}: check_params runs on the host, not inside jit; use histojax.debug.checked")
    values = {k: v.addressable_data(0) if isinstance(v, jax.Array) and not v.is_fully_addressable else v
              for k, v in values.items()}  # replicated over several processes: this process's copy
    validate_params(values, env.tile_size, where=where)
    _check_start_level(env.action, values["start_level"], where)


def _check_start_level(mode, start_level, where: str) -> None:
    """``ValueError`` for a ``start_level`` other than 0 with a reading mode (its episodes start at the coarsest
    level; the env would ignore it)."""
    if not isinstance(mode, Navigation) and np.any(np.asarray(start_level) != 0):
        raise ValueError(f"{where}: start_level={start_level!r} is for the navigation modes (discrete, continuous); "
                         f"{mode.name!r} episodes start at the coarsest level")


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
            raise BundleError(folder, "no dataset.json yet: the dataset is being built by `histojax dataset` ("
                              + (f"{len(locks)} slide lock(s) held, e.g. bundles/{locks[0]}" if locks else
                                 "plan.json written, not every slide recorded") + "); wait for the run, or finish it "
                              f"with `histojax dataset --merge --out {folder}`") from None
        raise BundleError(folder, "not a dataset folder (no dataset.json); make one with "
                          "`python -m data_tools synth` or pass slides=[...]") from None
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
        raise BundleError(index, f"the {split!r} split of this subset is empty: a subset keeps the whole set's split, "
                          f"and none of its slides is on the {split} side; build some with `python -m data_tools c16 "
                          f"--slides NAME ...` on the same --out (see the 'test' / 'train' lists of the full set)")
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
        raise BundleError(index, f"fold={fold!r}: this dataset has no folds; build it with `histojax dataset ... "
                          "--folds K` (or `c16 --folds K`), or drop fold")
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
        raise BundleError(index, f"fold={fold}: this dataset's folds cut its train side (its test set is fixed): fold "
                          f"{fold}'s held-out slides are split='validation'; the test set is split='test' without fold")
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


def _label_of(bundle, labels) -> int:
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
