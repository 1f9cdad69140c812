"""Assembly of the block-sparse normal equations from robustly weighted residual blocks."""

from __future__ import annotations

import torch

from diffloc.optim.lm.block_system import _System
from diffloc.optim.lm.linearize import BlockLinearization
from diffloc.optim.lm.structure import _Structure, _upper_to_full
from diffloc.optim.robust import KernelFn


def _add_products(
    out: torch.Tensor,
    index: torch.Tensor | None,
    left: torch.Tensor,
    right: torch.Tensor,
    upper: bool = False,
) -> None:
    """Add the entries of the per-block products ``left_m^T right_m`` to ``out`` in place.

    Entry ``(i, j)`` of block ``m`` is ``sum_r left[:, i, r, m] * right[:, j, r, m]``: one
    (B, M) multiply-add per residual component over all blocks at once (a Python loop over
    the ``I`` rows only). Each row of entries goes through one small reused buffer into
    ``out[:, entries, index[m]]`` by ``index_add_``, which keeps the temporaries in cache.

    Args:
        out: (B, C, S) sums, entries row-major over ``(i, j)``: ``C = I J``, or
            ``I (I + 1) / 2`` with ``upper``.
        index: (M,) int64 destination in ``[0, S)`` of every block, or ``None``: sum over
            the blocks (``S = 1``).
        left: (B, I, R, M) components of the left factors.
        right: (B, J, R, M) components of the right factors.
        upper: only the entries ``i <= j`` (``left`` and ``right`` of the same size ``I``).
    """
    R = left.shape[2]
    buffer = left.new_empty(left.shape[0], right.shape[1], left.shape[3])
    start = 0
    for i in range(left.shape[1]):
        cols = right[:, i:] if upper else right
        entries = buffer[:, : cols.shape[1]]
        torch.mul(left[:, i, None, 0], cols[:, :, 0], out=entries)
        for k in range(1, R):
            entries.addcmul_(left[:, i, None, k], cols[:, :, k])
        sums = out[:, start : start + cols.shape[1]]
        if index is None:
            sums += entries.sum(-1, keepdim=True)
        else:
            sums.index_add_(2, index, entries)
        start += cols.shape[1]


def _assemble(
    lin: BlockLinearization, mask: torch.Tensor, kernel: KernelFn, structure: _Structure
) -> _System:
    """Normal equations of the masked, robustly weighted blocks (no loop over blocks).

    Component-major: the residuals and Jacobians are read through permuted views (B, R, M)
    and (B, 6, R, M) with the blocks innermost (free when the linearization was made in that
    layout, as :meth:`~diffloc.optim.surfel_cost.SurfelReprojectionCost.linearize` does), where
    torch's element-wise kernels are fastest. Each entry of the blocks' 6x6 products
    ``J_x^T W J_y`` is a multiply-add over all blocks at once (:func:`_add_products`: the 21
    upper entries of the diagonal contributions, all 36 of the off-diagonal ones), added to
    its destination blocks by ``index_add_``.
    """
    s = structure
    keep, zero = mask[:, None, :], lin.residuals.new_zeros(())  # (B, 1, M)
    r = torch.where(keep, lin.residuals.transpose(1, 2), zero)  # (B, R, M)
    rho, weight = kernel((r * r).sum(1))
    cost = torch.where(mask, rho, zero).sum(-1).mul_(0.5)
    weight = torch.where(mask, weight, zero)[:, None, None]  # (B, 1, 1, M)

    def component_major(J: torch.Tensor) -> torch.Tensor:  # (B, M, R, N) -> (B, N, R, M)
        return torch.where(keep[:, None], J.permute(0, 3, 2, 1), zero)

    J_a = component_major(lin.jac_a)
    J_b = None if lin.jac_b is None else component_major(lin.jac_b)
    if s.same is not None:  # both poses are one: the block depends on it through both
        J_a = J_a + torch.where(s.same, J_b, zero)
    B, F, dtype, device = r.shape[0], s.num_free, r.dtype, r.device
    diag = torch.zeros(B, 21, F + 1, dtype=dtype, device=device)  # + the fixed-pose slot
    grad_p = torch.zeros(B, 6, F + 1, dtype=dtype, device=device)
    J_e = None if lin.jac_extra is None else component_major(lin.jac_extra)
    E = s.num_extra
    H_pe = torch.zeros(B, 6 * E, F + 1, dtype=dtype, device=device)
    weighted = []
    for J, slot in ((J_a, s.a_slot), (J_b, s.b_slot)):
        if J is None:
            continue
        WJ = J * weight
        weighted.append(WJ)
        _add_products(diag, slot, WJ, J, upper=True)
        _add_products(grad_p, slot, r[:, None], WJ)  # one row of 6 entries: J^T W r
        if J_e is not None:
            _add_products(H_pe, slot, WJ, J_e)
    K = s.off_rows.numel()
    off = torch.zeros(B, 36, K + 1, dtype=dtype, device=device)
    if K:
        left, right = weighted[0], J_b
        if s.swap is not None:  # pose a is the column: the block is (W J_b)^T J_a
            left, right = torch.where(s.swap, weighted[1], left), torch.where(s.swap, J_a, right)
        _add_products(off, s.off_index, left, right)
    H_ee = torch.zeros(B, E * E, 1, dtype=dtype, device=device)
    grad_e = torch.zeros(B, E, 1, dtype=dtype, device=device)
    if J_e is not None:
        WJ_e = J_e * weight
        _add_products(H_ee, None, WJ_e, J_e)
        _add_products(grad_e, None, r[:, None], WJ_e)
    diag_blocks = diag[:, _upper_to_full(device), :F].permute(0, 2, 1).reshape(B, F, 6, 6)
    # Support: the robust weights of the blocks on each pose, in residual components.
    support = torch.zeros(B, F + 1, dtype=dtype, device=device)
    block_weight = weight[:, 0, 0] * r.shape[1]
    for slot in (s.a_slot, s.b_slot):
        if slot is not None:
            support.index_add_(1, slot, block_weight)
    return _System(
        cost=cost,
        grad=torch.cat((grad_p[..., :F].transpose(1, 2).flatten(1), grad_e[..., 0]), dim=1),
        diag_blocks=diag_blocks,
        off_blocks=off[..., :K].permute(0, 2, 1).reshape(B, K, 6, 6),
        H_pe=H_pe[..., :F].reshape(B, 6, E, F).permute(0, 3, 1, 2),
        H_ee=H_ee.view(B, E, E),
        support=support[:, :F],
        structure=s,
    )
