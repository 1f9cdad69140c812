import numpy as np
import pytest
import torch

from diffloc.render.texture import MipmapTextures


def test_constant_textures_sample_their_colour_at_every_level():
    textures = [np.full((8, 8, 3), c, np.float32) for c in (0.2, 0.7)]
    mip = MipmapTextures(textures)
    n = 50
    material = torch.tensor([0, 1] * (n // 2))
    uv = torch.rand(n, 2, generator=torch.Generator().manual_seed(0)) * 10 - 5
    footprint = torch.logspace(-1, 3, n)
    colours = mip.sample(material, uv, footprint)
    expected = torch.where(material[:, None] == 0, 0.2, 0.7).expand(-1, 3)
    torch.testing.assert_close(colours, expected, atol=1e-6, rtol=0)


def test_texel_centres_are_exact_and_coordinates_wrap():
    texture = np.random.default_rng(0).random((4, 4, 3)).astype(np.float32)
    mip = MipmapTextures([texture])
    rows, cols = np.meshgrid(np.arange(4), np.arange(4), indexing="ij")
    uv = torch.tensor(np.stack([(cols + 0.5) / 4, (rows + 0.5) / 4], -1).reshape(-1, 2))
    for shift in (0.0, 3.0, -2.0):
        got = mip.sample(torch.zeros(16, dtype=torch.long), uv + shift, torch.ones(16))
        np.testing.assert_allclose(got.numpy(), texture.reshape(-1, 3), atol=1e-6)


def test_large_footprint_returns_the_texture_mean():
    texture = np.random.default_rng(1).random((16, 16, 3)).astype(np.float32)
    mip = MipmapTextures([texture])
    got = mip.sample(torch.zeros(3, dtype=torch.long), torch.rand(3, 2), torch.full((3,), 1e4))
    np.testing.assert_allclose(
        got.numpy(), np.broadcast_to(texture.mean((0, 1)), (3, 3)), atol=1e-5
    )


def test_non_power_of_two_textures_are_resized():
    mip = MipmapTextures([np.ones((5, 7, 3), np.float32), np.zeros((16, 16, 3), np.float32)])
    assert mip.size == 16


def test_trilinear_sampling_blends_the_next_level_only_where_needed():
    g = torch.Generator().manual_seed(0)
    textures = [torch.rand(16, 16, 3, generator=g).numpy() for _ in range(2)]
    mip = MipmapTextures(textures)
    n = 500
    material = torch.randint(0, 2, (n,), generator=g)
    uv = torch.rand(n, 2, generator=g) * 3 - 1  # wrapping coordinates
    footprint = torch.rand(n, generator=g) * 40  # magnified (< 1 texel), between levels, clamped
    got = mip.sample(material, uv, footprint)
    level = torch.log2(footprint.clamp_min(1.0)).clamp(max=mip.num_levels - 1)
    lower = torch.floor(level).long()
    upper = (lower + 1).clamp(max=mip.num_levels - 1)
    blend = (level - lower)[:, None]
    below, above = mip._bilinear(material, uv, lower).t(), mip._bilinear(material, uv, upper).t()
    expected = (1 - blend) * below + blend * above  # every sample at both levels, as defined
    assert bool((footprint < 1).any()) and bool((blend > 0).any())
    assert torch.equal(got, expected)


def test_lookups_in_chunks_give_the_same_colours_bit_for_bit():
    g = torch.Generator().manual_seed(1)
    textures = [torch.rand(s, s, 3, generator=g).numpy() for s in (32, 8)]
    n = 1000
    material = torch.randint(0, 2, (n,), generator=g)
    uv = torch.rand(n, 2, generator=g) * 4 - 2
    footprint = torch.rand(n, generator=g) * 80  # every level, blended and clamped
    whole = MipmapTextures(textures).sample(material, uv, footprint)
    for chunk_size in (1, 7, 999):
        chunked = MipmapTextures(textures, chunk_size=chunk_size).sample(material, uv, footprint)
        assert torch.equal(chunked.view(torch.int32), whole.view(torch.int32)), chunk_size
    assert MipmapTextures(textures).sample(material[:0], uv[:0], footprint[:0]).shape == (0, 3)


def test_bad_chunk_sizes_and_too_many_texels_are_refused():
    with pytest.raises(ValueError, match="chunk_size"):
        MipmapTextures([np.ones((4, 4, 3), np.float32)], chunk_size=0)
    huge = np.broadcast_to(np.zeros((1, 1, 3), np.float32), (32768, 32768, 3))  # no memory
    with pytest.raises(ValueError, match="too many"):  # 2 x 1.4e9 texels overflow int32 indices
        MipmapTextures([huge, huge])
