import numpy as np
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
    expected = (1 - blend) * mip._bilinear(material, uv, lower) + blend * mip._bilinear(
        material, uv, upper
    )  # every sample at both levels, as the definition reads
    assert bool((footprint < 1).any()) and bool((blend > 0).any())
    assert torch.equal(got, expected)
