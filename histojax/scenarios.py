"""Scenarios as data: a :class:`Scenario` names the slide(s), the zoom levels, the view size, the
reward, the observation and action modes, an optional region rule and the step limit; it loads
from TOML or JSON and registers as an environment id, so ``histojax.make(id)`` works::

    id = "CAMELYON16-tumor_001-Hard-v0"
    n_levels = 7
    reward = "histogym"
    max_steps_in_episode = 300

    [[slides]]
    slide = "~/data/camelyon16/training/tumor/tumor_001.tif"       # built into the cache on first use
    annotations = "~/data/camelyon16/training/lesion_annotations/tumor_001.xml"

    [label_map]
    "_0" = "tumour"
    "_1" = "tumour"
    "_2" = "exclusion"

    histojax.register_scenario("camelyon16_tumor_001.toml")
    env, params = histojax.make("CAMELYON16-tumor_001-Hard-v0")

Keys (all optional but ``id``): ``slides`` — a list of bundle folders, of slide files, or of tables
``{slide = FILE, annotations = FILE}`` / ``{bundle = DIR}`` (absent: the embedded sample slide);
relative paths are taken from the scenario file's folder. ``n_levels`` (3; ``levels`` is accepted as
an older spelling), ``tile_size`` (128),
``reward`` ("dense"), ``obs_mode`` ("pixels"), ``action_mode`` ("discrete"), ``with_position``
(false), ``max_steps_in_episode`` (100 / 200 / 300 for 3 / 5 / 7 levels, else 100 per 2 levels),
``label_map`` (annotation group → tumour / exclusion / tissue / ignore), ``region`` — a table with
one of ``box = [x0, y0, x1, y1]`` (level-0 px), ``group = "tumour"`` (the bounding box of an
annotation group/label) or ``polygon = [[x, y], ...]``, and ``margin`` (level-0 px), ``params``
(other ``EnvParams`` fields, e.g. ``stride``), and ``train`` / ``test`` (lists of slide names for
splits). Every setting is spelled as the env spells it (``histojax.make(id, n_levels=..., obs_mode=...)``),
and registering makes the same record as a built-in id (:class:`histojax.registry.EnvSpec`). A slide file
is built into a bundle in the cache (:func:`histojax.cache.cached_bundle`) the first time the id is made
and reused after. Several slides make a dataset (``reset`` draws one);
``make(id, split="train" | "test" | "all")`` picks the scenario's ``train`` / ``test`` lists.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any

from data_tools.bundle_files.format import file_digest  # noqa: F401  (re-exported)
from data_tools.errors import HistojaxDataError
from histojax.cache import cached_bundle  # noqa: F401  (re-exported)

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

DEFAULT_MAX_STEPS = {3: 100, 5: 200, 7: 300}
_KEYS = (
    "id",
    "slides",
    "n_levels",
    "levels",
    "tile_size",
    "reward",
    "obs_mode",
    "action_mode",
    "with_position",
    "max_steps_in_episode",
    "label_map",
    "region",
    "params",
    "train",
    "test",
)


class ScenarioError(HistojaxDataError, ValueError):
    """A scenario file or object is malformed (names the file and the problem)."""


@dataclasses.dataclass(frozen=True)
class SlideSource:
    """One slide of a scenario: a ready ``bundle`` folder, or a ``slide`` file (with optional
    ``annotations``) that is built into a cached bundle on first use."""

    bundle: str | None = None
    slide: str | None = None
    annotations: str | None = None

    @property
    def name(self) -> str:
        return Path(self.bundle or self.slide).name


@dataclasses.dataclass(frozen=True)
class RegionRule:
    """The part of the slide a scenario uses: exactly one of ``box`` (x0, y0, x1, y1 in level-0 px),
    ``group`` (an annotation group/label whose union's bounding box is the region) or ``polygon``
    (vertices in level-0 px); ``margin`` grows it (level-0 px)."""

    box: tuple[float, float, float, float] | None = None
    group: str | None = None
    polygon: tuple[tuple[float, float], ...] | None = None
    margin: float = 0.0

    def build_argument(self):
        """The ``region=`` argument of :func:`data_tools.bundle.build_bundle`."""
        if self.polygon is not None:
            import shapely

            return shapely.Polygon(self.polygon)
        return self.group if self.group is not None else tuple(self.box)


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A registered environment as data (see the module doc for every field)."""

    id: str
    slides: tuple[SlideSource, ...] | None = None  # None: the embedded sample slide
    n_levels: int = 3
    tile_size: int = 128
    reward: str = "dense"
    obs_mode: str = "pixels"
    action_mode: str = "discrete"
    with_position: bool = False
    max_steps_in_episode: int | None = None
    label_map: dict[str, str] | None = None
    region: RegionRule | None = None
    params: dict[str, Any] = dataclasses.field(default_factory=dict)
    train: tuple[str, ...] = ()
    test: tuple[str, ...] = ()
    source: str | None = None  # the file it was loaded from

    @property
    def levels(self) -> int:
        """The older spelling of :attr:`n_levels`."""
        return self.n_levels

    def spec(self) -> dict:
        """The :class:`histojax.registry.EnvSpec` settings of this scenario."""
        steps = self.max_steps_in_episode or DEFAULT_MAX_STEPS.get(self.n_levels, 50 * self.n_levels)
        return dict(
            n_levels=self.n_levels,
            tile_size=self.tile_size,
            reward=self.reward,
            obs_mode=self.obs_mode,
            action_mode=self.action_mode,
            with_position=self.with_position,
            max_steps_in_episode=steps,
            **self.params,
        )


# ----------------------------------------------------------------------------- loading
def _fail(where, problem: str):
    raise ScenarioError(where, problem)


def _path(value, base: Path | None, where, what: str) -> str:
    if not isinstance(value, str) or not value:
        _fail(where, f"{what} must be a path string, got {value!r}")
    p = Path(value).expanduser()
    if not p.is_absolute() and base is not None:
        p = base / p
    return str(p)


def _slide_source(item, base, where) -> SlideSource:
    if isinstance(item, (str, Path)):
        p = _path(str(item), base, where, "slides entry")
        return SlideSource(bundle=p) if Path(p).is_dir() else SlideSource(slide=p)
    if isinstance(item, SlideSource):
        return item
    if isinstance(item, dict):
        extra = set(item) - {"bundle", "slide", "annotations"}
        if extra or ("bundle" in item) == ("slide" in item):
            _fail(where, f"slides entry {item!r} must have either 'bundle' or 'slide' (+ optional 'annotations')")
        if "bundle" in item:
            if "annotations" in item:
                _fail(where, "a bundle already holds its annotations; give 'slide' + 'annotations' instead")
            return SlideSource(bundle=_path(item["bundle"], base, where, "bundle"))
        ann = item.get("annotations")
        return SlideSource(
            slide=_path(item["slide"], base, where, "slide"),
            annotations=None if ann is None else _path(ann, base, where, "annotations"),
        )
    _fail(where, f"slides entry {item!r} must be a path or a table with 'slide'/'bundle'")


def _region(value, where) -> RegionRule | None:
    if value is None or isinstance(value, RegionRule):
        return value
    if not isinstance(value, dict):
        _fail(where, f"region must be a table with one of box / group / polygon, got {value!r}")
    extra = set(value) - {"box", "group", "polygon", "margin"}
    given = [k for k in ("box", "group", "polygon") if k in value]
    if extra or len(given) != 1:
        _fail(
            where,
            f"region must have exactly one of 'box', 'group', 'polygon' (and optional 'margin'), "
            f"got keys {sorted(value)}",
        )
    margin = value.get("margin", 0.0)
    if isinstance(margin, bool) or not isinstance(margin, (int, float)) or margin < 0:
        _fail(where, f"region margin must be a number >= 0 (level-0 px), got {margin!r}")
    try:
        if "box" in value:
            box = tuple(float(v) for v in value["box"])
            if len(box) != 4 or box[2] <= box[0] or box[3] <= box[1]:
                raise ValueError
            return RegionRule(box=box, margin=float(margin))
        if "group" in value:
            if not isinstance(value["group"], str) or not value["group"]:
                raise ValueError
            return RegionRule(group=value["group"], margin=float(margin))
        poly = tuple((float(x), float(y)) for x, y in value["polygon"])
        if len(poly) < 3:
            raise ValueError
        return RegionRule(polygon=poly, margin=float(margin))
    except (TypeError, ValueError):
        _fail(
            where,
            f"region {given[0]} = {value[given[0]]!r} is malformed (box: [x0, y0, x1, y1] with "
            "x0 < x1, y0 < y1; group: a name; polygon: at least 3 [x, y] vertices)",
        )


def scenario_from_dict(data: dict, base: Path | None = None, where=None) -> Scenario:
    """Validate a scenario mapping (as read from TOML/JSON) and build a :class:`Scenario`;
    relative paths are taken from ``base``. Errors name ``where``."""
    from data_tools.annotations import LABELS
    from histojax.core import rewards
    from histojax.core.modes.factory import ACTION_MODES as action_modes
    from histojax.core.modes.factory import OBS_MODES as obs_modes
    from histojax.registry import PARAM_FIELDS

    if not isinstance(data, dict):
        _fail(where, "a scenario must be a table/object of settings")
    unknown = sorted(set(data) - set(_KEYS))
    if unknown:
        _fail(where, f"unknown scenario key(s) {unknown}; known: {', '.join(_KEYS)}")
    if not isinstance(data.get("id"), str) or not data["id"].strip():
        _fail(where, "a scenario needs an 'id' string (the name given to histojax.make)")

    def check(key, ok, expected):
        if key in data and not ok(data[key]):
            _fail(where, f"{key} = {data[key]!r}: expected {expected}")

    def is_int(v):
        return isinstance(v, int) and not isinstance(v, bool)

    if "levels" in data and "n_levels" in data:
        _fail(where, "give n_levels (or its older spelling levels), not both")
    for key in ("n_levels", "levels"):
        check(key, lambda v: is_int(v) and v >= 2, "an integer >= 2 (3 Easy, 5 Medium, 7 Hard)")
    check("tile_size", lambda v: is_int(v) and v >= 8, "an integer >= 8 (view size in px)")
    check("max_steps_in_episode", lambda v: is_int(v) and v >= 1, "an integer >= 1")
    check("reward", lambda v: v in rewards.PRESETS, f"one of {rewards.PRESETS}")
    check("obs_mode", lambda v: v in obs_modes, f"one of {tuple(obs_modes)}")
    check("action_mode", lambda v: v in action_modes, f"one of {tuple(action_modes)}")
    check("with_position", lambda v: isinstance(v, bool), "true or false")
    check(
        "label_map",
        lambda v: isinstance(v, dict) and all(x in LABELS for x in v.values()),
        f"a table mapping annotation groups to one of {LABELS}",
    )
    check(
        "params",
        lambda v: isinstance(v, dict) and set(v) <= set(PARAM_FIELDS) - {"max_steps_in_episode"},
        f"a table of EnvParams fields among {[f for f in PARAM_FIELDS if f != 'max_steps_in_episode']}",
    )
    for split in ("train", "test"):
        check(
            split,
            lambda v: isinstance(v, list) and all(isinstance(x, (str, int)) for x in v),
            "a list of slide names or indices",
        )
    slides = data.get("slides")
    if slides is not None:
        if isinstance(slides, (str, dict)):
            slides = [slides]
        if not isinstance(slides, (list, tuple)) or not slides:
            _fail(where, "slides must be a non-empty list (leave it out for the embedded sample slide)")
        slides = tuple(_slide_source(s, base, where) for s in slides)
    return Scenario(
        id=data["id"].strip(),
        slides=slides,
        n_levels=data.get("n_levels", data.get("levels", 3)),
        tile_size=data.get("tile_size", 128),
        reward=data.get("reward", "dense"),
        obs_mode=data.get("obs_mode", "pixels"),
        action_mode=data.get("action_mode", "discrete"),
        with_position=data.get("with_position", False),
        max_steps_in_episode=data.get("max_steps_in_episode"),
        label_map=data.get("label_map"),
        region=_region(data.get("region"), where),
        params=dict(data.get("params", {})),
        train=tuple(str(x) for x in data.get("train", ())),
        test=tuple(str(x) for x in data.get("test", ())),
        source=None if where is None else str(where),
    )


def load_scenario(path) -> Scenario:
    """Read a scenario from a ``.toml`` or ``.json`` file (by extension; else TOML, then JSON).
    Raises :class:`ScenarioError` (a ``ValueError``) naming the file on any problem."""
    path = Path(path).expanduser()
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise ScenarioError(path, f"cannot read scenario file ({e.strerror or e})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ScenarioError(path, "scenario file is not UTF-8 text") from None
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise ScenarioError(path, f"invalid JSON ({e})") from None
    else:
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise ScenarioError(path, f"invalid TOML ({e})") from None
    return scenario_from_dict(data, base=path.parent, where=path)


# ----------------------------------------------------------------------------- building and registering
def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip("-").lower() or "scenario"


def _recipe(scenario: Scenario):
    """``f(spec) -> bundle path`` for the registry: builds the scenario's slide on first use."""

    def build(spec: dict):
        from data_tools.bundle import LEVEL_SETS
        from histojax.sample import SAMPLE_ANNOTATIONS, SAMPLE_SLIDE, sample_bundle

        n, tile = int(spec["n_levels"]), int(spec.get("tile_size", scenario.tile_size))
        level_sets = LEVEL_SETS if n in LEVEL_SETS else (n,)

        def one(source: SlideSource):
            if source.bundle is not None:
                return source.bundle
            return cached_bundle(
                source.slide,
                source.annotations,
                tile_size=tile,
                level_sets=level_sets,
                label_map=scenario.label_map,
                region=scenario.region,
                prefix=f"scenario-{_slug(scenario.id)}",
            )

        if scenario.slides is None:
            if scenario.region is None and not scenario.label_map and n in LEVEL_SETS:
                return sample_bundle(tile_size=tile, progress=False)
            return one(SlideSource(slide=str(SAMPLE_SLIDE), annotations=str(SAMPLE_ANNOTATIONS)))
        if len(scenario.slides) == 1:
            return one(scenario.slides[0])
        # a dataset: the split's slides (make(..., split="train" | "test" | "all"); no lists = all)
        split = spec.get("split", "train")
        names = {"train": scenario.train, "test": scenario.test}.get(split) or ()
        chosen = [s for s in scenario.slides if not names or s.name in names]
        return [one(s) for s in chosen]

    return build


def register_scenario(scenario_or_path) -> Scenario:
    """Register a :class:`Scenario` (or load one from a TOML/JSON file first) so that
    ``histojax.make(scenario.id)`` works; returns the scenario. Nothing is built until ``make``."""
    from histojax.registry import EnvSpec, register_spec

    scenario = scenario_or_path if isinstance(scenario_or_path, Scenario) else load_scenario(scenario_or_path)
    where = scenario.source or scenario.id
    if scenario.region is not None and scenario.slides is not None and scenario.slides[0].bundle is not None:
        raise ScenarioError(
            where,
            "a region rule needs the slide file (a bundle is already cut); give "
            "{slide = ..., annotations = ...} or build the region with "
            "`python -m data_tools build SLIDE --region ...`",
        )
    names = {s.name for s in scenario.slides or ()} | {"0"} | ({"sample"} if scenario.slides is None else set())
    for split in (*scenario.train, *scenario.test):
        if split not in names:
            raise ScenarioError(where, f"train/test entry {split!r} names no slide of the scenario ({sorted(names)})")
    try:
        register_spec(EnvSpec(id=scenario.id, settings=scenario.spec(), slide=_recipe(scenario), scenario=scenario))
    except TypeError as e:
        raise ScenarioError(where, str(e)) from None
    return scenario


# ----------------------------------------------------------------------------- built-in region scenarios
TARGET_MARGIN = 300  # level-0 px around the embedded slide's target annotation

for _name, _levels in (("Easy", 3), ("Medium", 5), ("Hard", 7)):
    register_scenario(
        Scenario(
            id=f"HistoJAX-{_name}-Region-v0", n_levels=_levels, region=RegionRule(group="tumour", margin=TARGET_MARGIN)
        )
    )

__all__ = [
    "RegionRule",
    "Scenario",
    "ScenarioError",
    "SlideSource",
    "cached_bundle",
    "file_digest",
    "load_scenario",
    "register_scenario",
    "scenario_from_dict",
]
