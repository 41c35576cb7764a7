"""Pictures on the host (numpy + Pillow): the slide thumbnail, the tumour outline, view boxes,
trajectories and GIFs. Not jittable and not meant to be: call with concrete states."""
from __future__ import annotations

import json
import types
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

TUMOUR_COLOUR = (0, 170, 0)
START_COLOUR = (0, 200, 255)
END_COLOUR = (255, 0, 0)


def level_colour(z: int, n_levels: int) -> tuple[int, int, int]:
    """Blue (coarsest) → red (finest)."""
    f = z / max(n_levels - 1, 1)
    return int(40 + 215 * f), int(60 * (1 - f)), int(255 * (1 - f))


def bundle_of(env, slide_index: int = 0):
    """The host bundle of slide ``slide_index`` of ``env`` (datasets have one per slide)."""
    bundles = getattr(env, "_bundles", ()) or (env._bundle,)
    return bundles[int(slide_index)]


def _canvas(env, max_side: int, slide_index: int = 0):
    """The slide drawn at most ``max_side`` px a side from the coarsest env level that is at least
    that large (else the finest). Returns ``(PIL image, canvas px per level-0 px)``."""
    bundle = bundle_of(env, slide_index)
    k = next((i for i, p in enumerate(bundle.pixels) if max(p.shape[:2]) >= max_side), len(bundle.pixels) - 1)
    level = np.asarray(bundle.pixels[k])
    fit = min(1.0, max_side / max(level.shape[:2]))
    size = (max(1, round(level.shape[1] * fit)), max(1, round(level.shape[0] * fit)))
    image = Image.fromarray(level).resize(size, Image.Resampling.BOX)
    return image, size[0] / (level.shape[1] * bundle.metadata["levels"][k]["downsample"])


def _draw_tumour(draw: ImageDraw.ImageDraw, env, scale: float, slide_index: int = 0) -> None:
    path = Path(bundle_of(env, slide_index).path) / "annotations.geojson"
    if not path.is_file():
        return
    import shapely.geometry

    for feature in json.loads(path.read_text()).get("features", []):
        if feature.get("properties", {}).get("label", "tumour") != "tumour":
            continue
        geom = shapely.geometry.shape(feature["geometry"])
        for poly in getattr(geom, "geoms", [geom]):
            for ring in [poly.exterior, *poly.interiors]:
                pts = [(x * scale, y * scale) for x, y in ring.coords]
                if len(pts) > 1:
                    draw.line(pts, fill=TUMOUR_COLOUR, width=2)


def view_box_level0(env, z: int, x: int, y: int, slide_index: int = 0) -> tuple[float, float, float, float]:
    """The view at ``(z, x, y)`` as a level-0 px box ``(left, top, right, bottom)``."""
    d = bundle_of(env, slide_index).metadata["levels"][int(z)]["downsample"]
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


def render_trajectory(env, z, x=None, y=None, path=None, title: str = "", max_side: int = 640,
                      slide_index: int | None = None) -> np.ndarray:
    """Draw a trajectory over the thumbnail: sequences ``z, x, y`` of one episode, or a stacked
    ``EnvState`` (e.g. from ``lax.scan``) as the only positional argument after ``env``.

    Views are boxes coloured by level (blue coarsest → red finest), their centres joined by a
    path coloured by the level it moved to; the start is a cyan dot, the end a red square and box. Saves a PNG to ``path`` when given.
    Returns the RGB uint8 picture.
    """
    if slide_index is None:
        slide_index = int(np.asarray(getattr(z, "slide_index", 0)).ravel()[0])
    z, x, y = _zxy(z, x, y)
    image, scale = _canvas(env, max_side, slide_index)
    draw = ImageDraw.Draw(image)
    _draw_tumour(draw, env, scale, slide_index)
    centres = []
    for zi, xi, yi in zip(z, x, y):
        box = [v * scale for v in view_box_level0(env, zi, xi, yi, slide_index)]
        draw.rectangle(box, outline=level_colour(zi, env.n_levels), width=1)
        centres.append(((box[0] + box[2]) / 2, (box[1] + box[3]) / 2))
    for (a, b), zi in zip(zip(centres[:-1], centres[1:]), z[1:]):
        draw.line([a, b], fill=level_colour(zi, env.n_levels), width=3)
    if centres:
        last = [v * scale for v in view_box_level0(env, z[-1], x[-1], y[-1], slide_index)]
        draw.rectangle(last, outline=END_COLOUR, width=3)
    if centres:
        (sx, sy), (ex, ey) = centres[0], centres[-1]
        draw.ellipse([sx - 6, sy - 6, sx + 6, sy + 6], fill=START_COLOUR, outline=(0, 0, 0))
        draw.rectangle([ex - 6, ey - 6, ex + 6, ey + 6], fill=END_COLOUR, outline=(0, 0, 0))
    legend = " ".join(f"z{k}" for k in range(env.n_levels))
    draw.text((6, 6), f"{title}  levels {legend} (blue coarse -> red fine)".strip(), fill=(0, 0, 0))
    if path is not None:
        image.save(path)
    return np.asarray(image)


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
        view = Image.fromarray(np.asarray(level[yi:yi + env.tile_size, xi:xi + env.tile_size]))
        view = view.resize((overview.height, overview.height), Image.NEAREST)
        frame = Image.new("RGB", (overview.width + view.width, overview.height), (255, 255, 255))
        frame.paste(overview, (0, 0))
        frame.paste(view, (overview.width, 0))
        # Pillow's default RGB → palette conversion (median cut) took ~0.8 s a frame; fast octree ~10 ms
        frames.append(frame.quantize(colors=256, method=Image.Quantize.FASTOCTREE))
    path = Path(path)
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    return path
