"""Indexed particle layout ↔ member-major layout.

A planner or a model env holds a flat batch of particles ``[B, ...]`` and a ``member [B]``
tensor saying which ensemble member each particle follows (PETS trajectory sampling). The
ensemble computes in member-major layout ``[E, C, ...]`` (C = the largest member count), one
batched matmul per layer. :class:`MemberLayout` packs particles into member-major slots
(padding unused slots with zeros) and unpacks the results.

Cost: one stable sort of ``member`` to build the layout, then one ``index_copy`` per packed
tensor and one ``index_select`` per unpacked tensor, i.e. O(B·F) memory traffic. Weights are
never gathered per particle (that would cost O(B·in·out) memory per layer). When members are
evenly spread (round-robin), there is no padding. ``benchmarks/world_model_speed.py``
measures the overhead against the member-major path.
"""

from __future__ import annotations

import torch

from rcvae_torchrl._checks import check_positive_int

__all__ = ["MemberLayout"]


class MemberLayout:
    """Maps particle i with member ``member[i]`` to slot ``(member[i], rank of i in its member)``.

    Args:
        member: int64 ``[B]`` with values in ``[0, ensemble_size)``.
        ensemble_size: number of members E.

    Example:
        >>> layout = MemberLayout(torch.tensor([1, 0, 1]), ensemble_size=2)
        >>> packed = layout.pack(torch.tensor([[10.0], [20.0], [30.0]]))
        >>> packed.squeeze(-1)
        tensor([[20.,  0.],
                [10., 30.]])
        >>> layout.unpack(packed).squeeze(-1)
        tensor([10., 20., 30.])
    """

    def __init__(self, member: torch.Tensor, ensemble_size: int) -> None:
        if not isinstance(member, torch.Tensor) or member.dtype not in (torch.int64, torch.int32):
            got = member.dtype if isinstance(member, torch.Tensor) else type(member).__name__
            raise TypeError(f"member: expected an int64 tensor [B], got {got}")
        if member.dim() != 1:
            raise ValueError(f"MemberLayout: member must be 1-D [B], got {tuple(member.shape)}.")
        check_positive_int("ensemble_size", ensemble_size)
        self.ensemble_size = ensemble_size
        self.batch_size = member.shape[0]
        try:
            counts = torch.bincount(member, minlength=ensemble_size)
        except RuntimeError:  # a negative member
            counts = None
        if counts is None or counts.numel() > ensemble_size:  # no extra pass over member
            raise ValueError(
                f"member: expected values in [0, {ensemble_size}), got range "
                f"[{int(member.min())}, {int(member.max())}]"
            )
        self.capacity = max(int(counts.max()), 1) if member.numel() else 1
        sorted_member, order = torch.sort(member, stable=True)
        starts = torch.cumsum(counts, 0) - counts
        rank = torch.arange(member.shape[0], device=member.device) - starts[sorted_member]
        slot = torch.empty_like(member)
        slot[order] = sorted_member * self.capacity + rank
        self.slot = slot

    def pack(self, x: torch.Tensor) -> torch.Tensor:
        """Particles ``[B, *F]`` → member-major ``[E, C, *F]`` (empty slots are zeros)."""
        flat = x.new_zeros((self.ensemble_size * self.capacity, *x.shape[1:]))
        flat.index_copy_(0, self.slot, x)
        return flat.view(self.ensemble_size, self.capacity, *x.shape[1:])

    def unpack(self, y: torch.Tensor) -> torch.Tensor:
        """Member-major ``[E, C, *F]`` → particles ``[B, *F]``."""
        return y.reshape(self.ensemble_size * self.capacity, *y.shape[2:]).index_select(
            0, self.slot
        )
