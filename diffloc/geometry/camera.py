"""Pinhole camera with radial-tangential (OpenCV / EuRoC) distortion.

Conventions (see ``ARCHITECTURE.md``):

- Camera frame is OpenCV: x right, y down, z forward.
- Pixel ``(u, v)``: integer coordinates are pixel centres, ``(0, 0)`` is the centre of the
  top-left pixel, so the image covers ``[-0.5, width - 0.5) x [-0.5, height - 0.5)``.
- Distortion ``(k1, k2, p1, p2)`` acts on normalised coordinates ``(x, y) = (X/Z, Y/Z)``::

      r2 = x^2 + y^2,  radial = 1 + k1 r2 + k2 r2^2
      x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
      y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
      u = fx x_d + cx,  v = fy y_d + cy

- A :class:`PinholeCamera` holds a batch of cameras: intrinsics of shape ``(...)`` (scalar
  tensors for one camera). Point tensors ``(..., N, k)`` broadcast their leading dimensions
  with the camera batch shape.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass
from typing import Any

import torch

from diffloc.checks import ShapeError, check_finite, check_positive_int, check_shape
from diffloc.geometry.se3 import invert, transform_points

__all__ = ["MIN_DEPTH", "PinholeCamera", "pose_jacobian_map"]

MIN_DEPTH = 1e-6
"""Points with camera-frame ``z <= MIN_DEPTH`` (metres) are not projectable."""

_MAX_UNDISTORT_ITERATIONS = 20


def _undistort_tolerance(dtype: torch.dtype) -> float:
    """Largest residual |distort(x) - x_d| at which the Newton iteration stops."""
    return 1e-14 if dtype == torch.float64 else 1e-7


@functools.lru_cache(maxsize=8)
def pose_jacobian_map(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The Jacobian of the normalised projection w.r.t. the pose as a linear map.

    With ``(x, y) = (X / Z, Y / Z)`` the normalised projection of a camera-frame point and
    ``u = (x, y, 1, 1/Z)``, the derivatives w.r.t. a left twist ``[v, w]`` of ``T_cw`` (as in
    :meth:`PinholeCamera.project_jacobian_pose`)::

        d(x, y)/dv = [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
        d(x, y)/dw = [[-x y, 1 + x^2, -y], [-(1 + y^2), x y, x]]

    are linear in the products ``u_a u_b``: ``J = (u u^T).flatten() @ map``, so a batch of
    Jacobians costs one outer product and one small matrix product.

    Args:
        dtype: floating dtype of the map.
        device: its device.

    Returns:
        (16, 12) map from ``(u u^T)`` flattened (index ``4 a + b``) to the Jacobian
        flattened parameter-major (index ``2 k + c`` for ``d (x, y)_c / d twist_k``, i.e. the
        (6, 2) transposed Jacobian row-major). Cached: never modify it in place.

    Example:
        >>> u = torch.tensor([0.0, 0.0, 1.0, 0.5], dtype=torch.float64)  # point (0, 0, 2)
        >>> J_t = ((u[:, None] * u).flatten() @ pose_jacobian_map(torch.float64, u.device))
        >>> J_t.view(6, 2).T.tolist()
        [[0.5, 0.0, 0.0, 0.0, 1.0, 0.0], [0.0, 0.5, 0.0, -1.0, 0.0, 0.0]]
    """
    x, y, one, iz = range(4)
    terms = (  # (a, b, coefficient of u_a u_b) for d (x, y)_c / d twist_k, index 2 k + c
        ((one, iz, 1.0),),  # dx/dv_x
        (),  # dy/dv_x
        (),  # dx/dv_y
        ((one, iz, 1.0),),  # dy/dv_y
        ((x, iz, -1.0),),  # dx/dv_z
        ((y, iz, -1.0),),  # dy/dv_z
        ((x, y, -1.0),),  # dx/dw_x
        ((one, one, -1.0), (y, y, -1.0)),  # dy/dw_x
        ((one, one, 1.0), (x, x, 1.0)),  # dx/dw_y
        ((x, y, 1.0),),  # dy/dw_y
        ((y, one, -1.0),),  # dx/dw_z
        ((x, one, 1.0),),  # dy/dw_z
    )
    with torch.inference_mode(False):  # an ordinary tensor even if first made in that mode
        out = torch.zeros(16, len(terms), dtype=dtype, device=device)
        for column, entries in enumerate(terms):
            for a, b, value in entries:
                out[4 * a + b, column] = value
    return out


def _as_float_tensor(value: Any, dtype: torch.dtype, device: torch.device | None) -> torch.Tensor:
    if isinstance(value, torch.Tensor):
        return value.to(dtype=dtype, device=device if device is not None else value.device)
    return torch.as_tensor(value, dtype=dtype, device=device)


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    """A batch of pinhole cameras sharing one image size.

    Attributes:
        fx: (...) focal length in pixels along u (positive).
        fy: (...) focal length in pixels along v (positive).
        cx: (...) principal point u (pixel-centre convention).
        cy: (...) principal point v.
        width: image width in pixels (positive int).
        height: image height in pixels (positive int).
        distortion: (..., 4) radial-tangential ``(k1, k2, p1, p2)``, or ``None`` for an
            ideal pinhole.

    Python numbers are accepted and become tensors; all parameters are cast to one floating
    dtype (the promoted dtype of the floating tensors given, distortion included, else torch's
    default) and broadcast to one batch shape.

    Raises:
        ValueError: width/height not positive ints, non-positive or non-finite focal lengths,
            non-finite principal point or distortion.
        ShapeError: a distortion tensor whose last dimension is not 4, or batch shapes that
            do not broadcast.

    Example:
        >>> cam = PinholeCamera(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
        >>> uv, valid = cam.project(torch.tensor([[0.0, 0.0, 2.0]]))
        >>> uv
        tensor([[319.5000, 239.5000]])
    """

    fx: torch.Tensor
    fy: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor
    width: int
    height: int
    distortion: torch.Tensor | None = None

    def __post_init__(self) -> None:
        width = check_positive_int(self.width, "camera width")
        height = check_positive_int(self.height, "camera height")
        values = {"fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy}
        tensors = [v for v in values.values() if isinstance(v, torch.Tensor)]
        if isinstance(self.distortion, torch.Tensor):
            tensors.append(self.distortion)
        float_tensors = [t for t in tensors if t.is_floating_point()]
        if float_tensors:
            dtype = float_tensors[0].dtype
            for t in float_tensors[1:]:
                dtype = torch.promote_types(dtype, t.dtype)
        else:
            dtype = torch.get_default_dtype()
        device = tensors[0].device if tensors else None
        converted = {k: _as_float_tensor(v, dtype, device) for k, v in values.items()}
        distortion = self.distortion
        shapes = [t.shape for t in converted.values()]
        if distortion is not None:
            distortion = _as_float_tensor(distortion, dtype, converted["fx"].device)
            check_shape(distortion, "*,4", "distortion")
            shapes.append(distortion.shape[:-1])
        try:
            batch = torch.broadcast_shapes(*shapes)
        except RuntimeError as exc:
            raise ValueError(f"camera parameter batch shapes do not broadcast: {shapes}") from exc
        for name, t in converted.items():
            check_finite(t, name)
        if not bool((converted["fx"] > 0).all() and (converted["fy"] > 0).all()):
            raise ValueError("focal lengths fx and fy must be positive")
        if distortion is not None:
            check_finite(distortion, "distortion")
            distortion = distortion.expand(*batch, 4)
        for name, t in converted.items():
            object.__setattr__(self, name, t.expand(batch))
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)
        object.__setattr__(self, "distortion", distortion)

    # ------------------------------------------------------------------ constructors

    @classmethod
    def from_fov(
        cls,
        width: int,
        height: int,
        hfov_rad: float | torch.Tensor,
        distortion: torch.Tensor | None = None,
        dtype: torch.dtype | None = None,
    ) -> PinholeCamera:
        """Camera with square pixels and the principal point at the image centre.

        ``fx = fy = width / (2 tan(hfov / 2))``, ``cx = (width - 1) / 2``,
        ``cy = (height - 1) / 2`` (pixel-centre convention).

        Args:
            width: image width in pixels.
            height: image height in pixels.
            hfov_rad: horizontal field of view in radians, in ``(0, pi)``; a tensor of shape
                ``(...)`` gives a batch of cameras.
            distortion: optional (..., 4) ``(k1, k2, p1, p2)``.
            dtype: dtype of the intrinsics; default: the dtype of ``distortion`` when it is a
                floating tensor, else torch's default dtype.

        Returns:
            The camera.

        Raises:
            ValueError: a field of view outside ``(0, pi)`` or a bad width/height.

        Example:
            >>> cam = PinholeCamera.from_fov(640, 480, math.pi / 2)
            >>> float(cam.fx), float(cam.cx)
            (320.0, 319.5)
        """
        width = check_positive_int(width, "camera width")
        height = check_positive_int(height, "camera height")
        if dtype is None:
            if isinstance(distortion, torch.Tensor) and distortion.is_floating_point():
                dtype = distortion.dtype
            else:
                dtype = torch.get_default_dtype()
        hfov = torch.as_tensor(hfov_rad, dtype=torch.float64)
        if not bool(torch.isfinite(hfov).all() and (hfov > 0).all() and (hfov < math.pi).all()):
            raise ValueError(f"hfov_rad must be in (0, pi), got {hfov_rad}")
        focal = (width / (2.0 * torch.tan(0.5 * hfov))).to(dtype)
        return cls(
            fx=focal,
            fy=focal.clone(),
            cx=torch.full_like(focal, (width - 1) / 2.0),
            cy=torch.full_like(focal, (height - 1) / 2.0),
            width=width,
            height=height,
            distortion=distortion,
        )

    @classmethod
    def from_K(
        cls,
        K: torch.Tensor,
        width: int,
        height: int,
        distortion: torch.Tensor | None = None,
    ) -> PinholeCamera:
        """Camera from a calibration matrix (skew must be zero).

        Args:
            K: (..., 3, 3) ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``.
            width: image width in pixels.
            height: image height in pixels.
            distortion: optional (..., 4) ``(k1, k2, p1, p2)``.

        Returns:
            The camera.

        Example:
            >>> K = torch.tensor([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
            >>> PinholeCamera.from_K(K, 640, 480).K.equal(K)
            True
        """
        check_shape(K, "*,3,3", "K")
        return cls(
            fx=K[..., 0, 0],
            fy=K[..., 1, 1],
            cx=K[..., 0, 2],
            cy=K[..., 1, 2],
            width=width,
            height=height,
            distortion=distortion,
        )

    # ------------------------------------------------------------------ tensor-dataclass API

    @property
    def batch_shape(self) -> torch.Size:
        """Shape ``(...)`` of the camera batch (``()`` for one camera)."""
        return self.fx.shape

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the intrinsics."""
        return self.fx.dtype

    @property
    def device(self) -> torch.device:
        """Device of the intrinsics."""
        return self.fx.device

    @property
    def K(self) -> torch.Tensor:
        """(..., 3, 3) calibration matrices ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
        zero = torch.zeros_like(self.fx)
        one = torch.ones_like(self.fx)
        rows = (self.fx, zero, self.cx, zero, self.fy, self.cy, zero, zero, one)
        return torch.stack(rows, dim=-1).reshape(*self.batch_shape, 3, 3)

    def to(self, *args: Any, **kwargs: Any) -> PinholeCamera:
        """Copy with all tensors moved/cast as by ``torch.Tensor.to`` (``self`` when nothing
        changes).

        Example:
            >>> PinholeCamera.from_fov(64, 48, 1.0).to(torch.float64).dtype
            torch.float64
        """

        def move(t: torch.Tensor) -> torch.Tensor:
            return t.to(*args, **kwargs)

        fields = {name: move(getattr(self, name)) for name in ("fx", "fy", "cx", "cy")}
        fields["distortion"] = None if self.distortion is None else move(self.distortion)
        if all(fields[name] is getattr(self, name) for name in fields):
            return self
        if fields["fx"].dtype not in (torch.float32, torch.float64):  # converted and checked
            return dataclasses.replace(self, **fields)
        return self._derived(**fields)

    def __getitem__(self, index: Any) -> PinholeCamera:
        """Index the camera batch dimensions, e.g. ``cams[0]`` or ``cams[1:, None]``."""
        if len(self.batch_shape) == 0:
            raise IndexError("cannot index a single (unbatched) camera")
        index_d = (*index, slice(None)) if isinstance(index, tuple) else (index, slice(None))
        return self._derived(
            fx=self.fx[index],
            fy=self.fy[index],
            cx=self.cx[index],
            cy=self.cy[index],
            distortion=None if self.distortion is None else self.distortion[index_d],
        )

    def _derived(self, **fields: torch.Tensor | None) -> PinholeCamera:
        """A copy with tensor fields taken (cast, moved or indexed) from this validated camera.

        They keep its checked properties, so the copy skips :meth:`__post_init__` (a dozen
        reductions, most of the cost of ``to`` in inner loops).
        """
        camera = object.__new__(PinholeCamera)
        for field in dataclasses.fields(self):
            object.__setattr__(
                camera, field.name, fields.get(field.name, getattr(self, field.name))
            )
        return camera

    def scaled(self, factor: float) -> PinholeCamera:
        """Camera of the image resized by ``factor`` (e.g. 0.5 halves width and height).

        The new size is ``round(width * factor) x round(height * factor)``. Intrinsics follow
        the pixel-centre convention with the realised per-axis ratios ``s_x = new_w / w``,
        ``s_y = new_h / h`` (equal to ``factor`` when the sizes divide exactly):
        ``fx' = fx s_x``, ``cx' = (cx + 0.5) s_x - 0.5`` (same for y). Distortion acts on
        normalised coordinates and is unchanged.

        Args:
            factor: positive scale factor.

        Returns:
            The resized camera.

        Raises:
            ValueError: a non-positive or non-finite factor, or an empty resized image.

        Example:
            >>> cam = PinholeCamera.from_fov(640, 480, 1.0).scaled(0.5)
            >>> cam.width, cam.height, float(cam.cx)
            (320, 240, 159.5)
        """
        if not (isinstance(factor, int | float) and math.isfinite(factor) and factor > 0):
            raise ValueError(f"scale factor must be a positive finite number, got {factor!r}")
        new_w, new_h = round(self.width * factor), round(self.height * factor)
        if new_w < 1 or new_h < 1:
            raise ValueError(
                f"scaling a {self.width}x{self.height} image by {factor} leaves no pixels"
            )
        sx, sy = new_w / self.width, new_h / self.height
        return dataclasses.replace(
            self,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=(self.cx + 0.5) * sx - 0.5,
            cy=(self.cy + 0.5) * sy - 0.5,
            width=new_w,
            height=new_h,
        )

    # ------------------------------------------------------------------ internals

    def _focal(self) -> torch.Tensor:
        """(..., 1, 2) focal lengths, broadcastable against (..., N, 2)."""
        return torch.stack((self.fx, self.fy), dim=-1)[..., None, :]

    def _centre(self) -> torch.Tensor:
        """(..., 1, 2) principal points, broadcastable against (..., N, 2)."""
        return torch.stack((self.cx, self.cy), dim=-1)[..., None, :]

    def _distort_and_jacobian(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Distorted coordinates (..., N, 2) and their Jacobian d xy_d / d xy (..., N, 2, 2)."""
        if self.distortion is None:
            eye = torch.eye(2, dtype=xy.dtype, device=xy.device)
            return xy, eye.expand(*xy.shape, 2)
        k1, k2, p1, p2 = self.distortion[..., None, :].unbind(-1)  # each (..., 1)
        x, y = xy.unbind(-1)
        xx, yy, xy_ = x * x, y * y, x * y
        r2 = xx + yy
        radial = 1.0 + r2 * (k1 + k2 * r2)
        x_d = x * radial + 2.0 * p1 * xy_ + p2 * (r2 + 2.0 * xx)
        y_d = y * radial + p1 * (r2 + 2.0 * yy) + 2.0 * p2 * xy_
        dradial = 2.0 * (k1 + 2.0 * k2 * r2)  # d radial / d(x or y) = dradial * (x or y)
        j00 = radial + dradial * xx + 2.0 * p1 * y + 6.0 * p2 * x
        j01 = dradial * xy_ + 2.0 * p1 * x + 2.0 * p2 * y
        j10 = dradial * xy_ + 2.0 * p1 * x + 2.0 * p2 * y
        j11 = radial + dradial * yy + 6.0 * p1 * y + 2.0 * p2 * x
        jac = torch.stack((j00, j01, j10, j11), dim=-1).reshape(*j00.shape, 2, 2)
        return torch.stack((x_d, y_d), dim=-1), jac

    @staticmethod
    def _solve2x2(jac: torch.Tensor, rhs: torch.Tensor) -> torch.Tensor:
        """Solve ``jac @ x = rhs`` for (..., 2, 2) and (..., 2) in closed form."""
        a, b, c, d = jac[..., 0, 0], jac[..., 0, 1], jac[..., 1, 0], jac[..., 1, 1]
        det = a * d - b * c
        r0, r1 = rhs.unbind(-1)
        return torch.stack((d * r0 - b * r1, a * r1 - c * r0), dim=-1) / det[..., None]

    def _normalise(self, uv: torch.Tensor) -> torch.Tensor:
        return (uv - self._centre()) / self._focal()

    # ------------------------------------------------------------------ distortion

    def distort(self, xy_normalized: torch.Tensor) -> torch.Tensor:
        """Apply the radial-tangential distortion to normalised image coordinates.

        Args:
            xy_normalized: (..., N, 2) ideal normalised coordinates ``(X/Z, Y/Z)``.

        Returns:
            (..., N, 2) distorted normalised coordinates (the input when there is no
            distortion).

        Example:
            >>> cam = PinholeCamera.from_fov(64, 48, 1.0, distortion=torch.tensor([0.1, 0, 0, 0]))
            >>> cam.distort(torch.tensor([[1.0, 0.0]]))
            tensor([[1.1000, 0.0000]])
        """
        check_shape(xy_normalized, "*,N,2", "xy_normalized")
        return self._distort_and_jacobian(xy_normalized)[0]

    def undistort_normalized(self, xy_distorted: torch.Tensor) -> torch.Tensor:
        """Invert :meth:`distort` by Newton's method.

        Iterates (without autograd) until the residual ``|distort(x) - x_d|`` is below
        1e-14 (float64) / 1e-7 (float32), at most 20 times, then takes one differentiable
        Newton step from the solution so that gradients w.r.t. the input and the distortion
        coefficients are the implicit-function gradients. Converges to better than 1e-10 in
        float64 over the whole image for EuRoC-level distortion. Where the distortion model is
        not invertible (far outside the calibrated field of view) the result is unspecified.

        Args:
            xy_distorted: (..., N, 2) distorted normalised coordinates.

        Returns:
            (..., N, 2) ideal normalised coordinates.

        Example:
            >>> cam = PinholeCamera.from_fov(64, 48, 1.0, distortion=torch.tensor([0.1, 0, 0, 0]))
            >>> cam.undistort_normalized(torch.tensor([[1.1, 0.0]]))
            tensor([[1., 0.]])
        """
        check_shape(xy_distorted, "*,N,2", "xy_distorted")
        if self.distortion is None:
            return xy_distorted
        tol = _undistort_tolerance(xy_distorted.dtype)
        with torch.no_grad():
            target = xy_distorted.detach()
            xy = target.clone()
            for _ in range(_MAX_UNDISTORT_ITERATIONS):
                xy_d, jac = self._distort_and_jacobian(xy)
                residual = xy_d - target
                if residual.numel() == 0 or float(residual.abs().max()) <= tol:
                    break
                xy = xy - self._solve2x2(jac, residual)
        xy_d, jac = self._distort_and_jacobian(xy)
        return xy - self._solve2x2(jac, xy_d - xy_distorted)

    # ------------------------------------------------------------------ projection

    def project(self, points_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Project camera-frame points to pixels (distortion applied).

        Args:
            points_cam: (..., N, 3) points in the OpenCV camera frame.

        Returns:
            ``(uv, valid)``: (..., N, 2) pixel coordinates and (..., N) bool, true where
            ``z > MIN_DEPTH``. ``uv`` of invalid points is finite but meaningless (they are
            projected as if at ``z = 1``). ``valid`` does not test the image bounds; see
            :meth:`in_image`.

        Example:
            >>> cam = PinholeCamera.from_fov(640, 480, math.pi / 2)
            >>> cam.project(torch.tensor([[1.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))[1]
            tensor([ True, False])
        """
        check_shape(points_cam, "*,N,3", "points_cam")
        z = points_cam[..., 2]
        valid = z > MIN_DEPTH
        z_safe = torch.where(valid, z, torch.ones_like(z))
        xy = points_cam[..., :2] / z_safe[..., None]
        xy_d = xy if self.distortion is None else self._distort_and_jacobian(xy)[0]
        return xy_d * self._focal() + self._centre(), valid

    def project_world(
        self, points_world: torch.Tensor, T_wc: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Project world points seen from camera poses ``T_wc`` (camera-to-world).

        Args:
            points_world: (..., N, 3) points in the world frame.
            T_wc: (..., 4, 4) camera-to-world transforms.

        Returns:
            ``(uv, valid)`` as in :meth:`project`.

        Example:
            >>> cam = PinholeCamera.from_fov(640, 480, math.pi / 2)
            >>> cam.project_world(torch.tensor([[0.0, 0.0, 2.0]]), torch.eye(4))[0]
            tensor([[319.5000, 239.5000]])
        """
        check_shape(points_world, "*,N,3", "points_world")
        check_shape(T_wc, "*,4,4", "T_wc")
        return self.project(transform_points(invert(T_wc), points_world))

    def unproject(self, uv: torch.Tensor, depth: torch.Tensor | None = None) -> torch.Tensor:
        """Back-project pixels to camera-frame points (distortion removed first).

        Args:
            uv: (..., N, 2) pixel coordinates.
            depth: optional (..., N) z-depth (not range) of each pixel; ``None`` gives rays
                with ``z = 1``. Depth 0 ("no measurement") gives the camera centre.

        Returns:
            (..., N, 3) points ``depth * (x, y, 1)`` in the camera frame.

        Example:
            >>> cam = PinholeCamera.from_fov(640, 480, math.pi / 2)
            >>> cam.unproject(torch.tensor([[319.5, 239.5]]), torch.tensor([2.0]))
            tensor([[0., 0., 2.]])
        """
        check_shape(uv, "*,N,2", "uv")
        xy = self.undistort_normalized(self._normalise(uv))
        rays = torch.cat((xy, torch.ones_like(xy[..., :1])), dim=-1)
        if depth is None:
            return rays
        check_shape(depth, "*,N", "depth")
        if depth.shape[-1] != uv.shape[-2]:
            raise ShapeError(
                f"depth must have shape (..., N) with N = {uv.shape[-2]} as in uv, "
                f"got {tuple(depth.shape)}"
            )
        return rays * depth[..., None]

    def undistort_points(self, uv: torch.Tensor) -> torch.Tensor:
        """Pixels of the ideal (undistorted) pinhole camera with the same ``K``.

        Args:
            uv: (..., N, 2) distorted pixel coordinates.

        Returns:
            (..., N, 2) undistorted pixel coordinates.

        Example:
            >>> cam = PinholeCamera.from_fov(640, 480, 1.2)
            >>> cam.undistort_points(torch.tensor([[10.0, 20.0]]))
            tensor([[10., 20.]])
        """
        check_shape(uv, "*,N,2", "uv")
        xy = self.undistort_normalized(self._normalise(uv))
        return xy * self._focal() + self._centre()

    def pixel_grid(self, dtype: torch.dtype | None = None) -> torch.Tensor:
        """Coordinates of all pixel centres.

        Args:
            dtype: output dtype (default: the camera's dtype).

        Returns:
            (H, W, 2) tensor with ``grid[v, u] == (u, v)``.

        Example:
            >>> PinholeCamera.from_fov(3, 2, 1.0).pixel_grid()[1, 2]
            tensor([2., 1.])
        """
        dtype = self.dtype if dtype is None else dtype
        u = torch.arange(self.width, dtype=dtype, device=self.device)
        v = torch.arange(self.height, dtype=dtype, device=self.device)
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        return torch.stack((uu, vv), dim=-1)

    def in_image(self, uv: torch.Tensor) -> torch.Tensor:
        """Whether pixel coordinates fall inside the image ``[-0.5, W-0.5) x [-0.5, H-0.5)``.

        Args:
            uv: (..., N, 2) pixel coordinates.

        Returns:
            (..., N) bool mask (false for NaN).

        Example:
            >>> PinholeCamera.from_fov(4, 4, 1.0).in_image(torch.tensor([[3.4, 0.0], [3.5, 0]]))
            tensor([ True, False])
        """
        check_shape(uv, "*,N,2", "uv")
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5) & (u < self.width - 0.5) & (v >= -0.5) & (v < self.height - 0.5)

    # ------------------------------------------------------------------ Jacobians

    def project_jacobian_point(self, points_cam: torch.Tensor) -> torch.Tensor:
        """Analytic Jacobian of :meth:`project` w.r.t. the camera-frame point.

        ``d uv / d X = diag(fx, fy) @ D @ [[1/z, 0, -x/z^2], [0, 1/z, -y/z^2]]`` where ``D`` is
        the 2x2 Jacobian of the distortion at the normalised point.

        Args:
            points_cam: (..., N, 3) points in the camera frame.

        Returns:
            (..., N, 2, 3) Jacobians (meaningless where ``z <= MIN_DEPTH``).

        Example:
            >>> cam = PinholeCamera.from_fov(640, 480, math.pi / 2)
            >>> cam.project_jacobian_point(torch.tensor([[0.0, 0.0, 2.0]]))[0, 0]
            tensor([160.,   0.,   0.])
        """
        check_shape(points_cam, "*,N,3", "points_cam")
        z = points_cam[..., 2]
        z_safe = torch.where(z > MIN_DEPTH, z, torch.ones_like(z))
        inv_z = 1.0 / z_safe
        xy = points_cam[..., :2] * inv_z[..., None]
        x, y = xy.unbind(-1)
        zero = torch.zeros_like(inv_z)
        j_norm = torch.stack((inv_z, zero, -x * inv_z, zero, inv_z, -y * inv_z), dim=-1)
        j_norm = j_norm.reshape(*inv_z.shape, 2, 3)
        j_dist = self._distort_and_jacobian(xy)[1]
        return self._focal()[..., None] * (j_dist @ j_norm)

    def project_jacobian_pose(self, points_cam: torch.Tensor) -> torch.Tensor:
        """Analytic Jacobian of :meth:`project` w.r.t. a left perturbation of ``T_cw``.

        With ``X_cam = T_cw X_world`` and ``delta = [v, w]`` a twist in the ordering of
        :mod:`diffloc.geometry.se3`, this is ``d project(se3_exp(delta) @ X_cam) / d delta`` at
        ``delta = 0``, i.e. ``J_point @ [I, -hat(X_cam)]`` (the perturbation acts in the camera
        frame, on the world-to-camera transform). To update a camera-to-world pose ``T_wc``
        with the solved step, use ``T_wc <- T_wc @ se3_exp(-delta)``.

        Args:
            points_cam: (..., N, 3) points in the camera frame.

        Returns:
            (..., N, 2, 6) Jacobians, columns ordered ``(v_x, v_y, v_z, w_x, w_y, w_z)``.

        Example:
            >>> cam = PinholeCamera.from_fov(640, 480, math.pi / 2)
            >>> cam.project_jacobian_pose(torch.tensor([[0.0, 0.0, 2.0]])).shape
            torch.Size([1, 2, 6])
        """
        check_shape(points_cam, "*,N,3", "points_cam")
        # Channel-first (..., k, N) intermediates: torch's element-wise kernels are much
        # faster with N innermost than with tiny trailing dimensions.
        z = points_cam[..., 2]
        inv_z = 1.0 / torch.where(z > MIN_DEPTH, z, torch.ones_like(z))
        x, y = points_cam[..., 0] * inv_z, points_cam[..., 1] * inv_z
        u = torch.stack((x, y, torch.ones_like(x), inv_z), dim=-2)  # (..., 4, N)
        outer = (u[..., :, None, :] * u[..., None, :, :]).flatten(-3, -2)  # (..., 16, N)
        j = (pose_jacobian_map(u.dtype, u.device).T @ outer).unflatten(-2, (6, 2))
        if self.distortion is not None:  # d xy_d / d xy @ j without a tiny matrix product
            d = self._distort_and_jacobian(torch.stack((x, y), dim=-1))[1].movedim(-3, -1)
            j = torch.addcmul(
                d[..., None, :, 0, :] * j[..., 0:1, :], d[..., None, :, 1, :], j[..., 1:2, :]
            )
        j = j * self._focal()[..., None]  # (..., 6, 2, N) times (fx, fy)
        return j.movedim(-1, -3).transpose(-1, -2)  # (..., N, 2, 6) view
