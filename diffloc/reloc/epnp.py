"""Batched EPnP (Lepetit, Moreno-Noguer & Fua, IJCV 2009): non-minimal PnP in closed form.

Every world point is written as a weighted sum of ``c`` control points,
``x_i = sum_j alpha_ij c_j`` (``sum_j alpha_ij = 1``). Projection is affine-invariant, so the
camera-frame control points satisfy two linear equations per correspondence; the solution is
a combination ``sum_k beta_k v_k`` of the right null vectors of that ``2N x 3c`` system, with
the betas fixed by the (rigid) distances between control points. The ``K`` smallest
eigenvectors are tried with ``K = 1, 2, 3`` null vectors (linearised betas, then Gauss-Newton
on the distance equations); the candidate with the smallest reprojection error wins.

Control points are the centroid plus the principal axes (scaled by their standard deviation).
Planar point sets (smallest principal variance below ``PLANAR_RATIO`` of the largest) use three
control points in the plane and ``K <= 2``, as in the paper. Exactly four non-planar points
would need four null vectors (not implemented): their pose is the P3P solution of the first
three points that best reprojects all four. Correspondences carry weights, so the same code
fits a pose to the inliers of a RANSAC model.
"""

from __future__ import annotations

import itertools

import torch

from diffloc.checks import ShapeError, check_finite, check_shape
from diffloc.reloc.p3p import p3p_flat

__all__ = ["PLANAR_RATIO", "solve_epnp"]

PLANAR_RATIO = 1e-4
"""Point sets whose smallest principal variance is below this fraction of the largest one are
solved with the planar (3 control point) variant."""

_BETA_GN_ITERATIONS = 4


def _pairs(c: int) -> tuple[list[int], list[int]]:
    a, b = zip(*itertools.combinations(range(c), 2), strict=True)
    return list(a), list(b)


def _control_points(
    points: torch.Tensor, weights: torch.Tensor, planar: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """World control points (B, c, 3) and barycentric coordinates alpha (B, N, c)."""
    total = weights.sum(-1, keepdim=True)
    centroid = (weights[..., None] * points).sum(-2) / total
    centred = points - centroid[:, None]
    cov = (centred * weights[..., None]).transpose(-1, -2) @ centred / total[..., None]
    evals, evecs = torch.linalg.eigh(cov)  # ascending
    start = 1 if planar else 0
    axes = evecs[..., start:].transpose(-1, -2)  # (B, k, 3) unit rows
    scale = torch.sqrt(evals[..., start:].clamp(min=torch.finfo(points.dtype).tiny))
    coords = (centred @ axes.transpose(-1, -2)) / scale[:, None]
    alpha = torch.cat((1.0 - coords.sum(-1, keepdim=True), coords), dim=-1)
    ctrl = torch.cat((centroid[:, None], centroid[:, None] + scale[..., None] * axes), dim=-2)
    return ctrl, alpha


def _null_space(
    alpha: torch.Tensor, xy: torch.Tensor, weights: torch.Tensor, k: int
) -> torch.Tensor:
    """The k right singular vectors (B, k, c, 3) of the weighted EPnP system."""
    B, N, c = alpha.shape
    one = torch.ones_like(xy[..., 0])
    zero = torch.zeros_like(one)
    ex = torch.stack((one, zero, -xy[..., 0]), dim=-1)  # (B, N, 3)
    ey = torch.stack((zero, one, -xy[..., 1]), dim=-1)
    Mx = (alpha[..., None] * ex[:, :, None]).reshape(B, N, 3 * c)
    My = (alpha[..., None] * ey[:, :, None]).reshape(B, N, 3 * c)
    w = weights[..., None]
    MtM = (Mx * w).transpose(-1, -2) @ Mx + (My * w).transpose(-1, -2) @ My
    vecs = torch.linalg.eigh(MtM)[1][..., :k]  # smallest eigenvalues first
    return vecs.transpose(-1, -2).reshape(B, k, c, 3)


def _initial_betas(dv: torch.Tensor, rho: torch.Tensor) -> list[torch.Tensor]:
    """Linearised betas (B, K) for K = 1 .. number of null vectors (zero-padded).

    Args:
        dv: (B, K, P, 3) control-point differences of each null vector.
        rho: (B, P) squared world distances between control points.
    """
    K = dv.shape[1]
    zero = torch.zeros_like(rho[:, 0])
    norm0 = torch.linalg.vector_norm(dv[:, 0], dim=-1)
    beta1 = (norm0 * rho.sqrt()).sum(-1) / (norm0 * norm0).sum(-1).clamp(min=1e-300)
    out = [torch.stack((beta1, *[zero] * (K - 1)), dim=-1)]
    for n in range(2, K + 1):
        ia, ib = zip(*itertools.combinations_with_replacement(range(n), 2), strict=True)
        ia, ib = list(ia), list(ib)
        factor = torch.tensor(
            [1.0 if i == j else 2.0 for i, j in zip(ia, ib, strict=True)],
            dtype=rho.dtype,
            device=rho.device,
        )
        L = (dv[:, ia] * dv[:, ib]).sum(-1).transpose(-1, -2) * factor  # (B, P, n(n+1)/2)
        prod = torch.linalg.lstsq(L, rho[..., None]).solution[..., 0]  # beta_i beta_j, i <= j
        # Products are ordered (0, 0), (0, 1), ..., (0, n-1), (1, 1), ...: (0, i) is column i.
        squares = [prod[:, ia.index(i)].clamp(min=0.0).sqrt() for i in range(n)]
        signs = [torch.ones_like(zero)] + [torch.sign(prod[:, i]) for i in range(1, n)]
        betas = [sign * square for sign, square in zip(signs, squares, strict=True)]
        out.append(torch.stack((*betas, *[zero] * (K - n)), dim=-1))
    return out


def _refine_betas(beta: torch.Tensor, dv: torch.Tensor, rho: torch.Tensor) -> torch.Tensor:
    """Gauss-Newton on ``|sum_k beta_k dv_k|^2 = rho`` for all pairs; beta (B, K)."""
    eye = torch.eye(beta.shape[-1], dtype=beta.dtype, device=beta.device)
    for _ in range(_BETA_GN_ITERATIONS):
        diff = (beta[:, :, None, None] * dv).sum(1)  # (B, P, 3)
        r = (diff * diff).sum(-1) - rho  # (B, P)
        J = 2.0 * (diff[:, None] * dv).sum(-1).transpose(-1, -2)  # (B, P, K)
        H = J.transpose(-1, -2) @ J
        damping = 1e-12 * torch.diagonal(H, dim1=-2, dim2=-1).sum(-1)[:, None, None] * eye
        step = torch.linalg.solve(H + damping + 1e-300 * eye, (J.transpose(-1, -2) @ r[..., None]))
        beta = beta - step[..., 0]
    return beta


def _absolute_orientation(
    points_world: torch.Tensor, points_cam: torch.Tensor, weights: torch.Tensor
) -> torch.Tensor:
    """Weighted rigid fit T_cw (B, 4, 4) with ``points_cam ~ R points_world + t`` (Kabsch)."""
    w = weights[..., None]
    total = w.sum(-2)
    mu_w = (w * points_world).sum(-2) / total
    mu_c = (w * points_cam).sum(-2) / total
    H = ((points_cam - mu_c[:, None]) * w).transpose(-1, -2) @ (points_world - mu_w[:, None])
    U, _, Vh = torch.linalg.svd(H)
    d = torch.linalg.det(U @ Vh)
    U = torch.cat((U[..., :2], U[..., 2:] * d[:, None, None]), dim=-1)
    R = U @ Vh
    t = mu_c - (R @ mu_w[..., None])[..., 0]
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def _reprojection_cost(
    T_cw: torch.Tensor, points_world: torch.Tensor, xy: torch.Tensor, weights: torch.Tensor
) -> torch.Tensor:
    """Weighted squared normalised-plane reprojection error (...); points behind count 1e30.

    ``T_cw`` (..., 4, 4) broadcasts with ``points_world`` (..., N, 3), ``xy`` (..., N, 2) and
    ``weights`` (..., N).
    """
    pc = points_world @ T_cw[..., :3, :3].transpose(-1, -2) + T_cw[..., None, :3, 3]
    z = pc[..., 2]
    ok = z > 0
    proj = pc[..., :2] / torch.where(ok, z, torch.ones_like(z))[..., None]
    err = ((proj - xy) ** 2).sum(-1)
    err = torch.where(ok, err, torch.full_like(err, 1e30))
    return (weights * err).sum(-1)


def _four_point_variant(
    points_world: torch.Tensor, xy: torch.Tensor, weights: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Four non-planar points: the P3P solution of the first three that best fits all four.

    EPnP's case of four null vectors is not implemented; this replaces it. Returns T_cw
    (B, 4, 4) and (B,) whether a P3P solution existed.
    """
    rays = torch.cat((xy, torch.ones_like(xy[..., :1])), dim=-1)
    rays = rays / torch.linalg.vector_norm(rays, dim=-1, keepdim=True)
    R, t, valid = p3p_flat(rays[:, :3], points_world[:, :3], refine_iterations=2)
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = torch.where(
        valid[..., None, None], R, torch.eye(3, dtype=R.dtype, device=R.device)
    )
    T[..., :3, 3] = torch.where(valid[..., None], t, torch.zeros_like(t))
    T[..., 3, 3] = 1.0
    cost = _reprojection_cost(T, points_world[:, None], xy[:, None], weights[:, None])
    cost = torch.where(valid, cost, torch.full_like(cost, torch.inf))
    best = cost.argmin(-1)
    return T[torch.arange(T.shape[0]), best], valid.any(-1)


def _epnp_variant(
    points_world: torch.Tensor, xy: torch.Tensor, weights: torch.Tensor, planar: bool
) -> torch.Tensor:
    """EPnP with 4 (general) or 3 (planar) control points; returns T_cw (B, 4, 4)."""
    ctrl, alpha = _control_points(points_world, weights, planar)
    c = ctrl.shape[1]
    K = c - 1
    ia, ib = _pairs(c)
    rho = ((ctrl[:, ia] - ctrl[:, ib]) ** 2).sum(-1)  # (B, P)
    null = _null_space(alpha, xy, weights, K)  # (B, K, c, 3)
    dv = null[:, :, ia] - null[:, :, ib]  # (B, K, P, 3)
    best_T, best_cost = None, None
    for beta in _initial_betas(dv, rho):
        beta = _refine_betas(beta, dv, rho)
        ctrl_cam = (beta[:, :, None, None] * null).sum(1)  # (B, c, 3)
        points_cam = alpha @ ctrl_cam  # (B, N, 3)
        flip = (weights * points_cam[..., 2]).sum(-1) < 0
        points_cam = torch.where(flip[:, None, None], -points_cam, points_cam)
        T = _absolute_orientation(points_world, points_cam, weights)
        cost = _reprojection_cost(T, points_world, xy, weights)
        if best_T is None:
            best_T, best_cost = T, cost
        else:
            better = cost < best_cost
            best_T = torch.where(better[:, None, None], T, best_T)
            best_cost = torch.where(better, cost, best_cost)
    return best_T


def epnp_flat(points_world: torch.Tensor, xy: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """:func:`solve_epnp` on flat float64 inputs (B, N, 3), (B, N, 2), (B, N), no checks."""
    total = weights.sum(-1, keepdim=True)
    centroid = (weights[..., None] * points_world).sum(-2) / total
    centred = points_world - centroid[:, None]
    cov = (centred * weights[..., None]).transpose(-1, -2) @ centred
    evals = torch.linalg.eigvalsh(cov)
    planar = evals[:, 0] <= PLANAR_RATIO * evals[:, 2]
    T_cw = torch.empty(points_world.shape[0], 4, 4, dtype=xy.dtype, device=xy.device)
    for flag in (False, True):
        sel = planar == flag
        if bool(sel.any()):
            T_cw[sel] = _epnp_variant(points_world[sel], xy[sel], weights[sel], flag)
    if points_world.shape[1] == 4 and bool((~planar).any()):
        sel = ~planar
        T_p3p, found = _four_point_variant(points_world[sel], xy[sel], weights[sel])
        T_cw[sel] = torch.where(found[:, None, None], T_p3p, T_cw[sel])
    return T_cw


def solve_epnp(
    points_world: torch.Tensor, xy_normalized: torch.Tensor, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """Closed-form camera pose from N >= 4 correspondences (EPnP), batched.

    No refinement is applied; :func:`diffloc.reloc.pnp.solve_pnp` adds Levenberg-Marquardt
    on the pixel reprojection error. Exact (to rounding) for noise-free data, planar or not.
    Computation is in float64.

    Args:
        points_world: (..., N, 3) world points.
        xy_normalized: (..., N, 2) undistorted normalised image coordinates ``(X/Z, Y/Z)``.
        weights: optional (..., N) non-negative weights (e.g. a float inlier mask); at least
            four points need positive weight.

    Returns:
        (..., 4, 4) world-to-camera transforms ``T_cw``.

    Raises:
        ShapeError: inconsistent shapes.
        ValueError: fewer than 4 points, non-finite inputs or negative weights.

    Example:
        >>> X = torch.tensor([[0.0, 0, 4], [1, 0, 5], [0, 1, 6], [1, 1, 4], [-1, 0, 7]]).double()
        >>> T_cw = solve_epnp(X, X[:, :2] / X[:, 2:])
        >>> torch.allclose(T_cw, torch.eye(4, dtype=torch.float64), atol=1e-9)
        True
    """
    check_shape(points_world, "*,N,3", "points_world")
    check_shape(xy_normalized, "*,N,2", "xy_normalized")
    if points_world.shape[:-1] != xy_normalized.shape[:-1]:
        raise ShapeError(
            f"points_world (..., N, 3) and xy_normalized (..., N, 2) disagree: "
            f"{tuple(points_world.shape)} vs {tuple(xy_normalized.shape)}"
        )
    if points_world.shape[-2] < 4:
        raise ValueError(f"EPnP needs at least 4 points, got {points_world.shape[-2]}")
    check_finite(points_world, "points_world")
    check_finite(xy_normalized, "xy_normalized")
    batch = points_world.shape[:-2]
    n = points_world.shape[-2]
    X = points_world.to(torch.float64).reshape(-1, n, 3)
    xy = xy_normalized.to(torch.float64).reshape(-1, n, 2)
    if weights is None:
        w = torch.ones_like(xy[..., 0])
    else:
        if weights.shape != points_world.shape[:-1]:
            raise ShapeError(
                f"weights must have shape {tuple(points_world.shape[:-1])}, "
                f"got {tuple(weights.shape)}"
            )
        check_finite(weights, "weights")
        if bool((weights < 0).any()):
            raise ValueError("weights must be non-negative")
        w = weights.to(torch.float64).reshape(-1, n)
    return epnp_flat(X, xy, w).reshape(*batch, 4, 4)
