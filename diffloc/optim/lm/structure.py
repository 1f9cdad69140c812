"""Static sparsity of the block normal equations: free-pose slots and pose-pair blocks."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch


@functools.lru_cache(maxsize=8)
def _upper_to_full(device: torch.device) -> torch.Tensor:
    """(36,) position in the row-major upper triangle (21 entries, ``i <= j``) of every
    entry ``(i, j)`` of a symmetric 6x6 matrix, row-major. Never modified in place."""
    with torch.inference_mode(False):  # an ordinary tensor even if first made in one
        position = torch.zeros(6, 6, dtype=torch.long, device=device)
        rows, cols = torch.triu_indices(6, 6, device=device)
        position[rows, cols] = position[cols, rows] = torch.arange(21, device=device)
    return position.flatten()


def _block_flat_index(rows: torch.Tensor, cols: torch.Tensor, size: int) -> torch.Tensor:
    """(N * 36,) flat indices into a (size, size) matrix of the 6x6 blocks at slot ``rows``
    (N,), ``cols`` (N,), entries row-major within each block."""
    eye6 = torch.arange(6, device=rows.device)
    row_index = (6 * rows[:, None, None] + eye6[None, :, None]) * size
    return (row_index + 6 * cols[:, None, None] + eye6[None, None, :]).flatten()


@dataclass
class _Structure:
    """Static sparsity of the normal equations, computed once per solve.

    Free poses get slots ``0 .. P_free - 1`` and fixed poses the extra slot ``P_free``, whose
    contributions the assembly drops. ``H`` is stored as one 6x6 diagonal block per free pose
    and ``K`` upper off-diagonal blocks, one per unordered pair of distinct free poses sharing
    a residual block: block ``k`` sits at slot row ``off_rows[k] <`` column ``off_cols[k]``
    and its transpose below the diagonal. Per residual block (M,): ``a_slot`` / ``b_slot``
    are the slots of its poses (``b_slot`` is ``P_free`` for a block whose two poses are the
    same: its Jacobians add up on ``a``), ``off_index`` its upper block (``K``: none),
    ``swap`` whether pose ``a`` is that block's column, ``same`` whether both poses are one.
    ``None``: one-pose blocks (``b_slot``, ``off_index``) or all false (``swap``, ``same``).
    """

    free: torch.Tensor  # (P_free,) pose index of each slot
    num_extra: int
    off_rows: torch.Tensor  # (K,)
    off_cols: torch.Tensor  # (K,)
    a_slot: torch.Tensor
    b_slot: torch.Tensor | None = None
    off_index: torch.Tensor | None = None
    swap: torch.Tensor | None = None
    same: torch.Tensor | None = None

    @property
    def num_free(self) -> int:
        return int(self.free.numel())

    @property
    def size(self) -> int:
        """Number of unknowns ``D = 6 P_free + E``."""
        return 6 * self.num_free + self.num_extra

    @functools.cached_property
    def dense_index(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Flat (D * D) positions of the diagonal blocks (P_free * 36,), the upper blocks
        (K * 36,) and their transposes (K * 36,, entry ``(k, i, j)`` at ``(col j, row i)``)."""
        diag = torch.arange(self.num_free, device=self.free.device)
        rows, cols, size = self.off_rows, self.off_cols, self.size
        upper = _block_flat_index(rows, cols, size)
        lower = _block_flat_index(cols, rows, size).view(-1, 6, 6).mT.flatten()
        return _block_flat_index(diag, diag, size), upper, lower

    @classmethod
    def from_blocks(
        cls,
        num_poses: int,
        index_a: torch.Tensor,
        index_b: torch.Tensor | None,
        is_fixed: torch.Tensor,
        num_extra: int,
    ) -> _Structure:
        device = index_a.device
        free = torch.nonzero(~is_fixed.to(device))[:, 0]
        n_free = int(free.numel())
        slot_of = torch.full((num_poses,), n_free, dtype=torch.long, device=device)
        slot_of[free] = torch.arange(n_free, device=device)
        a_slot = slot_of[index_a]
        empty = torch.zeros(0, dtype=torch.long, device=device)
        if index_b is None:
            return cls(free, num_extra, empty, empty, a_slot)
        same = index_a == index_b
        b_slot = torch.where(same, n_free, slot_of[index_b])
        paired = (a_slot < n_free) & (b_slot < n_free)
        key = torch.minimum(a_slot, b_slot) * n_free + torch.maximum(a_slot, b_slot)
        unique, inverse = torch.unique(key[paired], return_inverse=True)
        off_index = torch.full_like(a_slot, unique.numel())
        off_index[paired] = inverse
        swap = paired & (a_slot > b_slot)
        return cls(
            free=free,
            num_extra=num_extra,
            off_rows=torch.div(unique, n_free, rounding_mode="floor"),
            off_cols=unique % n_free,
            a_slot=a_slot,
            b_slot=b_slot,
            off_index=off_index,
            swap=swap if bool(swap.any()) else None,
            same=same if bool(same.any()) else None,
        )
