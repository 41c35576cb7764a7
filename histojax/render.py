"""Pictures on the host: the slide thumbnail, the tumour outline, view boxes (Pillow), trajectories
(matplotlib, Agg canvas: no display needed) and GIFs (Pillow). Not jittable and not meant to be: call
with concrete states."""
from __future__ import annotations

import json
import types
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from data_tools.bundle_format import ANNOTATIONS, atomic_file

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


def _canvas(env, max_side: int, slide_index: int = 0):
    """The slide drawn at most ``max_side`` px a side from the coarsest env level that is at least
    that large (else the finest). Returns ``(PIL image, canvas px per level-0 px)``."""
    bundle = bundle_of(env, slide_index)
    with_pixels = [i for i, p in enumerate(bundle.pixels) if getattr(p, "has_pixels", True)]  # coarsest first
    k = next((i for i in with_pixels if max(bundle.pixels[i].shape[:2]) >= max_side), with_pixels[-1])
    level = np.asarray(bundle.pixels[k])
    fit = min(1.0, max_side / max(level.shape[:2]))
    size = (max(1, round(level.shape[1] * fit)), max(1, round(level.shape[0] * fit)))
    image = Image.fromarray(level).resize(size, Image.Resampling.BOX)
    return image, size[0] / (level.shape[1] * bundle.downsamples[k])


def tumour_rings(env, slide_index: int = 0) -> list[np.ndarray]:
    """The tumour outline of a slide of ``env`` as rings ``(N, 2)`` of level-0 px ``(x, y)``
    (exteriors and holes; empty when the bundle has no annotations)."""
    path = Path(bundle_of(env, slide_index).path) / ANNOTATIONS
    if not path.is_file():
        return []
    import shapely.geometry

    rings = []
    for feature in json.loads(path.read_text()).get("features", []):
        if feature.get("properties", {}).get("label", "tumour") != "tumour":
            continue
        geom = shapely.geometry.shape(feature["geometry"])
        for poly in getattr(geom, "geoms", [geom]):
            rings += [np.asarray(ring.coords, np.float64) for ring in [poly.exterior, *poly.interiors]
                      if len(ring.coords) > 1]
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


def trajectory_figure(env, z, x=None, y=None, title: str = "", max_side: int = 640,
                      slide_index: int | None = None):
    """A matplotlib Figure (Agg canvas attached) of one trajectory over the slide thumbnail: sequences
    ``z, x, y`` of one episode, or a stacked ``EnvState`` (e.g. from ``lax.scan``) as ``z``.

    Axes are in level-0 px. Each view is a box coloured by its level (blue coarsest → red finest,
    :func:`level_colour`), the path joins the view centres (each step coloured by the level it moved
    to), the tumour is outlined in green, the start is a cyan ring (visible around the end when a
    zoom kept the centre) and the end a red square with its box drawn thick; a legend names all of them.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Rectangle

    if slide_index is None:
        slide_index = int(np.asarray(getattr(z, "slide_index", 0)).ravel()[0])
    z, x, y = _zxy(z, x, y)
    image, scale = _canvas(env, max_side, slide_index)
    width0, height0 = image.width / scale, image.height / scale
    colour = lambda k: tuple(c / 255 for c in level_colour(int(k), env.n_levels))  # noqa: E731
    aspect = image.height / image.width
    image_width = min(6.5, 7.0 / aspect)  # inches: at most 6.5 wide and 7 high
    fig = Figure(figsize=(image_width + 3.2, max(image_width * aspect, 2.5) + 1.0), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.imshow(np.asarray(image), extent=(0, width0, height0, 0), interpolation="antialiased")
    handles = []
    rings = tumour_rings(env, slide_index)
    for ring in rings:
        ax.plot(ring[:, 0], ring[:, 1], color=tuple(c / 255 for c in TUMOUR_COLOUR), linewidth=1.5)
    if rings:
        handles.append(Line2D([], [], color=tuple(c / 255 for c in TUMOUR_COLOUR), linewidth=1.5, label="tumour"))
    boxes = [view_box_level0(env, zi, xi, yi, slide_index) for zi, xi, yi in zip(z, x, y)]
    for (left, top, right, bottom), zi in zip(boxes, z):
        ax.add_patch(Rectangle((left, top), right - left, bottom - top, fill=False, edgecolor=colour(zi),
                               linewidth=0.9))
    centres = np.array([((b[0] + b[2]) / 2, (b[1] + b[3]) / 2) for b in boxes]).reshape(-1, 2)
    if len(centres) > 1:
        ax.add_collection(LineCollection(np.stack([centres[:-1], centres[1:]], axis=1),
                                         colors=[colour(k) for k in z[1:]], linewidths=2.2))
    downsamples = bundle_of(env, slide_index).downsamples
    for k in range(env.n_levels):
        seen = "" if k in set(z.tolist()) else ", not visited"
        handles.append(Line2D([], [], color=colour(k), linewidth=2.2,
                              label=f"level {k}: downsample {downsamples[k]:.3g}{seen}"))
    if len(centres):
        left, top, right, bottom = boxes[-1]
        ax.add_patch(Rectangle((left, top), right - left, bottom - top, fill=False,
                               edgecolor=tuple(c / 255 for c in END_COLOUR), linewidth=2.5))
        start = ax.plot(*centres[0], marker="o", markersize=15, markerfacecolor="none", markeredgewidth=3,
                        markeredgecolor=tuple(c / 255 for c in START_COLOUR), linestyle="none", label="start")[0]
        end = ax.plot(*centres[-1], marker="s", markersize=9, color=tuple(c / 255 for c in END_COLOUR),
                      markeredgecolor="black", linestyle="none", label=f"end (after {len(z) - 1} steps)")[0]
        handles += [start, end]
    ax.set_xlim(0, width0)
    ax.set_ylim(height0, 0)
    ax.set_xlabel("x (level-0 px)")
    ax.set_ylabel("y (level-0 px)")
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small", frameon=False,
              title="views (boxes) and path", title_fontsize="small", alignment="left")
    if title:
        ax.set_title(title, fontsize="medium")
    return fig


def figure_rgb(fig) -> np.ndarray:
    """Draw a matplotlib Figure, cropped to what it shows (labels and legend included); RGB uint8
    ``(H, W, 3)``."""
    import io

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", bbox_inches="tight", pad_inches=0.15)
    buffer.seek(0)
    with Image.open(buffer) as image:
        return np.asarray(image.convert("RGB"))


def render_trajectory(env, z, x=None, y=None, path=None, title: str = "", max_side: int = 640,
                      slide_index: int | None = None) -> np.ndarray:
    """Draw a trajectory over the thumbnail (:func:`trajectory_figure`): sequences ``z, x, y`` of one
    episode, or a stacked ``EnvState`` as the only positional argument after ``env``. Saves a PNG to
    ``path`` when given. Returns the RGB uint8 picture ``(H, W, 3)``."""
    fig = trajectory_figure(env, z, x, y, title=title, max_side=max_side, slide_index=slide_index)
    picture = figure_rgb(fig)
    if path is not None:
        with atomic_file(path) as tmp:  # the previous picture or the new one, never half of one
            Image.fromarray(picture).save(tmp, format="PNG")
    return picture


def animate(env, z, x=None, y=None, path="trajectory.gif", fps: int = 4, max_side: int = 480,
            slide_index: int | None = None) -> Path:
    """Write a GIF (Pillow, no ffmpeg) of a trajectory (``z, x, y`` sequences or a stacked
    ``EnvState``): each frame shows the thumbnail with the current view box beside the view
    itself. Returns the path."""
    if slide_index is None:
        slide_index = int(np.asarray(getattr(z, "slide_index", 0)).ravel()[0])
    bundle = bundle_of(env, slide_index)
    base, scale = _thumbnail_with_tumour(env, max_side, slide_index)  # drawn once, boxes per frame
    frames = []
    for zi, xi, yi in zip(*_zxy(z, x, y)):
        s = types.SimpleNamespace(z=zi, x=xi, y=yi, slide_index=slide_index)  # a concrete state
        overview = _draw_view(base.copy(), env, s, scale, slide_index)
        level = bundle.pixels[zi]
        if getattr(level, "has_pixels", True):
            view = Image.fromarray(np.asarray(level[yi:yi + env.tile_size, xi:xi + env.tile_size]))
        else:  # a feature-only bundle keeps no pixels at this level: a grey view
            view = Image.new("RGB", (env.tile_size, env.tile_size), (200, 200, 200))
        view = view.resize((overview.height, overview.height), Image.NEAREST)
        frame = Image.new("RGB", (overview.width + view.width, overview.height), (255, 255, 255))
        frame.paste(overview, (0, 0))
        frame.paste(view, (overview.width, 0))
        # Pillow's default RGB → palette conversion (median cut) took ~0.8 s a frame; fast octree ~10 ms
        frames.append(frame.quantize(colors=256, method=Image.Quantize.FASTOCTREE))
    path = Path(path)
    with atomic_file(path) as tmp:
        frames[0].save(tmp, format="GIF", save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    return path
