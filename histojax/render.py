"""Pictures on the host: the slide thumbnail, the tumour outline, view boxes (Pillow), trajectories
(matplotlib, Agg canvas: no display needed) and GIFs (Pillow). Not jittable and not meant to be: call
with concrete states."""

from __future__ import annotations

import json
import types
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from data_tools.bundle_files.format import ANNOTATIONS
from data_tools.bundle_files.safe_files import own_file
from data_tools.bundle_files.writes import atomic_file

TUMOUR_COLOUR = (0, 170, 0)
START_COLOUR = (0, 200, 255)
END_COLOUR = (255, 0, 0)


def level_colour(z: int, n_levels: int) -> tuple[int, int, int]:
    """Blue (coarsest) → red (finest)."""
    f = z / max(n_levels - 1, 1)
    return int(40 + 215 * f), int(60 * (1 - f)), int(255 * (1 - f))


def bundle_of(env, slide_index: int = 0):
    """The host bundle of slide ``slide_index`` of ``env`` (datasets have one per slide)."""
    return env.bundles[int(slide_index)]


def slide_name(env, slide_index: int = 0) -> str:
    """The name of slide ``slide_index`` of ``env`` (its bundle folder's name)."""
    return Path(bundle_of(env, slide_index).path).name


def _titled(title: str, env, slide_index: int) -> str:
    """``title`` with the slide's name on a line of its own (once)."""
    name = slide_name(env, slide_index)
    return title if name in title else "\n".join(t for t in (title, f"slide {name}") if t)


def _canvas(env, max_side: int, slide_index: int = 0):
    """The slide drawn ``max_side`` px on its longer side from the coarsest env level with pixels that is at
    least that large (else the finest with pixels, enlarged). Returns ``(PIL image, canvas px per level-0 px)``."""
    bundle = bundle_of(env, slide_index)
    with_pixels = [i for i, p in enumerate(bundle.pixels) if getattr(p, "has_pixels", True)]  # coarsest first
    k = next((i for i in with_pixels if max(bundle.pixels[i].shape[:2]) >= max_side), with_pixels[-1])
    level = np.asarray(bundle.pixels[k])
    fit = max_side / max(
        level.shape[:2]
    )  # < 1: shrunk; > 1 (a feature-only bundle keeps its coarsest level only): grown
    size = (max(1, round(level.shape[1] * fit)), max(1, round(level.shape[0] * fit)))
    image = Image.fromarray(level).resize(size, Image.Resampling.BOX if fit <= 1 else Image.Resampling.BICUBIC)
    return image, size[0] / (level.shape[1] * bundle.downsamples[k])


def tumour_rings(env, slide_index: int = 0) -> list[np.ndarray]:
    """The tumour outline of a slide of ``env`` as rings ``(N, 2)`` of level-0 px ``(x, y)``
    (exteriors and holes; empty when the bundle has no annotations). A link or other entry that is not the
    bundle's own file is refused (``BundleError`` naming the bundle and the entry)."""
    bundle = Path(bundle_of(env, slide_index).path)
    if not ((bundle / ANNOTATIONS).exists() or (bundle / ANNOTATIONS).is_symlink()):
        return []
    path = own_file(bundle, ANNOTATIONS, "annotations")
    import shapely.geometry

    rings = []
    for feature in json.loads(path.read_text()).get("features", []):
        if feature.get("properties", {}).get("label", "tumour") != "tumour":
            continue
        geom = shapely.geometry.shape(feature["geometry"])
        for poly in getattr(geom, "geoms", [geom]):
            rings += [
                np.asarray(ring.coords, np.float64) for ring in [poly.exterior, *poly.interiors] if len(ring.coords) > 1
            ]
    return rings


def _draw_tumour(draw: ImageDraw.ImageDraw, env, scale: float, slide_index: int = 0) -> None:
    for ring in tumour_rings(env, slide_index):
        draw.line([(x * scale, y * scale) for x, y in ring], fill=TUMOUR_COLOUR, width=2)


def view_box_level0(env, z: int, x: int, y: int, slide_index: int = 0) -> tuple[float, float, float, float]:
    """The view at ``(z, x, y)`` as a level-0 px box ``(left, top, right, bottom)``."""
    d = bundle_of(env, slide_index).downsamples[int(z)]
    return x * d, y * d, (x + env.tile_size) * d, (y + env.tile_size) * d


def _thumbnail_with_tumour(env, max_side: int, slide_index: int = 0):
    """``(PIL image, scale)``: the slide thumbnail (:func:`_canvas`) with the tumour outlined."""
    image, scale = _canvas(env, max_side, slide_index)
    _draw_tumour(ImageDraw.Draw(image), env, scale, slide_index)
    return image, scale


def _draw_view(image, env, state, scale: float, slide_index: int):
    """Draw the view box of ``state`` (concrete ``z, x, y``) on ``image`` in place."""
    box = [v * scale for v in view_box_level0(env, int(state.z), int(state.x), int(state.y), slide_index)]
    ImageDraw.Draw(image).rectangle(box, outline=level_colour(int(state.z), env.n_levels), width=3)
    return image


def render_state(env, state, params=None, max_side: int = 640) -> np.ndarray:
    """RGB uint8 ``(H, W, 3)``: thumbnail of the env's slide, tumour outline, the current view box."""
    index = int(getattr(state, "slide_index", 0))
    image, scale = _thumbnail_with_tumour(env, max_side, index)
    return np.asarray(_draw_view(image, env, state, scale, index))


def _zxy(z, x, y):
    """Accept either three sequences or a stacked state (anything with ``.z``, ``.x``, ``.y``)."""
    if x is None and y is None:
        z, x, y = z.z, z.x, z.y
    return tuple(np.asarray(a).astype(int).ravel() for a in (z, x, y))


def _rgb(c) -> tuple[float, float, float]:
    return tuple(v / 255 for v in c)


def _level_crop(env, slide_index: int, box) -> tuple[np.ndarray, tuple[float, float, float, float]] | None:
    """Pixels of the level-0 box ``(left, top, right, bottom)`` from the coarsest bundle level (with pixels)
    at which the crop is at least 320 px a side (else the finest with pixels; at most 1,600 px a side):
    ``(RGB array, the box it really covers)``; None when no level keeps pixels."""
    bundle = bundle_of(env, slide_index)
    with_pixels = [k for k, p in enumerate(bundle.pixels) if getattr(p, "has_pixels", True)]  # coarsest first
    if not with_pixels:
        return None
    side = max(box[2] - box[0], box[3] - box[1])
    fits = [k for k in with_pixels if side / bundle.downsamples[k] <= 1600]
    k = next((k for k in fits if side / bundle.downsamples[k] >= 320), (fits or with_pixels[:1])[-1])
    d, level = bundle.downsamples[k], bundle.pixels[k]
    h, w = level.shape[:2]
    x0, y0 = max(0, int(box[0] // d)), max(0, int(box[1] // d))
    x1, y1 = min(w, int(np.ceil(box[2] / d))), min(h, int(np.ceil(box[3] / d)))
    if x1 <= x0 or y1 <= y0:
        return None
    return np.asarray(level[y0:y1, x0:x1]), (x0 * d, y0 * d, x1 * d, y1 * d)


def _draw_path(ax, env, z, boxes, centres) -> None:
    """Boxes coloured by level, the path between view centres (coloured by the level moved to), the thick end box."""
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Rectangle

    colour = lambda k: _rgb(level_colour(int(k), env.n_levels))  # noqa: E731
    for (left, top, right, bottom), zi in zip(boxes, z):
        ax.add_patch(
            Rectangle((left, top), right - left, bottom - top, fill=False, edgecolor=colour(zi), linewidth=0.9)
        )
    if len(centres) > 1:
        ax.add_collection(
            LineCollection(
                np.stack([centres[:-1], centres[1:]], axis=1), colors=[colour(k) for k in z[1:]], linewidths=2.2
            )
        )
    if len(centres):
        left, top, right, bottom = boxes[-1]
        ax.add_patch(
            Rectangle((left, top), right - left, bottom - top, fill=False, edgecolor=_rgb(END_COLOUR), linewidth=2.5)
        )


def _path_markers(ax, centres, n_steps: int, marker: float = 1.0) -> list:
    """The start ring and the end square (``marker`` scales them); returns their legend handles."""
    start = ax.plot(
        *centres[0],
        marker="o",
        markersize=15 * marker,
        markerfacecolor="none",
        markeredgewidth=3,
        markeredgecolor=_rgb(START_COLOUR),
        linestyle="none",
        label="start",
    )[0]
    end = ax.plot(
        *centres[-1],
        marker="s",
        markersize=9 * marker,
        color=_rgb(END_COLOUR),
        markeredgecolor="black",
        linestyle="none",
        label=f"end (after {_count(n_steps, 'step')})",
    )[0]
    return [start, end]


def inset_box(boxes, width0: float, height0: float, small: float = 0.1, min_zoom: float = 3.0):
    """The level-0 box ``(left, top, right, bottom)`` a zoomed inset shows: around the path's views that are
    hard to see on the whole slide (side under ``small`` of its longer side), square, padded to four times the
    smallest of them; None when there are none or the inset would enlarge less than ``min_zoom`` times."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    longer = max(width0, height0)
    sides = np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1])
    fine = b[sides < small * longer]
    if not len(fine):
        return None
    left, top, right, bottom = fine[:, 0].min(), fine[:, 1].min(), fine[:, 2].max(), fine[:, 3].max()
    side = max(right - left, bottom - top, 4 * sides[sides < small * longer].min()) * 1.3
    if longer / side < min_zoom:
        return None
    cx, cy = (left + right) / 2, (top + bottom) / 2
    return cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2


def trajectory_figure(
    env, z, x=None, y=None, title: str = "", max_side: int = 640, slide_index: int | None = None, inset: bool = True
):
    """A matplotlib Figure (Agg canvas attached) of one trajectory over the thumbnail of the episode's own
    slide: sequences ``z, x, y`` of one episode (first entry: the view at reset), or a stacked ``EnvState``
    (e.g. from ``lax.scan``) as ``z``; ``slide_index`` (default: the state's ``slide_index``, else 0) picks the
    slide of a dataset. The title gets the slide's name.

    Axes are in level-0 px. Each view is a box coloured by its level (blue coarsest → red finest,
    :func:`level_colour`), the path joins the view centres (each step coloured by the level it moved
    to), the tumour is outlined in green, the start is a cyan ring (visible around the end when a
    zoom kept the centre) and the end a red square with its box drawn thick; a legend names all of them.
    With ``inset``, views too small to see on the whole slide (fine levels of a large slide) get a zoomed
    inset around them (:func:`inset_box`), drawn from a finer level, in the corner away from the path.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    if slide_index is None:
        slide_index = int(np.asarray(getattr(z, "slide_index", 0)).ravel()[0])
    z, x, y = _zxy(z, x, y)
    image, scale = _canvas(env, max_side, slide_index)
    width0, height0 = image.width / scale, image.height / scale
    aspect = image.height / image.width
    image_width = min(6.5, 7.0 / aspect)  # inches: at most 6.5 wide and 7 high
    fig = Figure(figsize=(image_width + 3.2, max(image_width * aspect, 2.5) + 1.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.imshow(np.asarray(image), extent=(0, width0, height0, 0), interpolation="antialiased")
    handles = []
    rings = tumour_rings(env, slide_index)
    for ring in rings:
        ax.plot(ring[:, 0], ring[:, 1], color=_rgb(TUMOUR_COLOUR), linewidth=1.5)
    if rings:
        handles.append(Line2D([], [], color=_rgb(TUMOUR_COLOUR), linewidth=1.5, label="tumour"))
    boxes = [view_box_level0(env, zi, xi, yi, slide_index) for zi, xi, yi in zip(z, x, y)]
    centres = np.array([((b[0] + b[2]) / 2, (b[1] + b[3]) / 2) for b in boxes]).reshape(-1, 2)
    _draw_path(ax, env, z, boxes, centres)
    downsamples = bundle_of(env, slide_index).downsamples
    for k in range(env.n_levels):
        seen = "" if k in set(z.tolist()) else ", not visited"
        handles.append(
            Line2D(
                [],
                [],
                color=_rgb(level_colour(k, env.n_levels)),
                linewidth=2.2,
                label=f"level {k}: downsample {downsamples[k]:.3g}{seen}",
            )
        )
    if len(centres):
        handles += _path_markers(ax, centres, len(z) - 1)
    ax.set_xlim(0, width0)
    ax.set_ylim(height0, 0)
    ax.set_xlabel("x (level-0 px)")
    ax.set_ylabel("y (level-0 px)")
    zoom = inset_box(boxes, width0, height0) if inset else None
    if zoom is not None:

        def path(axin):
            _draw_path(axin, env, z, boxes, centres)
            _path_markers(axin, centres, len(z) - 1, marker=0.7)

        _inset(ax, env, slide_index, zoom, rings, width0, height0, path)
    ax.legend(
        handles=handles,
        loc="upper left",
        bbox_to_anchor=(1.02, 1.0),
        fontsize="small",
        frameon=False,
        title="views (boxes) and path",
        title_fontsize="small",
        alignment="left",
    )
    ax.set_title(_titled(title, env, slide_index), fontsize="medium")
    return fig


def _inset(ax, env, slide_index: int, zoom, rings, width0: float, height0: float, draw):
    """A zoomed inset of level-0 box ``zoom`` (px) in the corner of ``ax`` farthest from it: the level's pixels
    (or feature map) there, the tumour outline, and whatever ``draw(axin)`` adds (the path, the views read)."""
    cx, cy = (zoom[0] + zoom[2]) / 2, (zoom[1] + zoom[3]) / 2
    left_side = cx > width0 / 2  # the path is on the right: the inset goes left
    bottom_side = cy < height0 / 2  # the path is in the upper half: the inset goes down (y axis points down)
    axin = ax.inset_axes([0.02 if left_side else 0.56, 0.02 if bottom_side else 0.56, 0.42, 0.42])
    crop = _level_crop(env, slide_index, zoom)
    if crop is not None:
        pixels, (l0, t0, r0, b0) = crop
        axin.imshow(pixels, extent=(l0, r0, b0, t0), interpolation="antialiased")
    for ring in rings:
        axin.plot(ring[:, 0], ring[:, 1], color=_rgb(TUMOUR_COLOUR), linewidth=1.5)
    draw(axin)
    axin.set_xlim(zoom[0], zoom[2])
    axin.set_ylim(zoom[3], zoom[1])
    axin.set_xticks([])
    axin.set_yticks([])
    axin.set_title(f"zoomed ×{max(1, round(width0 / (zoom[2] - zoom[0])))}", fontsize="x-small", pad=2)
    ax.indicate_inset_zoom(axin, edgecolor="black")
    return axin


def figure_rgb(fig) -> np.ndarray:
    """Draw a matplotlib Figure, cropped to what it shows (labels and legend included); RGB uint8
    ``(H, W, 3)``."""
    import io

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight", pad_inches=0.15)
    buffer.seek(0)
    with Image.open(buffer) as image:
        return np.asarray(image.convert("RGB"))


def render_trajectory(
    env,
    z,
    x=None,
    y=None,
    path=None,
    title: str = "",
    max_side: int = 640,
    slide_index: int | None = None,
    inset: bool = True,
) -> np.ndarray:
    """Draw a trajectory over the thumbnail (:func:`trajectory_figure`): sequences ``z, x, y`` of one
    episode, or a stacked ``EnvState`` as the only positional argument after ``env``. Saves a PNG to
    ``path`` when given. Returns the RGB uint8 picture ``(H, W, 3)``."""
    fig = trajectory_figure(env, z, x, y, title=title, max_side=max_side, slide_index=slide_index, inset=inset)
    return _save(figure_rgb(fig), path)


def _save(picture: np.ndarray, path) -> np.ndarray:
    if path is not None:
        with atomic_file(path) as tmp:  # the previous picture or the new one, never half of one
            Image.fromarray(picture).save(tmp, format="PNG")
    return picture


# ----------------------------------------------------------------------------- reading map
def reading_record(record, x=None, y=None, length=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(z, x, y)`` int arrays of the views one episode saw, in order (entry 0: the view at reset):
    from a dict with ``"z", "x", "y"`` (and optionally ``"length"``: entries past ``length + 1`` are
    dropped), three sequences, or a stacked ``EnvState``."""
    if isinstance(record, dict):
        length = record.get("length", length)
        z, x, y = record["z"], record["x"], record["y"]
    else:
        z = record
    z, x, y = _zxy(z, x, y)
    if length is not None:
        n = int(np.asarray(length)) + 1
        z, x, y = z[:n], x[:n], y[:n]
    return z, x, y


def reading_order(z, x, y) -> list[tuple[tuple[int, int, int], int, int]]:
    """The distinct views of a trajectory, in the order first seen: ``[((z, x, y), first step, times seen), ...]``."""
    first, count = {}, {}
    for step, view in enumerate(zip(*(np.asarray(a).tolist() for a in (z, x, y)))):
        first.setdefault(view, step)
        count[view] = count.get(view, 0) + 1
    return [(view, first[view], count[view]) for view in first]


def reading_map_figure(
    env, params, record, slide_index: int | None = None, score=None, title: str = "", max_side: int = 640
):
    """A matplotlib Figure of **where a policy read** on one slide: over the thumbnail of the episode's slide,
    each distinct view it visited (from the per-step record ``record``, see :func:`reading_record`) is a box
    filled by the step it was first visited (colour bar; step 0 is the view at reset) with a dot at its
    centre (visible however small the view; views too small to see get a zoomed inset, :func:`inset_box`),
    the tumour outlined in green. The title names the slide, its
    label (``params.slide.slide_label``: tumour / normal) and ``score`` (a float: the policy's tumour score;
    a string: shown as it is). Axes in level-0 px."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Rectangle

    if slide_index is None:
        slide_index = int(
            np.asarray(
                record.get("slide", 0) if isinstance(record, dict) else getattr(record, "slide_index", 0)
            ).ravel()[0]
        )
    z, x, y = reading_record(record)
    views = reading_order(z, x, y)
    image, scale = _canvas(env, max_side, slide_index)
    width0, height0 = image.width / scale, image.height / scale
    aspect = image.height / image.width
    image_width = min(6.5, 7.0 / aspect)
    fig = Figure(figsize=(image_width + 2.6, max(image_width * aspect, 2.5) + 1.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.imshow(np.asarray(image), extent=(0, width0, height0, 0), interpolation="antialiased")
    rings = tumour_rings(env, slide_index)
    for ring in rings:
        ax.plot(ring[:, 0], ring[:, 1], color=_rgb(TUMOUR_COLOUR), linewidth=1.5)
    cmap, norm = colormaps["viridis"], Normalize(0, max(1, len(z) - 1))
    boxes = [view_box_level0(env, zi, xi, yi, slide_index) for (zi, xi, yi), _, _ in views]

    def draw(on):  # the views: boxes filled by first visit, a dot at each centre
        for ((zi, _, _), first, _), (left, top, right, bottom) in zip(views, boxes):
            c = cmap(norm(first))
            fill = 0.12 + 0.4 * zi / max(env.n_levels - 1, 1)  # coarse views (large boxes) lighter, fine ones solid
            on.add_patch(
                Rectangle((left, top), right - left, bottom - top, facecolor=(*c[:3], fill), edgecolor=c, linewidth=1.2)
            )
        if boxes:
            b = np.asarray(boxes)
            return on.scatter(
                (b[:, 0] + b[:, 2]) / 2,
                (b[:, 1] + b[:, 3]) / 2,
                c=[v[1] for v in views],
                cmap=cmap,
                norm=norm,
                s=18,
                edgecolors="white",
                linewidths=0.6,
                zorder=3,
            )
        return None

    dots = draw(ax)
    ax.set_xlim(0, width0)
    ax.set_ylim(height0, 0)
    ax.set_xlabel("x (level-0 px)")
    ax.set_ylabel("y (level-0 px)")
    zoom = inset_box(boxes, width0, height0) if boxes else None
    if zoom is not None:  # views too small to see on the whole slide: a zoomed inset around them
        _inset(ax, env, slide_index, zoom, rings, width0, height0, draw)
    if dots is not None:
        bar = fig.colorbar(dots, ax=ax, fraction=0.04, pad=0.02)
        bar.set_label("step first visited (0: the view at reset)")
        if len(z) - 1 <= 10:
            bar.set_ticks(range(len(z)))
    handles = [Line2D([], [], color=_rgb(TUMOUR_COLOUR), linewidth=1.5, label="tumour")] if rings else []
    handles.append(
        Rectangle(
            (0, 0),
            1,
            1,
            facecolor=(0.5, 0.5, 0.5, 0.45),
            edgecolor="grey",
            label=visited_words(
                views,
                len(z) - 1,
                env.n_levels,
                record.get("fraction_read") if isinstance(record, dict) else None,
                getattr(getattr(env, "action", None), "name", "") == "glimpse",
            ),
        )
    )
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(0.0, -0.12), fontsize="small", frameon=False)
    ax.set_title(
        _titled("\n".join(t for t in (title, _label_and_score(params, slide_index, score)) if t), env, slide_index),
        fontsize="medium",
    )
    return fig


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def visited_words(views, steps: int, n_levels: int, fraction_read=None, reveals: bool = False) -> str:
    """The reading map's legend for the views an episode stood on (``views``: :func:`reading_order`'s
    ``((z, x, y), first step, ...)``) in ``steps`` steps, with how many lie at the finest level ``n_levels − 1``:
    only finest views count as read (the fraction read is of the finest level's tissue views), so a map of coarse
    views says why it stands beside "0 % read". ``reveals`` (a set reader, ``glimpse``): the cells it picks at a
    coarser level reveal the finest views under them, so the legend says so and gives ``fraction_read`` (the
    episode's fraction of the tissue read), the figure its table prints."""
    levels = sorted({int(v[0][0]) for v in views})
    finest = sum(int(v[0][0]) == n_levels - 1 for v in views)
    head = f"{_count(len(views), 'view')} stood on in {_count(steps, 'step')} (levels {levels}; fill: darker at finer levels)"
    known = fraction_read is not None and np.isfinite(float(fraction_read))
    said = f"{float(fraction_read):.1%} of the tissue's finest views read" if known else ""
    if reveals:
        return (
            f"{head}\neach cell picked reveals the finest views (level {n_levels - 1}) under it, which count as read"
            + (f": {said}" if said else "")
        )
    return f"{head}\n{finest} of them at the finest level ({n_levels - 1}), the only views counted as read" + (
        f" ({said})" if said else ""
    )


def _label_and_score(params, slide_index: int, score) -> str:
    label = None
    if params is not None and getattr(params.slide, "slide_label", None) is not None:
        labels = np.asarray(params.slide.slide_label)
        label = int(labels if labels.ndim == 0 else labels[slide_index])
    parts = [] if label is None else [f"{'tumour' if label else 'normal'} slide"]
    if isinstance(score, str):
        parts.append(score)
    elif score is not None and np.isfinite(score):
        parts.append(f"tumour score {float(score):.3f}")
    return ", ".join(parts)


def render_reading_map(
    env, params, record, slide_index: int | None = None, score=None, path=None, title: str = "", max_side: int = 640
) -> np.ndarray:
    """Draw :func:`reading_map_figure` (where a policy read on one slide; ``record`` the episode's per-step
    ``z, x, y``); saves a PNG to ``path`` when given. Returns the RGB uint8 picture ``(H, W, 3)``."""
    fig = reading_map_figure(env, params, record, slide_index=slide_index, score=score, title=title, max_side=max_side)
    return _save(figure_rgb(fig), path)


# ----------------------------------------------------------------------------- GIF
def feature_heatmap(env, params, slide_index: int, z: int):
    """The heat map a feature-only slide shows instead of its pixels at scenario level ``z``:
    ``(values (gh, gw) float32, stride px, label)``, or None when the slide has no feature grid. pcam-cnn's
    features give their tumour logit (entry :data:`data_tools.features.pcam_cnn.VIEW_LOGIT`); other encoders,
    which have none, the distance of each cell's features from the slide level's median (how unlike the
    typical cell it is), said in the label."""
    from data_tools.features import pcam_cnn

    slides = getattr(params, "slide", None)
    if slides is None or slides.features is None:
        return None
    s = slides.select(int(slide_index))
    off = int(np.asarray(s.feature_offset)[z])
    gw, gh = int(np.asarray(s.feature_grid_width)[z]), int(np.asarray(s.feature_grid_height)[z])
    grid = np.asarray(s.features[off : off + gw * gh], np.float32).reshape(gh, gw, -1)
    encoder = (dict(bundle_of(env, slide_index).metadata).get("features") or {}).get("encoder") or "unknown encoder"
    if str(encoder).startswith(pcam_cnn.NAME) and grid.shape[-1] > pcam_cnn.VIEW_LOGIT:
        return (
            grid[..., pcam_cnn.VIEW_LOGIT],
            int(np.asarray(s.feature_stride)),
            f"tumour logit ({encoder}, feature {pcam_cnn.VIEW_LOGIT})",
        )
    flat = grid.reshape(-1, grid.shape[-1])
    values = np.linalg.norm(grid - np.median(flat, axis=0), axis=-1)
    return values, int(np.asarray(s.feature_stride)), f"|features - median| ({encoder}: no tumour logit)"


def _heat_panel(heat, x: int, y: int, tile: int, side: int, limits) -> Image.Image:
    """The view's neighbourhood on a feature heat map (two views each side), the view outlined, captioned."""
    from matplotlib import colormaps

    values, stride, label = heat
    per_view = max(1, tile // max(stride, 1))
    fx, fy = int(round(x / max(stride, 1))), int(round(y / max(stride, 1)))
    r = 2 * per_view
    window = np.full((per_view + 2 * r, per_view + 2 * r), np.nan, np.float32)
    gh, gw = values.shape
    y0, x0 = fy - r, fx - r
    ys, xs = slice(max(0, y0), min(gh, y0 + window.shape[0])), slice(max(0, x0), min(gw, x0 + window.shape[1]))
    window[ys.start - y0 : ys.stop - y0, xs.start - x0 : xs.stop - x0] = values[ys, xs]
    lo, hi = limits
    rgba = colormaps["YlOrRd"](np.clip((window - lo) / max(hi - lo, 1e-9), 0, 1))  # low: pale, high: dark red
    rgb = (rgba[..., :3] * 255).astype(np.uint8)
    rgb[np.isnan(window)] = (200, 200, 200)
    panel = Image.fromarray(rgb).resize((side, side), Image.NEAREST)
    draw = ImageDraw.Draw(panel)
    cell = side / window.shape[0]
    draw.rectangle(
        [r * cell, r * cell, (r + per_view) * cell - 1, (r + per_view) * cell - 1], outline=(0, 200, 255), width=3
    )
    draw.rectangle([0, 0, side, 14], fill=(255, 255, 255))
    draw.text((3, 2), f"{label}: {lo:.2g} to {hi:.2g}", fill=(0, 0, 0))
    return panel


def animate(
    env,
    z,
    x=None,
    y=None,
    path="trajectory.gif",
    fps: int = 4,
    max_side: int = 480,
    slide_index: int | None = None,
    params=None,
) -> Path:
    """Write a GIF (Pillow, no ffmpeg) of a trajectory (``z, x, y`` sequences, first entry the view at
    reset, or a stacked ``EnvState``) on its own slide (``slide_index``, default the state's, else 0):
    each frame shows the thumbnail with the current view box beside the view itself. A feature-only
    slide keeps no pixels there: the view panel shows the features as a heat map around the view
    (:func:`feature_heatmap`, from ``params``, default the env's; its range and what it is are written
    on it). Returns the path."""
    if slide_index is None:
        slide_index = int(np.asarray(getattr(z, "slide_index", 0)).ravel()[0])
    params = params if params is not None else getattr(env, "default_params", None)
    bundle = bundle_of(env, slide_index)
    base, scale = _thumbnail_with_tumour(env, max_side, slide_index)  # drawn once, boxes per frame
    heats = {}
    frames = []
    for zi, xi, yi in zip(*_zxy(z, x, y)):
        s = types.SimpleNamespace(z=zi, x=xi, y=yi, slide_index=slide_index)  # a concrete state
        overview = _draw_view(base.copy(), env, s, scale, slide_index)
        level = bundle.pixels[zi]
        side = overview.height
        if getattr(level, "has_pixels", True):
            view = Image.fromarray(np.asarray(level[yi : yi + env.tile_size, xi : xi + env.tile_size]))
            view = view.resize((side, side), Image.NEAREST)
        else:  # a feature-only bundle keeps no pixels at this level: its features as a heat map
            if zi not in heats:
                heat = feature_heatmap(env, params, slide_index, int(zi))
                heats[zi] = heat if heat is None else (heat, tuple(np.nanpercentile(heat[0], [1, 99]).tolist()))
            if heats[zi] is None:
                view = Image.new("RGB", (side, side), (200, 200, 200))
                ImageDraw.Draw(view).text((4, 4), "no pixels or features at this level", fill=(0, 0, 0))
            else:
                view = _heat_panel(heats[zi][0], int(xi), int(yi), env.tile_size, side, heats[zi][1])
        frame = Image.new("RGB", (overview.width + view.width, overview.height), (255, 255, 255))
        frame.paste(overview, (0, 0))
        frame.paste(view, (overview.width, 0))
        # Pillow's default RGB → palette conversion (median cut) took ~0.8 s a frame; fast octree ~10 ms
        frames.append(frame.quantize(colors=256, method=Image.Quantize.FASTOCTREE))
    path = Path(path)
    with atomic_file(path) as tmp:
        frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    return path
