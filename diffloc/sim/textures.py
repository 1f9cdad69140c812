"""Albedo textures of the simulated worlds: real photographs mixed with procedural patterns.

Every material is an (S, S, 3) float32 image in [0, 1], gamma-encoded like a photograph. The
catalogue :data:`MATERIALS` is fixed: each entry has a name, a recipe and the size of one texture
repeat in metres (``repeat_m``; 0 means the texture is stretched once over each face, as for a
poster or a window). Recipes draw only from the generator they are given, so a catalogue made
twice from equal generators is identical.

Surfaces that tile (floors, walls, ground) are seamless: procedural patterns are periodic by
construction (noise is synthesised in the Fourier domain, grids use integer repeat counts) and
tiled photographs are cross-faded with a half-period shifted copy of themselves. Textures are
kept busy on purpose (grain, speckle, joints, stains) because the rendered images feed keypoint
detectors. Photographs come from ``skimage.data`` and are limited to those bundled with the
package, so nothing is downloaded.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import skimage.data
from skimage.color import rgb2gray
from skimage.transform import resize

from diffloc.checks import check_shape

__all__ = [
    "BUNDLED_PHOTOS",
    "MATERIALS",
    "POSTERS",
    "MaterialSpec",
    "load_photo",
    "make_materials",
    "make_seamless",
    "material_repeat_m",
    "periodic_noise",
]

# Photographs shipped inside the scikit-image wheel (no pooch download needed). Others in
# ``skimage.data`` (brain, eagle, lily, skin, ...) are fetched from the network and never used.
BUNDLED_PHOTOS = (
    "astronaut",
    "brick",
    "camera",
    "chelsea",
    "coffee",
    "coins",
    "grass",
    "gravel",
    "hubble_deep_field",
    "immunohistochemistry",
    "moon",
    "page",
    "retina",
    "rocket",
    "stereo_motorcycle",
    "text",
)

Recipe = Callable[[np.random.Generator, int], np.ndarray]


@functools.cache
def _photo_readonly(name: str) -> np.ndarray:
    if name not in BUNDLED_PHOTOS:
        raise ValueError(f"unknown photo {name!r}; bundled photos are {list(BUNDLED_PHOTOS)}")
    try:
        image = getattr(skimage.data, name)()
    except Exception as error:  # a broken install; never download
        raise RuntimeError(
            f"could not load the bundled photo skimage.data.{name}(): {error}"
        ) from error
    if name == "stereo_motorcycle":
        image = image[0]
    image = np.asarray(image, dtype=np.float32) / 255.0
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    image = np.ascontiguousarray(image[:, :, :3])
    image.setflags(write=False)
    return image


def load_photo(name: str) -> np.ndarray:
    """A bundled scikit-image photograph as an (H, W, 3) float32 array in [0, 1] (a copy).

    Args:
        name: one of :data:`BUNDLED_PHOTOS`.

    Example:
        >>> load_photo("coffee").shape
        (400, 600, 3)
    """
    return _photo_readonly(name).copy()


def _square(
    image: np.ndarray, size: int, crop: tuple[float, float, float] = (0.5, 0.5, 1.0)
) -> np.ndarray:
    """Crop a square (centre fractions cy, cx; side fraction of the short side) and resize it.

    Args:
        image: (H, W, C) image.
        size: output side length.
        crop: (centre_y, centre_x, side) with the centre in [0, 1] image fractions and the side as
            a fraction of ``min(H, W)``.

    Returns:
        (size, size, C) float32 image.
    """
    height, width = image.shape[:2]
    side = max(8, int(round(min(height, width) * crop[2])))
    top = int(round(np.clip(crop[0] * height - side / 2, 0, height - side)))
    left = int(round(np.clip(crop[1] * width - side / 2, 0, width - side)))
    patch = image[top : top + side, left : left + side]
    factor = side // size
    if factor >= 2:  # box-filter down first: fast, and it removes the aliasing
        cut = (side // factor) * factor
        patch = (
            patch[:cut, :cut]
            .reshape(cut // factor, factor, cut // factor, factor, -1)
            .mean(axis=(1, 3))
        )
    out = resize(patch, (size, size), order=1, anti_aliasing=False, preserve_range=True)
    return out.astype(np.float32)


def periodic_noise(
    rng: np.random.Generator, size: int, beta: float = 2.0, stretch: float = 1.0
) -> np.ndarray:
    """Seamlessly tileable fractal noise with a power spectrum ~ 1 / f**beta.

    Synthesised in the Fourier domain, so it wraps perfectly in both directions.

    Args:
        rng: source of randomness.
        size: side length S of the square output.
        beta: spectral exponent; 0 is white noise, 2 is cloudy, 3 is very smooth.
        stretch: > 1 makes streaks along the image x axis (brushed metal, wood grain).

    Returns:
        (S, S) float32 field with zero mean and unit standard deviation.
    """
    fy = np.fft.fftfreq(size)[:, None]
    fx = np.fft.rfftfreq(size)[None, :]
    freq = np.sqrt((fx * stretch) ** 2 + fy**2)
    freq[0, 0] = 1.0
    amplitude = freq ** (-beta / 2.0)
    amplitude[0, 0] = 0.0
    shape = (size, size // 2 + 1)
    spectrum = amplitude * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))
    field = np.fft.irfft2(spectrum, s=(size, size))
    field = (field - field.mean()) / max(float(field.std()), 1e-12)
    return field.astype(np.float32)


def make_seamless(image: np.ndarray) -> np.ndarray:
    """Make a square image tile without seams by cross-fading it with a half-period shift.

    Along each axis in turn, the image is blended with a copy rolled by half its size using a
    weight that is 1 in the middle and 0 at the borders, so the borders come from the inside of
    the image. Contrast lost in the blend is restored (the two layers are nearly uncorrelated).

    Args:
        image: (S, S, C) float image.

    Returns:
        (S, S, C) float32 seamlessly tileable image.
    """
    check_shape(image, "S,S,C", "image")
    size = image.shape[0]
    out = image.astype(np.float32)
    weight = np.sin(np.pi * (np.arange(size) + 0.5) / size) ** 2
    norm = np.sqrt(weight**2 + (1.0 - weight) ** 2)
    for axis in (0, 1):
        shape = [1, 1, 1]
        shape[axis] = size
        w, n = weight.reshape(shape), norm.reshape(shape)
        mean = out.mean(axis=(0, 1), keepdims=True)
        rolled = np.roll(out, size // 2, axis=axis)
        out = mean + (w * (out - mean) + (1.0 - w) * (rolled - mean)) / n
    return out.astype(np.float32)


def _unit_noise(
    rng: np.random.Generator, size: int, beta: float, stretch: float = 1.0
) -> np.ndarray:
    """Tileable noise squashed to [0, 1] (about 0.5 +- 0.17 per standard deviation)."""
    return 0.5 + 0.5 * np.tanh(periodic_noise(rng, size, beta, stretch) / 3.0)


def _jitter(rng: np.random.Generator, color: Sequence[float], amount: float = 0.06) -> np.ndarray:
    """A base colour (3,) with a small random tint and brightness change."""
    color = np.asarray(color, dtype=np.float32)
    return np.clip(
        color * (1.0 + rng.uniform(-amount, amount)) + rng.uniform(-amount, amount, 3) * 0.5, 0, 1
    )


def _rgb(value: np.ndarray, color: np.ndarray) -> np.ndarray:
    """(S, S) intensity times a colour (3,) -> (S, S, 3) clipped to [0, 1]."""
    return np.clip(value[:, :, None] * color[None, None, :], 0.0, 1.0).astype(np.float32)


def _grid(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel-centre coordinates (S, S) in [0, 1): x (columns) and y (rows)."""
    t = (np.arange(size, dtype=np.float32) + 0.5) / size
    return np.meshgrid(t, t)


def _joints(frac: np.ndarray, width: float) -> np.ndarray:
    """1 inside a joint of relative ``width`` around integer positions of ``frac``, else 0."""
    distance = np.abs(frac - np.round(frac))
    return (distance < width / 2).astype(np.float32)


def _grain_detail(rng: np.random.Generator, size: int, strength: float) -> np.ndarray:
    """Multiplicative fine detail (S, S) around 1 mixing medium and fine tileable noise."""
    mid = periodic_noise(rng, size, 1.6)
    fine = periodic_noise(rng, size, 0.4)
    return 1.0 + strength * (0.6 * mid + 0.4 * fine) / 2.0


def _stains(rng: np.random.Generator, size: int, amount: float) -> np.ndarray:
    """Multiplicative blotchy darkening (S, S) in [1 - amount, 1]."""
    blotch = periodic_noise(rng, size, 2.6)
    return 1.0 - amount * np.clip(blotch - 0.8, 0.0, 1.5) / 1.5


# --------------------------------------------------------------------------- recipes


def _plaster(color: Sequence[float]) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        low = periodic_noise(rng, size, 3.0)
        mid = periodic_noise(rng, size, 1.8)
        fine = periodic_noise(rng, size, 0.3)
        value = 0.82 + 0.05 * low + 0.05 * mid + 0.045 * fine
        scuff = periodic_noise(rng, size, 1.2, stretch=2.5)
        value = value - 0.12 * (scuff > 1.9)
        return _rgb(value * _stains(rng, size, 0.12), _jitter(rng, color))

    return recipe


def _floor_tiles(color: Sequence[float], tiles: int, accent: Sequence[float]) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        x, y = _grid(size)
        ix, iy = np.floor(x * tiles).astype(int), np.floor(y * tiles).astype(int)
        shade = rng.uniform(0.82, 1.08, (tiles, tiles))[iy, ix]
        is_accent = rng.random((tiles, tiles)) < 0.18
        base, acc = _jitter(rng, color), _jitter(rng, accent)
        colors = np.where(is_accent[iy, ix][:, :, None], acc, base) * shade[:, :, None]
        marble = np.sin(8.0 * np.pi * (x + y) + 2.5 * periodic_noise(rng, size, 2.2))
        detail = _grain_detail(rng, size, 0.22) * (1.0 + 0.06 * marble)
        grout = np.maximum(_joints(x * tiles, 0.035), _joints(y * tiles, 0.035))
        image = colors * detail[:, :, None]
        image = image * (1 - grout[:, :, None]) + 0.32 * grout[:, :, None]
        return np.clip(image, 0, 1).astype(np.float32)

    return recipe


def _checker_marble(rng: np.random.Generator, size: int) -> np.ndarray:
    x, y = _grid(size)
    squares = 4
    dark = (np.floor(x * squares) + np.floor(y * squares)) % 2 == 1
    veins = np.abs(np.sin(6.0 * np.pi * x + 5.0 * periodic_noise(rng, size, 2.4)))
    value = 0.78 + 0.18 * veins + 0.05 * periodic_noise(rng, size, 0.8)
    light_c, dark_c = _jitter(rng, (0.95, 0.93, 0.88)), _jitter(rng, (0.28, 0.26, 0.3))
    image = np.where(dark[:, :, None], _rgb(value, dark_c), _rgb(value, light_c))
    grout = np.maximum(_joints(x * squares, 0.02), _joints(y * squares, 0.02))
    return np.clip(image * (1 - 0.5 * grout[:, :, None]), 0, 1).astype(np.float32)


def _carpet(color: Sequence[float]) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        x, y = _grid(size)
        loops = 24
        pattern = np.sin(2 * np.pi * loops * x) * np.sin(2 * np.pi * loops * y)
        motif = np.abs(np.sin(2 * np.pi * 3 * x) + np.sin(2 * np.pi * 3 * y)) > 1.2
        fibre = periodic_noise(rng, size, 0.0)
        value = (
            0.7
            + 0.08 * pattern
            + 0.12 * fibre
            + 0.12 * motif
            + 0.05 * periodic_noise(rng, size, 2.5)
        )
        return _rgb(value * _stains(rng, size, 0.15), _jitter(rng, color))

    return recipe


def _wood(color: Sequence[float], planks: int) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        x, y = _grid(size)
        row = np.floor(y * planks).astype(int)
        offsets = rng.random(planks)
        lengths = rng.choice([1, 2], planks)  # plank joints per repeat along x
        shade = rng.uniform(0.8, 1.15, (planks, 1)) * rng.uniform(0.95, 1.05, (planks, 3))
        warp = periodic_noise(rng, size, 2.5, stretch=4.0)
        rings = np.sin(2 * np.pi * (3 * y * planks + 0.8 * warp + 2 * offsets[row]))
        streaks = periodic_noise(rng, size, 1.0, stretch=6.0)
        value = 0.78 + 0.12 * rings + 0.07 * streaks
        plank_x = (x + offsets[row]) * lengths[row]
        plank_id = (np.floor(plank_x).astype(int) + 7 * row) % planks
        joints = np.maximum(_joints(y * planks, 0.04), _joints(plank_x, 0.012))
        base = _jitter(rng, color)
        image = _rgb(value, base) * shade[plank_id]
        image = image * (1 - 0.6 * joints[:, :, None])
        return np.clip(image, 0, 1).astype(np.float32)

    return recipe


def _concrete(color: Sequence[float]) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        x, y = _grid(size)
        value = 0.66 + 0.07 * periodic_noise(rng, size, 2.2) + 0.06 * periodic_noise(rng, size, 0.6)
        pores = periodic_noise(rng, size, 0.0) < -2.2
        value = value - 0.25 * pores
        formwork = np.maximum(_joints(y * 2, 0.01), _joints(x * 1, 0.008))
        value = value * (1 - 0.3 * formwork) * _stains(rng, size, 0.2)
        return _rgb(value, _jitter(rng, color))

    return recipe


def _ceiling_tiles(rng: np.random.Generator, size: int) -> np.ndarray:
    x, y = _grid(size)
    tiles = 4
    fissures = periodic_noise(rng, size, 0.2) < -1.6
    value = 0.88 + 0.03 * periodic_noise(rng, size, 1.5) - 0.22 * fissures
    rails = np.maximum(_joints(x * tiles, 0.05), _joints(y * tiles, 0.05))
    value = value * (1 - rails) + 0.62 * rails
    return _rgb(value, _jitter(rng, (0.97, 0.96, 0.93), 0.03))


def _bricks(color: Sequence[float], courses: int, per_course: int) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        x, y = _grid(size)
        course = np.floor(y * courses).astype(int)
        bx = x * per_course + 0.5 * (course % 2)
        brick = (np.floor(bx).astype(int) % per_course) + per_course * course
        count = courses * per_course
        shades = rng.uniform(0.72, 1.15, (count, 1)) * rng.uniform(0.92, 1.08, (count, 3))
        photo = rgb2gray(make_seamless(_square(load_photo("brick"), size, (0.5, 0.5, 0.5))))
        detail = 0.75 + 0.5 * (photo - photo.mean())
        base = _jitter(rng, color, 0.08)
        image = (
            base[None, None, :]
            * shades[brick]
            * (detail * _grain_detail(rng, size, 0.25))[:, :, None]
        )
        mortar = np.maximum(_joints(y * courses, 0.12), _joints(bx, 0.05))
        mortar_color = 0.75 * _unit_noise(rng, size, 0.5)[:, :, None] + 0.2
        image = image * (1 - mortar[:, :, None]) + mortar_color * mortar[:, :, None]
        return np.clip(image * _stains(rng, size, 0.2)[:, :, None], 0, 1).astype(np.float32)

    return recipe


def _ashlar(color: Sequence[float]) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        x, y = _grid(size)
        courses, per_course = 4, 2
        course = np.floor(y * courses).astype(int)
        bx = x * per_course + 0.5 * (course % 2)
        block = (np.floor(bx).astype(int) % per_course) + per_course * course
        shades = rng.uniform(0.85, 1.1, courses * per_course)
        grain = rgb2gray(make_seamless(_square(load_photo("moon"), size, (0.5, 0.5, 0.6))))
        value = shades[block] * (0.82 + 0.35 * (grain - grain.mean()))
        value = value * _grain_detail(rng, size, 0.2) * _stains(rng, size, 0.25)
        joints = np.maximum(_joints(y * courses, 0.02), _joints(bx, 0.012))
        value = value * (1 - 0.45 * joints)
        return _rgb(value, _jitter(rng, color, 0.05))

    return recipe


def _pavers(color: Sequence[float]) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        x, y = _grid(size)
        rows, per_row = 8, 4
        row = np.floor(y * rows).astype(int)
        bx = x * per_row + 0.5 * (row % 2)
        stone = (np.floor(bx).astype(int) % per_row) + per_row * row
        count = rows * per_row
        shades = rng.uniform(0.75, 1.15, (count, 1)) * rng.uniform(0.94, 1.06, (count, 3))
        value = 0.8 + 0.1 * periodic_noise(rng, size, 1.2) + 0.06 * periodic_noise(rng, size, 0.2)
        image = _rgb(value, _jitter(rng, color)) * shades[stone]
        joints = np.maximum(_joints(y * rows, 0.06), _joints(bx, 0.03))
        image = image * (1 - 0.65 * joints[:, :, None])
        return np.clip(image * _stains(rng, size, 0.2)[:, :, None], 0, 1).astype(np.float32)

    return recipe


def _asphalt(rng: np.random.Generator, size: int) -> np.ndarray:
    aggregate = periodic_noise(rng, size, 0.0)
    value = 0.34 + 0.05 * periodic_noise(rng, size, 2.4) + 0.06 * aggregate
    value = value + 0.25 * (aggregate > 2.3) - 0.1 * (aggregate < -2.3)
    cracks = np.abs(periodic_noise(rng, size, 2.0)) < 0.025
    patches = periodic_noise(rng, size, 3.0) > 1.3
    value = value * (1 - 0.5 * cracks) * (1 - 0.15 * patches)
    return _rgb(value, _jitter(rng, (0.95, 0.95, 1.0), 0.04))


def _photo_surface(photo: str, color: Sequence[float], crop: float, gray: bool) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        image = _square(
            load_photo(photo), size, (rng.uniform(0.4, 0.6), rng.uniform(0.4, 0.6), crop)
        )
        image = make_seamless(image)
        if gray:
            value = rgb2gray(image)
            value = 0.55 + 0.9 * (value - value.mean())
            image = _rgb(value, _jitter(rng, color) * 1.6)
        else:
            image = image * _jitter(rng, color)[None, None, :] * 1.6
        return np.clip(image * _stains(rng, size, 0.15)[:, :, None], 0, 1).astype(np.float32)

    return recipe


def _metal(color: Sequence[float]) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        brushed = periodic_noise(rng, size, 1.2, stretch=12.0)
        scratches = np.abs(periodic_noise(rng, size, 1.0, stretch=30.0)) > 2.4
        value = 0.75 + 0.08 * brushed + 0.05 * periodic_noise(rng, size, 2.5) + 0.12 * scratches
        return _rgb(value * _stains(rng, size, 0.1), _jitter(rng, color, 0.05))

    return recipe


def _paint(color: Sequence[float]) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        flakes = periodic_noise(rng, size, 0.0)
        value = 0.8 + 0.06 * periodic_noise(rng, size, 2.0) + 0.05 * flakes
        x, y = _grid(size)
        seams = np.maximum(_joints(x * 2, 0.006), _joints(y * 2, 0.006))
        value = value * (1 - 0.45 * seams) * _stains(rng, size, 0.15)
        return _rgb(value, _jitter(rng, color, 0.05))

    return recipe


def _glass(tint: Sequence[float], panes_x: int, panes_y: int) -> Recipe:
    """A window: sky reflections in dark glass, split into panes by light bars (fit to a face)."""

    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        x, y = _grid(size)
        sky = _unit_noise(rng, size, 2.8)
        reflection = 0.18 + 0.35 * sky * (1.1 - y) + 0.08 * periodic_noise(rng, size, 0.8) * 0.3
        interior = rng.uniform(0.6, 1.0, (4, 4))[
            np.floor(y * 4).astype(int), np.floor(x * 4).astype(int)
        ]
        glass = _rgb(reflection * interior, _jitter(rng, tint))
        bars = np.maximum(_joints(x * panes_x, 0.05), _joints(y * panes_y, 0.05))
        border = np.maximum(np.minimum(x, 1 - x), 0) < 0.04
        border |= np.maximum(np.minimum(y, 1 - y), 0) < 0.04
        frame = np.maximum(bars, border.astype(np.float32))[:, :, None]
        frame_color = _jitter(rng, (0.92, 0.92, 0.9), 0.03)[None, None, :] * (
            0.9 + 0.1 * sky[:, :, None]
        )
        return np.clip(glass * (1 - frame) + frame_color * frame, 0, 1).astype(np.float32)

    return recipe


def _door(color: Sequence[float]) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        x, y = _grid(size)
        grain = np.sin(2 * np.pi * (14 * x + 0.7 * periodic_noise(rng, size, 2.5, stretch=0.15)))
        value = 0.75 + 0.1 * grain + 0.05 * periodic_noise(rng, size, 0.6)
        panel_x = (x > 0.15) & (x < 0.85)
        upper = panel_x & (y > 0.08) & (y < 0.45)
        lower = panel_x & (y > 0.55) & (y < 0.92)
        panels = upper | lower
        edge = np.zeros_like(value)
        for box in ((0.15, 0.85, 0.08, 0.45), (0.15, 0.85, 0.55, 0.92)):
            dx = np.minimum(np.abs(x - box[0]), np.abs(x - box[1]))
            dy = np.minimum(np.abs(y - box[2]), np.abs(y - box[3]))
            inside = (
                (x > box[0] - 0.02)
                & (x < box[1] + 0.02)
                & (y > box[2] - 0.02)
                & (y < box[3] + 0.02)
            )
            edge = np.maximum(edge, (inside & (np.minimum(dx, dy) < 0.018)).astype(np.float32))
        handle = ((x - 0.88) ** 2 + (y - 0.5) ** 2) < 0.025**2
        value = value * (1 + 0.08 * panels) * (1 - 0.45 * edge)
        image = _rgb(value, _jitter(rng, color))
        image[handle] = (0.85, 0.82, 0.7)
        return image

    return recipe


def _books(rng: np.random.Generator, size: int) -> np.ndarray:
    """One shelf row of book spines with titles (fit to a face)."""
    x, y = _grid(size)
    widths = rng.uniform(0.018, 0.06, 64)
    edges = np.cumsum(widths)
    edges = edges[edges < 1.0]
    book = np.searchsorted(edges, x)
    count = len(edges) + 1
    palette = np.array(
        [
            [0.6, 0.1, 0.1],
            [0.1, 0.2, 0.5],
            [0.1, 0.4, 0.2],
            [0.85, 0.75, 0.3],
            [0.9, 0.9, 0.85],
            [0.2, 0.2, 0.2],
            [0.5, 0.3, 0.15],
            [0.4, 0.1, 0.4],
            [0.9, 0.5, 0.1],
        ],
        dtype=np.float32,
    )
    colors = palette[rng.integers(0, len(palette), count)] * rng.uniform(0.7, 1.1, (count, 1))
    tops = rng.uniform(0.0, 0.3, count)
    gap = rng.random(count) < 0.08
    image = colors[book] * (0.85 + 0.1 * periodic_noise(rng, size, 0.5))[:, :, None]
    band_lo, band_hi = rng.uniform(0.35, 0.55, count), rng.uniform(0.6, 0.8, count)
    title = (y > band_lo[book]) & (y < band_hi[book])
    lettering = title & (periodic_noise(rng, size, 0.0) > 0.3)
    image = np.where(title[:, :, None], image * 0.6 + 0.35, image)
    image = np.where(lettering[:, :, None], image * 0.3, image)
    starts = np.concatenate([[0.0], edges])
    spine_edge = (x - starts[book]) < 0.004
    image = np.where(spine_edge[:, :, None], image * 0.45, image)
    empty = (y < tops[book]) | gap[book]
    image = np.where(empty[:, :, None], 0.12, image)
    return np.clip(image, 0, 1).astype(np.float32)


def _fabric(color: Sequence[float], stripes: int) -> Recipe:
    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        x, y = _grid(size)
        weave = np.sin(2 * np.pi * 64 * x) * np.sin(2 * np.pi * 64 * y)
        band = (np.floor(x * stripes) % 2).astype(np.float32)
        value = 0.72 + 0.06 * weave + 0.1 * band + 0.08 * periodic_noise(rng, size, 0.5)
        return _rgb(value * _stains(rng, size, 0.15), _jitter(rng, color))

    return recipe


def _cardboard(rng: np.random.Generator, size: int) -> np.ndarray:
    x, y = _grid(size)
    value = 0.75 + 0.05 * np.sin(2 * np.pi * 40 * y) + 0.07 * periodic_noise(rng, size, 1.5)
    image = _rgb(value, _jitter(rng, (0.72, 0.55, 0.36)))
    text = rgb2gray(_square(load_photo("text"), size // 2, (0.5, rng.uniform(0.3, 0.7), 1.0)))
    half = size // 2
    top = rng.integers(0, size - half)
    left = rng.integers(0, size - half)
    ink = text < 0.45
    region = image[top : top + half, left : left + half]
    region[ink] = region[ink] * 0.25
    tape = np.abs(x - 0.5) < 0.06
    image[tape] = image[tape] * 0.6 + 0.3
    return np.clip(image, 0, 1).astype(np.float32)


def _board(background: str, photo: str, notes: int) -> Recipe:
    """A whiteboard or notice board with pinned or written pages (fit to a face)."""

    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        if background == "cork":
            value = (
                0.7 + 0.12 * periodic_noise(rng, size, 0.2) + 0.06 * periodic_noise(rng, size, 2.0)
            )
            image = _rgb(value, _jitter(rng, (0.72, 0.52, 0.32)))
        else:
            value = 0.93 + 0.02 * periodic_noise(rng, size, 2.5)
            image = _rgb(value, _jitter(rng, (1.0, 1.0, 1.0), 0.02))
        source = load_photo(photo)
        for _ in range(notes):
            side = int(size * rng.uniform(0.22, 0.4))
            crop = (rng.uniform(0.3, 0.7), rng.uniform(0.2, 0.8), rng.uniform(0.35, 0.8))
            note = _square(source, side, crop)
            if background != "cork":
                ink = rgb2gray(note) < 0.5
                note = np.where(
                    ink[:, :, None], _jitter(rng, (0.1, 0.2, 0.7), 0.3) * 0.6, image[:side, :side]
                )
            top, left = rng.integers(0, size - side, 2)
            image[top : top + side, left : left + side] = note
        frame = np.zeros((size, size), bool)
        border = max(2, size // 40)
        frame[:border], frame[-border:], frame[:, :border], frame[:, -border:] = (
            True,
            True,
            True,
            True,
        )
        image[frame] = (0.7, 0.7, 0.72)
        return np.clip(image, 0, 1).astype(np.float32)

    return recipe


def _poster(photo: str, crop: tuple[float, float, float]) -> Recipe:
    """A photograph with a white margin (fit to a face)."""

    def recipe(rng: np.random.Generator, size: int) -> np.ndarray:
        margin = max(2, size // 24)
        inner = _square(load_photo(photo), size - 2 * margin, crop)
        paper = _jitter(rng, (0.96, 0.95, 0.92), 0.02)
        image = np.empty((size, size, 3), np.float32)
        image[:] = paper
        image[margin:-margin, margin:-margin] = inner * rng.uniform(0.92, 1.02)
        return np.clip(image, 0, 1).astype(np.float32)

    return recipe


def _light_panel(rng: np.random.Generator, size: int) -> np.ndarray:
    x, y = _grid(size)
    louvres = np.maximum(_joints(x * 6, 0.08), _joints(y * 6, 0.08))
    border = np.minimum(np.minimum(x, 1 - x), np.minimum(y, 1 - y)) < 0.05
    value = 0.97 - 0.25 * louvres - 0.35 * border + 0.02 * periodic_noise(rng, size, 1.0)
    return _rgb(value, np.array([1.0, 1.0, 0.97], np.float32))


def _slate(rng: np.random.Generator, size: int) -> np.ndarray:
    x, y = _grid(size)
    rows, per_row = 8, 6
    row = np.floor(y * rows).astype(int)
    bx = x * per_row + 0.5 * (row % 2)
    slate = (np.floor(bx).astype(int) % per_row) + per_row * row
    shades = rng.uniform(0.75, 1.2, rows * per_row)
    value = shades[slate] * (0.55 + 0.06 * periodic_noise(rng, size, 0.6))
    frac = y * rows - np.floor(y * rows)
    value = value * (0.8 + 0.25 * frac) * (1 - 0.5 * _joints(bx, 0.02))
    return _rgb(value * _stains(rng, size, 0.2), _jitter(rng, (0.52, 0.55, 0.62)))


def _bark(rng: np.random.Generator, size: int) -> np.ndarray:
    ridges = periodic_noise(rng, size, 1.6, stretch=0.12)
    value = 0.5 + 0.12 * ridges + 0.08 * periodic_noise(rng, size, 0.4)
    value = value - 0.2 * (np.abs(ridges) < 0.15)
    return _rgb(value, _jitter(rng, (0.62, 0.48, 0.36)))


def _foliage(rng: np.random.Generator, size: int) -> np.ndarray:
    base = _photo_surface("grass", (0.35, 0.55, 0.25), 0.5, gray=True)(rng, size)
    holes = periodic_noise(rng, size, 1.4) > 1.2
    base[holes] *= 0.35
    return base


def _water(rng: np.random.Generator, size: int) -> np.ndarray:
    ripples = np.sin(periodic_noise(rng, size, 2.0) * 4.0)
    value = 0.6 + 0.15 * ripples + 0.05 * periodic_noise(rng, size, 0.5)
    return _rgb(value, _jitter(rng, (0.35, 0.55, 0.7)))


def _rubber(rng: np.random.Generator, size: int) -> np.ndarray:
    x, _ = _grid(size)
    value = 0.22 + 0.06 * (np.sin(2 * np.pi * 24 * x) > 0.3) + 0.04 * periodic_noise(rng, size, 0.5)
    return _rgb(value, np.array([1.0, 1.0, 1.0], np.float32))


def _sign(rng: np.random.Generator, size: int) -> np.ndarray:
    """A street sign: dark text of the ``text`` photo on a coloured board (fit to a face)."""
    board = _jitter(rng, (0.15, 0.35, 0.6), 0.1)
    text = rgb2gray(_square(load_photo("page"), size, (0.5, rng.uniform(0.3, 0.7), 1.0)))
    ink = text < 0.45
    image = np.empty((size, size, 3), np.float32)
    image[:] = board
    image[ink] = (0.95, 0.95, 0.92)
    image = image * (1 + 0.05 * periodic_noise(rng, size, 1.0))[:, :, None]
    return np.clip(image, 0, 1).astype(np.float32)


# --------------------------------------------------------------------------- catalogue


@dataclass(frozen=True)
class MaterialSpec:
    """One catalogue entry.

    Attributes:
        name: material name (``[a-z0-9_]``, used for file names).
        recipe: ``recipe(rng, size) -> (size, size, 3)`` float32 image in [0, 1].
        repeat_m: metres covered by one texture repeat; 0 stretches the texture once over each
            face (posters, windows, doors, signs).
    """

    name: str
    recipe: Recipe
    repeat_m: float


MATERIALS: tuple[MaterialSpec, ...] = (
    # structure and floors
    MaterialSpec("plaster_white", _plaster((0.95, 0.94, 0.9)), 2.5),
    MaterialSpec("plaster_warm", _plaster((0.96, 0.86, 0.7)), 2.5),
    MaterialSpec("plaster_blue", _plaster((0.72, 0.82, 0.92)), 2.5),
    MaterialSpec("plaster_green", _plaster((0.75, 0.88, 0.72)), 2.5),
    MaterialSpec("brick_wall", _bricks((0.72, 0.36, 0.26), 16, 4), 2.0),
    MaterialSpec("concrete", _concrete((0.85, 0.84, 0.8)), 3.0),
    MaterialSpec("floor_tiles", _floor_tiles((0.82, 0.8, 0.74), 4, (0.45, 0.5, 0.55)), 2.4),
    MaterialSpec("floor_checker", _checker_marble, 3.2),
    MaterialSpec("carpet_grey", _carpet((0.55, 0.57, 0.62)), 1.6),
    MaterialSpec("carpet_red", _carpet((0.62, 0.32, 0.3)), 1.6),
    MaterialSpec("wood_floor", _wood((0.74, 0.55, 0.36), 8), 2.4),
    MaterialSpec("ceiling_tiles", _ceiling_tiles, 2.4),
    MaterialSpec("light_panel", _light_panel, 0.0),
    # furniture and fittings
    MaterialSpec("wood", _wood((0.78, 0.6, 0.42), 4), 1.2),
    MaterialSpec("wood_dark", _wood((0.45, 0.3, 0.2), 4), 1.2),
    MaterialSpec("metal", _metal((0.75, 0.77, 0.8)), 1.0),
    MaterialSpec("metal_dark", _metal((0.32, 0.34, 0.37)), 1.0),
    MaterialSpec("paint_red", _paint((0.8, 0.12, 0.1)), 1.0),
    MaterialSpec("fabric_blue", _fabric((0.3, 0.4, 0.62), 12), 0.8),
    MaterialSpec("fabric_green", _fabric((0.35, 0.55, 0.4), 6), 0.8),
    MaterialSpec("cardboard", _cardboard, 0.0),
    MaterialSpec("books", _books, 0.0),
    MaterialSpec("door_wood", _door((0.72, 0.52, 0.34)), 0.0),
    MaterialSpec("window_glass", _glass((0.55, 0.68, 0.85), 2, 3), 0.0),
    MaterialSpec("whiteboard", _board("white", "page", 3), 0.0),
    MaterialSpec("notice_board", _board("cork", "page", 5), 0.0),
    MaterialSpec("foliage", _foliage, 1.5),
    # outdoors
    MaterialSpec("asphalt", _asphalt, 4.0),
    MaterialSpec("gravel", _photo_surface("gravel", (0.78, 0.72, 0.6), 0.6, gray=True), 2.5),
    MaterialSpec("grass", _photo_surface("grass", (0.42, 0.6, 0.3), 0.6, gray=True), 3.0),
    MaterialSpec("paving", _pavers((0.74, 0.7, 0.64)), 3.0),
    MaterialSpec("facade_stone", _ashlar((0.88, 0.76, 0.55)), 4.0),
    MaterialSpec("facade_brick", _bricks((0.66, 0.34, 0.25), 24, 5), 3.0),
    MaterialSpec("facade_render", _plaster((0.93, 0.88, 0.78)), 3.0),
    MaterialSpec("stone_trim", _concrete((0.95, 0.9, 0.78)), 2.0),
    MaterialSpec("roof_slate", _slate, 4.0),
    MaterialSpec("window_facade", _glass((0.45, 0.55, 0.7), 2, 4), 0.0),
    MaterialSpec("door_facade", _door((0.3, 0.35, 0.3)), 0.0),
    MaterialSpec("car_red", _paint((0.72, 0.1, 0.1)), 2.0),
    MaterialSpec("car_blue", _paint((0.15, 0.25, 0.6)), 2.0),
    MaterialSpec("car_silver", _paint((0.78, 0.8, 0.82)), 2.0),
    MaterialSpec("car_glass", _glass((0.3, 0.35, 0.4), 1, 1), 0.0),
    MaterialSpec("rubber", _rubber, 0.8),
    MaterialSpec("bark", _bark, 1.0),
    MaterialSpec("water", _water, 2.0),
    MaterialSpec("sign_text", _sign, 0.0),
    # posters: photographs that make places recognisable
    MaterialSpec("poster_coffee", _poster("coffee", (0.5, 0.5, 1.0)), 0.0),
    MaterialSpec("poster_astronaut", _poster("astronaut", (0.45, 0.5, 1.0)), 0.0),
    MaterialSpec("poster_chelsea", _poster("chelsea", (0.5, 0.45, 1.0)), 0.0),
    MaterialSpec("poster_rocket", _poster("rocket", (0.5, 0.5, 1.0)), 0.0),
    MaterialSpec("poster_hubble", _poster("hubble_deep_field", (0.5, 0.5, 0.8)), 0.0),
    MaterialSpec("poster_camera", _poster("camera", (0.5, 0.5, 1.0)), 0.0),
    MaterialSpec("poster_moon", _poster("moon", (0.5, 0.5, 1.0)), 0.0),
    MaterialSpec("poster_coins", _poster("coins", (0.5, 0.5, 1.0)), 0.0),
    MaterialSpec("poster_cells", _poster("immunohistochemistry", (0.5, 0.5, 1.0)), 0.0),
    MaterialSpec("poster_retina", _poster("retina", (0.5, 0.5, 0.9)), 0.0),
    MaterialSpec("poster_motorcycle", _poster("stereo_motorcycle", (0.5, 0.5, 1.0)), 0.0),
    MaterialSpec("poster_page", _poster("page", (0.5, 0.3, 1.0)), 0.0),
    MaterialSpec("poster_galaxy", _poster("hubble_deep_field", (0.3, 0.7, 0.45)), 0.0),
)
POSTERS = tuple(spec.name for spec in MATERIALS if spec.name.startswith("poster_"))
"""The poster materials of the catalogue (wall posters, banners), in catalogue order."""

_BY_NAME = {spec.name: index for index, spec in enumerate(MATERIALS)}


def material_repeat_m(name: str) -> float:
    """Metres per texture repeat of a catalogue material (0 = stretched once over a face)."""
    if name not in _BY_NAME:
        raise ValueError(f"unknown material {name!r}; known: {sorted(_BY_NAME)}")
    return MATERIALS[_BY_NAME[name]].repeat_m


def make_materials(
    rng: np.random.Generator, size: int, names: Sequence[str] | None = None
) -> tuple[list[str], list[np.ndarray]]:
    """Make the textures of the material catalogue (or of a subset of it).

    One seed per catalogue entry is drawn from ``rng`` first, so a material's texture depends only
    on the generator's state and the material's catalogue position, not on which subset is asked
    for; the generator always advances by the same amount.

    Args:
        rng: source of randomness (tints, tile shades, noise, crops).
        size: texture side length S in texels (>= 16).
        names: materials to make, in this order; ``None`` makes the whole catalogue.

    Returns:
        ``(names, textures)``: the material names and one (S, S, 3) float32 image in [0, 1] each.

    Example:
        >>> names, textures = make_materials(np.random.default_rng(0), 64, ["brick_wall", "grass"])
        >>> textures[0].shape
        (64, 64, 3)
    """
    if isinstance(size, bool) or not isinstance(size, int | np.integer) or size < 16:
        raise ValueError(f"texture size must be an integer >= 16, got {size!r}")
    seeds = rng.integers(0, 2**63 - 1, size=len(MATERIALS))
    wanted = [spec.name for spec in MATERIALS] if names is None else list(names)
    unknown = [n for n in wanted if n not in _BY_NAME]
    if unknown:
        raise ValueError(f"unknown materials {unknown}; known: {sorted(_BY_NAME)}")
    if len(set(wanted)) != len(wanted):
        raise ValueError(f"material names must be unique, got {wanted}")
    textures = []
    for name in wanted:
        index = _BY_NAME[name]
        image = MATERIALS[index].recipe(np.random.default_rng(seeds[index]), int(size))
        textures.append(np.ascontiguousarray(np.clip(image, 0.0, 1.0), dtype=np.float32))
    return wanted, textures
