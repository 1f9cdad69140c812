"""Ray-disk conics of surfels: the disk test and inverse depth as polynomials in pixels.

The ray through a pixel centre ``d = ((u - cx) / fx, (v - cy) / fy, 1)`` hits the plane of a
surfel (centre ``c``, unit normal ``n``, radius ``r``, camera frame) at z-depth
``t = (n.c) / (n.d)``; the pixel is covered when ``|t d - c| <= r``. Multiplying by
``(n.d)^2`` makes the test a quadratic (conic) in the pixel coordinates and ``1 / t`` an
affine function of them, bounded by the analytic bounding box of the projected ellipse.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from diffloc.render.view import _View

_BBOX_MARGIN_PX = 1e-2
"""Slack added to the analytic ellipse bounding box against float32 rounding."""
_ELLIPSE_CONDITION = 1e-3
"""Ellipses with ``4AC - B^2 <= 1e-3 * 4AC`` (aspect ratio above ~30) use the sphere bound."""


@dataclass(frozen=True)
class _Conics:
    """Ray-disk conics of M surfels; ``(2, M)`` fields hold a ``u`` row and a ``v`` row.

    ``q(du, dv) = du (A du + B dv + D) + dv (C dv + E) <= 1`` is the ray-disk test in pixel
    offsets ``(du, dv)`` from the projected centre, and the inverse hit depth is
    ``g0 + gu du + gv dv``.
    """

    AC: torch.Tensor  # (2, M) A, C
    B: torch.Tensor  # (M,)
    DE: torch.Tensor  # (2, M) D, E
    g0: torch.Tensor  # (M,)
    g_uv: torch.Tensor  # (2, M) gu, gv
    centre: torch.Tensor  # (2, M) projected centre (u, v), pixels

    def select(self, index: torch.Tensor) -> _Conics:
        """The conics of the (K,) surfels ``index``."""
        return _Conics(*(field.index_select(-1, index) for field in vars(self).values()))


def _surfel_conics(
    c: torch.Tensor, n: torch.Tensor, r: torch.Tensor, view: _View
) -> tuple[_Conics, torch.Tensor, torch.Tensor]:
    """Ray-disk conics of surfels in front of the camera.

    The ray ``d = c / cz + (du / fx, dv / fy, 0)`` meets the plane ``n.p = k`` (``k = n.c``)
    at ``t = k / (n.d)``, and ``|t d - c| <= r`` is ``|k e - (n_x a + n_y b) c|^2 <=
    r^2 (n.d)^2`` with ``e = (a, b, 0)``, ``a = du / fx``, ``b = dv / fy``. Expanding with
    ``h = cz / k`` and ``m = |c|^2 - r^2`` and dividing by ``r^2 (k / cz)^2`` gives
    ``A = h^2 (k^2 - 2 k n_x c_x + n_x^2 m) / (r f_x)^2``,
    ``B = 2 h^2 (n_x n_y m - k (n_y c_x + n_x c_y)) / (r^2 f_x f_y)``, ``C`` like ``A``,
    ``D = -2 n_x h / f_x``, ``E = -2 n_y h / f_y``; ``1 / t = 1 / cz + n_x a / k + n_y b / k``.

    Args:
        c: (3, M) centres, camera frame, ``cz > 0``.
        n: (3, M) unit normals, camera frame.
        r: (M,) radii.
        view: the camera.

    Returns:
        ``(conics, k, cc)`` with (M,) ``k = n.c`` and ``cc = |c|^2``.
    """
    cc = (c * c).sum(0)
    cxy, cz, nxy = c[:2], c[2], n[:2]
    fx, fy = view.fx, view.fy
    f = c.new_tensor([[fx], [fy]])
    k = (n * c).sum(0)
    h = cz / k
    t = (h / r).square_()
    m = cc - r * r
    kn = k * nxy  # k n_x, k n_y
    AC = (
        (k * k - 2.0 * kn * cxy)
        .addcmul_(nxy * nxy, m)
        .mul_(t / c.new_tensor([[fx * fx], [fy * fy]]))
    )
    B = (nxy[0] * nxy[1] * m).sub_(kn[1] * cxy[0]).sub_(kn[0] * cxy[1]).mul_(t * (2.0 / (fx * fy)))
    DE = nxy * h * c.new_tensor([[-2.0 / fx], [-2.0 / fy]])
    g0 = cz.reciprocal()
    centre = (cxy * g0 * f).add_(c.new_tensor([[view.cx], [view.cy]]))
    return _Conics(AC, B, DE, g0, nxy / k / f, centre), k, cc


def _ellipse_box_offsets(conics: _Conics) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounding box ``(lo, hi)``, (2, M) offsets ``(du, dv)``, of ``q(du, dv) <= 1``.

    At the extremes of ``du`` the gradient of ``q`` is along ``du`` (``dq/ddv = 0``), which
    leaves the quadratic ``a du^2 + b du - c = 0`` with ``a = 4AC - B^2`` (> 0 for an ellipse),
    ``b = 4CD - 2BE``, ``c = E^2 + 4C``; the same for ``dv`` with the roles swapped. Where
    ``a`` is not positive or loses most of its digits to cancellation (very thin ellipses, a
    relative tolerance of :data:`_ELLIPSE_CONDITION`) the offsets are NaN.
    """
    A, C = conics.AC
    B = conics.B
    ac4 = 4.0 * A * C
    a = ac4 - B * B
    a = a.masked_fill_(a <= _ELLIPSE_CONDITION * ac4.abs(), math.nan)
    CA, ED = conics.AC.flip(0), conics.DE.flip(0)
    b = (4.0 * CA * conics.DE).sub_(2.0 * B * ED)
    root = (ED * ED + 4.0 * CA).mul_(4.0 * a).addcmul_(b, b).sqrt_()
    half_inv_a = 0.5 / a
    return (-b - root).mul_(half_inv_a), (root - b).mul_(half_inv_a)


def _surfel_boxes(
    conics: _Conics,
    near: torch.Tensor,
    r: torch.Tensor,
    c: torch.Tensor,
    view: _View,
    height: int,
    width: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(2, M) int32 inclusive pixel box corners ``lo = (u_lo, v_lo)``, ``hi``, in the image.

    The box is the analytic bounding box of the projected ellipse, intersected with the
    projection bound of the surfel's bounding sphere ``f r sqrt(x^2 + z^2) / (z (z - r))``
    (the only bound for ill-conditioned ellipses). A disk reaching the camera plane projects
    to an unbounded conic and gets the whole image. Empty boxes have ``lo > hi``.
    """
    lo, hi = _ellipse_box_offsets(conics)
    cxy, cz = c[:2], c[2]
    scale = r / (cz * (cz - r)).masked_fill_(near, 0.0)  # inf where near
    half = (
        (cxy * cxy).addcmul_(cz, cz).sqrt_().mul_(scale).mul_(c.new_tensor([[view.fx], [view.fy]]))
    )
    size = c.new_tensor([[width], [height]])
    # fmax / fmin skip the NaN offsets of ill-conditioned or unbounded conics.
    lo = torch.fmax(lo, -half).add_(conics.centre).sub_(_BBOX_MARGIN_PX).ceil_()
    hi = torch.fmin(hi, half).add_(conics.centre).add_(_BBOX_MARGIN_PX).floor_()
    lo = torch.clamp(lo, torch.zeros_like(size), size)
    hi = torch.clamp(hi, torch.full_like(size, -1.0), size - 1)
    return lo.to(torch.int32), hi.to(torch.int32)


def _window_polynomials(conics: _Conics, corner: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``1 - q`` and the inverse depth in offsets ``(i, j)`` from each window's corner.

    Substituting ``du = i + a``, ``dv = j + b`` (``(a, b) = corner - centre``) into
    ``q = du (A du + B dv + D) + dv (C dv + E)`` and ``g0 + gu du + gv dv``.

    Args:
        conics: the surfels' conics.
        corner: (2, M) int32 top-left pixel ``(u0, v0)`` of each window.

    Returns:
        ``(inside, inverse_depth)``: (6, M) coefficients of ``1 - q`` on the monomials
        ``(i^2, i j, j^2, i, j, 1)`` and (3, M) of the inverse depth on ``(i, j, 1)``.
    """
    (A, C), B, (D, E), (gu, gv) = conics.AC, conics.B, conics.DE, conics.g_uv
    a, b = corner - conics.centre
    qa = torch.addcmul(D, A, a).addcmul_(B, b)  # dq/ddu at (a, b) minus A a
    qb = torch.addcmul(E, C, b)
    q_i = qa + A * a
    q_j = qb.addcmul(B, a).addcmul_(C, b)
    q_1 = (qa * a).addcmul_(qb, b)
    inside = torch.stack((A, B, C, q_i, q_j, q_1 - 1.0)).neg_()
    inverse_depth = torch.stack((gu, gv, torch.addcmul(conics.g0, gu, a).addcmul_(gv, b)))
    return inside, inverse_depth
