"""Photometric image formation: Lambertian shading, exposure, white balance, blur and noise.

Albedo textures are stored gamma-encoded (like the photographs they come from). Shading is done
in linear intensity: ``linear = albedo ** gamma * (ambient + intensity * max(0, n . l) * lit)``,
then a sequence's exposure and per-channel white balance scale it, motion blur averages linear
sub-frames, sensor noise (read + shot) is added and the result is gamma-encoded again.

A sequence may switch on per-frame auto exposure (:class:`AutoExposureConfig`, off by default):
a controller meters each frame's mean linear luminance and moves the exposure towards the value
that brings it to a target, as a first-order lag in log exposure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from diffloc.checks import check_shape
from diffloc.render.raycast import MeshRaycaster, MeshRender


@dataclass
class LightingConfig:
    """Light and camera response of one sequence.

    Attributes:
        light_azimuth_deg: direction the light comes from, degrees counter-clockwise from +x.
        light_elevation_deg: light elevation above the horizon in degrees.
        light_intensity: directional light strength (linear units).
        ambient: ambient light strength (linear units).
        shadows: cast shadow rays towards the light (meaningful outdoors; costs one more cast).
        exposure: multiplies the linear image.
        white_balance: per-channel RGB gains.
        sky_color: RGB (gamma-encoded) of rays that hit nothing.
    """

    light_azimuth_deg: float = 30.0
    light_elevation_deg: float = 55.0
    light_intensity: float = 0.75
    ambient: float = 0.4
    shadows: bool = False
    exposure: float = 1.0
    white_balance: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0])
    sky_color: list[float] = field(default_factory=lambda: [0.62, 0.75, 0.92])


@dataclass
class SensorConfig:
    """Image sensor model shared by all sequences of a scene.

    Attributes:
        gamma: encoding gamma of textures and output images.
        read_noise_std: standard deviation of additive noise (fraction of full scale).
        shot_noise_std: noise standard deviation at full signal; scales with sqrt(signal).
        motion_blur_samples: sub-frames averaged per image (1 disables motion blur).
        exposure_time_s: time span the sub-frames cover, ending at the frame timestamp.
    """

    gamma: float = 2.2
    read_noise_std: float = 0.004
    shot_noise_std: float = 0.01
    motion_blur_samples: int = 1
    exposure_time_s: float = 0.02


@dataclass
class AutoExposureConfig:
    """Per-frame auto exposure of one sequence; off by default (the sequence's fixed exposure).

    Frame k meters ``m_k``, the mean luminance of its linear image after the sequence's exposure
    and white balance. The exposure that would bring it to the target is
    ``a*_k = clip(target_mean / m_k, min_scale, max_scale)``; the controller follows it with a
    first-order lag in log exposure, ``log a_k = (1 - adaptation) log a_{k-1} + adaptation log
    a*_k`` from ``a_{-1} = 1``. Frame k's exposure is ``lighting.exposure * a_k``.

    Attributes:
        enabled: switch the controller on.
        target_mean: mean linear luminance the controller aims for.
        adaptation: fraction of the log error corrected per frame, in (0, 1].
        min_scale: lowest exposure multiplier.
        max_scale: highest exposure multiplier.
    """

    enabled: bool = False
    target_mean: float = 0.18
    adaptation: float = 0.6
    min_scale: float = 0.25
    max_scale: float = 4.0


LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
"""Rec. 709 luminance weights of linear RGB."""


def auto_exposure_scales(
    metered: torch.Tensor, previous_scale: float, cfg: AutoExposureConfig
) -> torch.Tensor:
    """Exposure multipliers of consecutive frames chosen by the auto-exposure controller.

    Args:
        metered: (B,) mean linear luminance of B consecutive frames at multiplier 1.
        previous_scale: the multiplier of the frame before the first (1 at the start).
        cfg: the controller.

    Returns:
        (B,) float64 multipliers ``a_k`` (see :class:`AutoExposureConfig`).
    """
    check_shape(metered, "B", "metered")
    if not 0.0 < cfg.adaptation <= 1.0:
        raise ValueError(f"auto_exposure.adaptation must be in (0, 1], got {cfg.adaptation}")
    if not 0.0 < cfg.min_scale <= cfg.max_scale:
        raise ValueError(
            f"auto_exposure needs 0 < min_scale <= max_scale, got {cfg.min_scale}, {cfg.max_scale}"
        )
    if cfg.target_mean <= 0.0:
        raise ValueError(f"auto_exposure.target_mean must be > 0, got {cfg.target_mean}")
    wanted = (cfg.target_mean / metered.to(torch.float64).clamp_min(1e-6)).clamp(
        cfg.min_scale, cfg.max_scale
    )
    # Unrolled lag: log a_k = keep^(k+1) log a_-1 + sum_{i<=k} rate keep^(k-i) log a*_i.
    rate, keep = cfg.adaptation, 1.0 - cfg.adaptation
    k = torch.arange(metered.shape[0], dtype=torch.float64)
    lag = (k[:, None] - k[None, :]).clamp_min(0.0)
    weights = torch.where(k[:, None] >= k[None, :], rate * keep**lag, torch.zeros_like(lag))
    log_scale = keep ** (k + 1) * math.log(previous_scale) + weights @ wanted.log()
    return log_scale.exp()


def metered_luminance(linear: torch.Tensor, lighting: LightingConfig) -> torch.Tensor:
    """Mean linear luminance (B,) of (B, 3, H, W) radiance after exposure and white balance."""
    check_shape(linear, "B,3,H,W", "linear")
    gains = torch.tensor(lighting.white_balance, dtype=torch.float32) * lighting.exposure
    weights = torch.tensor(LUMINANCE_WEIGHTS, dtype=torch.float32) * gains
    return torch.einsum("bchw,c->b", linear.clamp_min(0.0), weights) / (
        linear.shape[2] * linear.shape[3]
    )


def light_direction(lighting: LightingConfig) -> torch.Tensor:
    """Unit vector (3,) pointing from the scene towards the light, world frame (z up)."""
    azimuth = math.radians(lighting.light_azimuth_deg)
    elevation = math.radians(lighting.light_elevation_deg)
    return torch.tensor(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        ],
        dtype=torch.float32,
    )


def shade(
    render: MeshRender,
    lighting: LightingConfig,
    sensor: SensorConfig,
    raycaster: MeshRaycaster | None = None,
) -> torch.Tensor:
    """Linear radiance of a rendered view under one directional light plus ambient light.

    Args:
        render: albedo (B, 3, H, W), normals, points and depth of the view.
        lighting: the light; ``lighting.shadows`` needs ``raycaster``.
        sensor: for the gamma of the albedo.
        raycaster: the scene's caster, used for shadow rays.

    Returns:
        (B, 3, H, W) float32 linear radiance (before exposure); sky pixels get the sky colour.
    """
    to_light = light_direction(lighting)
    cos_light = torch.einsum("bchw,c->bhw", render.normals, to_light).clamp_min(0.0)
    hit = render.depth[:, 0] > 0
    if lighting.shadows:
        if raycaster is None:
            raise ValueError("lighting.shadows needs the scene's raycaster")
        points = render.points.permute(0, 2, 3, 1).reshape(-1, 3)
        normals = render.normals.permute(0, 2, 3, 1).reshape(-1, 3)
        origins = points + 1e-3 * normals
        blocked = raycaster.cast(origins, to_light.expand_as(origins)).hit
        cos_light = cos_light * (~blocked).reshape(cos_light.shape).to(cos_light.dtype)
    irradiance = lighting.ambient + lighting.light_intensity * cos_light
    linear = render.albedo.clamp(0.0, 1.0) ** sensor.gamma * irradiance[:, None]
    sky = torch.tensor(lighting.sky_color, dtype=torch.float32) ** sensor.gamma
    return torch.where(hit[:, None], linear, sky[None, :, None, None].expand_as(linear))


def expose(
    linear: torch.Tensor,
    lighting: LightingConfig,
    sensor: SensorConfig,
    generator: torch.Generator,
    exposure_scales: torch.Tensor | None = None,
) -> torch.Tensor:
    """Apply exposure, white balance, sensor noise and gamma encoding.

    Args:
        linear: (B, 3, H, W) linear radiance (already averaged over motion-blur sub-frames).
        lighting: exposure and white balance of the sequence.
        sensor: noise levels and gamma.
        generator: random source of the noise.
        exposure_scales: (B,) per-frame multipliers of ``lighting.exposure`` (auto exposure),
            or ``None`` for the sequence's fixed exposure.

    Returns:
        (B, 3, H, W) float32 image in [0, 1].
    """
    check_shape(linear, "B,3,H,W", "linear")
    gains = torch.tensor(lighting.white_balance, dtype=torch.float32) * lighting.exposure
    if exposure_scales is None:
        signal = (linear * gains[None, :, None, None]).clamp(0.0, 1.0)
    else:
        check_shape(exposure_scales, f"{linear.shape[0]}", "exposure_scales")
        frame_gains = gains[None, :] * exposure_scales.to(torch.float32)[:, None]
        signal = (linear * frame_gains[:, :, None, None]).clamp(0.0, 1.0)
    noise = torch.randn(signal.shape, generator=generator, dtype=signal.dtype)
    noise_std = sensor.read_noise_std + sensor.shot_noise_std * signal.sqrt()
    return (signal + noise * noise_std).clamp(0.0, 1.0) ** (1.0 / sensor.gamma)
