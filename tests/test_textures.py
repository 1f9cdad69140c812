"""Material textures: shapes, ranges, determinism, seamless tiling, richness, photos offline."""

from __future__ import annotations

import numpy as np
import pytest

from diffloc.sim.textures import (
    BUNDLED_PHOTOS,
    MATERIALS,
    load_photo,
    make_materials,
    make_seamless,
    material_repeat_m,
    periodic_noise,
)


@pytest.fixture(scope="module")
def catalogue() -> tuple[list[str], list[np.ndarray]]:
    return make_materials(np.random.default_rng(0), 64)


def test_every_material_has_the_right_shape_type_and_range(catalogue):
    names, textures = catalogue
    assert names == [spec.name for spec in MATERIALS]
    assert len(set(names)) == len(names)
    for name, texture in zip(names, textures, strict=True):
        assert texture.shape == (64, 64, 3) and texture.dtype == np.float32, name
        assert texture.min() >= 0.0 and texture.max() <= 1.0, name
        assert name.replace("_", "").isalnum()


def test_textures_are_rich_no_large_flat_areas(catalogue):
    names, textures = catalogue
    for name, texture in zip(names, textures, strict=True):
        gray = texture.mean(axis=2)
        assert gray.std() > 0.02, name
        # Local contrast in most 8x8 blocks (no large flat patches).
        blocks = gray.reshape(8, 8, 8, 8).std(axis=(1, 3))
        assert (blocks > 0.004).mean() > 0.6, name


def test_materials_differ_from_each_other(catalogue):
    names, textures = catalogue
    means = np.array([t.mean(axis=(0, 1)) for t in textures])
    stack = np.stack(textures).reshape(len(textures), -1)
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            close_colour = np.abs(means[i] - means[j]).max() < 0.01
            assert not (close_colour and np.abs(stack[i] - stack[j]).mean() < 0.02), (
                names[i],
                names[j],
            )


def test_tiling_materials_have_no_seams():
    """The step across the wrap-around border is no larger than the largest step between any two
    neighbouring rows (columns) inside the texture. Raw photographs fail this (checked below)."""

    def seam_and_largest_inner_step(texture: np.ndarray, axis: int) -> tuple[float, float]:
        gray = texture.mean(axis=2).astype(np.float64)
        steps = np.abs(np.diff(gray, axis=axis)).mean(axis=1 - axis)
        seam = np.abs(np.take(gray, 0, axis=axis) - np.take(gray, -1, axis=axis)).mean()
        return seam, steps.max()

    raw = load_photo("gravel")[:128, :128]
    assert seam_and_largest_inner_step(raw, 0)[0] > 1.05 * seam_and_largest_inner_step(raw, 0)[1]
    names, textures = make_materials(np.random.default_rng(1), 128)
    for name, texture in zip(names, textures, strict=True):
        if material_repeat_m(name) == 0:
            continue  # stretched once over a face, never tiled
        for axis in (0, 1):
            seam, inner = seam_and_largest_inner_step(texture, axis)
            assert seam <= 1.05 * inner + 0.005, (name, axis, seam, inner)


def test_same_generator_same_textures_and_subsets_are_consistent():
    a = make_materials(np.random.default_rng(7), 32)
    b = make_materials(np.random.default_rng(7), 32)
    for ta, tb in zip(a[1], b[1], strict=True):
        assert np.array_equal(ta, tb)
    names, sub = make_materials(np.random.default_rng(7), 32, ["grass", "brick_wall"])
    assert names == ["grass", "brick_wall"]
    assert np.array_equal(sub[0], a[1][a[0].index("grass")])
    assert np.array_equal(sub[1], a[1][a[0].index("brick_wall")])
    c = make_materials(np.random.default_rng(8), 32, ["grass"])[1][0]
    assert not np.array_equal(c, sub[0])


def test_periodic_noise_wraps_and_is_standardised():
    field = periodic_noise(np.random.default_rng(0), 64, beta=2.5)
    assert field.shape == (64, 64)
    assert abs(field.mean()) < 1e-4 and abs(field.std() - 1) < 1e-4
    assert np.abs(field[0] - field[-1]).mean() < 2 * np.abs(np.diff(field, axis=0)).mean()


def test_make_seamless_removes_a_seam():
    ramp = np.tile(np.linspace(0, 1, 64, dtype=np.float32)[None, :, None], (64, 1, 3))
    out = make_seamless(ramp)
    assert np.abs(ramp[:, 0] - ramp[:, -1]).mean() > 0.9
    assert np.abs(out[:, 0] - out[:, -1]).mean() < 0.1


def test_bundled_photos_load_without_network():
    for name in BUNDLED_PHOTOS:
        photo = load_photo(name)
        assert photo.ndim == 3 and photo.shape[2] == 3 and photo.dtype == np.float32
        assert 0.0 <= photo.min() and photo.max() <= 1.0 and photo.std() > 0.05


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="size"):
        make_materials(np.random.default_rng(0), 8)
    with pytest.raises(ValueError, match="unknown materials"):
        make_materials(np.random.default_rng(0), 32, ["unobtainium"])
    with pytest.raises(ValueError, match="unknown photo"):
        load_photo("lily")
    with pytest.raises(ValueError, match="unknown material"):
        material_repeat_m("unobtainium")
