"""The cameras of a render batch: input checks and per-camera world-to-camera transforms.

Rules shared by the hard splatting renderers:

- **Cameras.** ``camera`` is one :class:`PinholeCamera` (batch shape ``()``) shared by all
  poses or a batch of ``B`` cameras of one image size. Point splats are placed at the
  (distorted) projection, so distorted cameras work; the surfel renderer needs an ideal
  pinhole (``distortion=None``) because it intersects pixel rays analytically.
- **Bad input.** Wrong shapes, ``B = 0`` -> :class:`~diffloc.checks.ShapeError`; non-finite
  poses -> ``ValueError``. Map entries with any NaN or infinite coordinate (centre, normal,
  radius, point) are treated as missing and *culled*; finite but invalid values (radius
  ``<= 0``, zero normal) raise ``ValueError``. Primitives behind the camera (centre or point
  with ``z <= MIN_DEPTH``) are culled; an empty map gives an empty render.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import torch

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.geometry.camera import PinholeCamera
from diffloc.geometry.se3 import invert

_MAX_PRIMITIVES = 2**31 - 1


def _check_poses(T_wc: torch.Tensor) -> int:
    """Validate (B, 4, 4) poses and return B."""
    check_shape(T_wc, "B,4,4", "T_wc")
    if T_wc.shape[0] == 0:
        raise ShapeError("T_wc must hold at least one pose, got shape (0, 4, 4)")
    check_finite(T_wc, "T_wc")
    return T_wc.shape[0]


def _check_camera(camera: PinholeCamera, batch: int) -> PinholeCamera:
    """A float32 copy of ``camera``, which must be one camera or a batch of ``batch``."""
    if not isinstance(camera, PinholeCamera):
        raise TypeError(f"camera must be a PinholeCamera, got {type(camera).__name__}")
    if tuple(camera.batch_shape) not in ((), (batch,)):
        raise ShapeError(
            f"camera batch shape must be () or ({batch},) to match T_wc, "
            f"got {tuple(camera.batch_shape)}"
        )
    return camera.to(torch.float32)


def _check_map_size(n: int, what: str, limit: int = _MAX_PRIMITIVES) -> None:
    if n > limit:
        raise ValueError(f"at most {limit} {what} can be rendered, got {n}")


@dataclass(frozen=True)
class _View:
    """One camera of a batch: world-to-camera transform and intrinsics."""

    R_cw: torch.Tensor  # (3, 3) float32
    t_cw: torch.Tensor  # (3, 1) float32
    fx: float
    fy: float
    cx: float
    cy: float
    camera: PinholeCamera  # unbatched, for the distortion model

    def to_camera(self, points_world_t: torch.Tensor, elementwise: bool = False) -> torch.Tensor:
        """(3, n) camera-frame coordinates of (3, n) world points (coordinates as rows).

        Pass ``points_world.T`` for (n, 3) points: the transposed view needs no copy. One
        matrix product by default; ``elementwise`` (:func:`_rigid_columns`, about 4x slower)
        rounds every point alike whatever n, as renders of subsets of a map need.
        """
        if elementwise:
            return _rigid_columns(self.R_cw, points_world_t, self.t_cw)
        return torch.addmm(self.t_cw, self.R_cw, points_world_t)


def _views(T_wc: torch.Tensor, camera: PinholeCamera) -> Iterator[_View]:
    """Yield the cameras of a validated batch one at a time."""
    T_cw = invert(T_wc.to(torch.float64)).to(torch.float32)
    batch = T_wc.shape[0]
    params = torch.stack((camera.fx, camera.fy, camera.cx, camera.cy), dim=-1).expand(batch, 4)
    for b, (fx, fy, cx, cy) in enumerate(params.tolist()):
        single = camera if len(camera.batch_shape) == 0 else camera[b]
        yield _View(T_cw[b, :3, :3], T_cw[b, :3, 3:], fx, fy, cx, cy, single)


def _rigid_columns(R: torch.Tensor, x: torch.Tensor, t: torch.Tensor | None = None) -> torch.Tensor:
    """``R x + t`` for (3, M) columns ``x``, elementwise: every column rounds alike whatever M.

    A matrix product picks its kernel by the number of columns, and its roundings with it
    (``(3, 3) x (3, M)`` products differ in the last bit between M = 10^4 and M = 10^5); the
    renderer draws varying subsets of a map (frustum, masks) and needs each surfel bit for bit
    alike in all of them.

    Args:
        R: (3, 3) rotation.
        x: (3, M) columns.
        t: (3, 1) translation, or ``None``.
    """
    out = R[:, :1] * x[:1] if t is None else torch.addcmul(t, R[:, :1], x[:1])
    return out.addcmul_(R[:, 1:2], x[1:2]).addcmul_(R[:, 2:], x[2:])
