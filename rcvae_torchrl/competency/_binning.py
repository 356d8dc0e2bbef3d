"""Grouped histogram entropies on a fixed grid, vectorised and memory-bounded (private).

Shared by :func:`~rcvae_torchrl.competency.histogram_entropy` (one group) and the histogram
estimator of :func:`~rcvae_torchrl.competency.decompose_uncertainty` (one group per ensemble
member). For each column (one batch element and dimension) it needs the pooled bin counts and the
per-group bin counts. Two exact strategies, chosen per chunk:

- dense counting (``torch.bincount``) when the bins a column spans are few, O(samples + bins);
- sorting otherwise: after sorting the keys ``bin·G + group`` along the sample axis, runs of equal
  keys are the per-group counts and runs of equal ``key // G`` the pooled counts.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import torch
from torch import Tensor

LN2 = math.log(2.0)

#: Default bound on the number of sample entries processed at once by the histogram estimators.
#: The peak working memory is a few tens of bytes per entry, so the default keeps it well under
#: 100 MB whatever the input size; 2**19 was the fastest of 2**18..2**22 on 2 CPU cores.
CHUNK_ELEMENTS = 1 << 19

#: Dense counting is used while (columns × bins spanned × groups) <= this factor × entries.
DENSE_FACTOR = 4


def batch_chunks(n_batch: int, per_item: int, chunk_elements: int) -> Iterator[slice]:
    """Slices over ``n_batch`` items so that each slice holds at most ``chunk_elements`` entries.

    A slice always holds at least one item, whatever ``per_item`` is.
    """
    step = max(1, chunk_elements // max(1, per_item))
    for start in range(0, n_batch, step):
        yield slice(start, min(start + step, n_batch))


def bin_ids(samples: Tensor, width: Tensor) -> Tensor:
    """Bin index ``floor(x / width)`` on the grid anchored at 0 (int64, same shape as samples).

    ``width`` is ``[]`` or ``[D]``. The division is done in the samples' dtype (float32 is 5x
    faster than float64 here), so bins are exact while ``|x / width| < 2**24`` for float32 input
    (``2**53`` for float64); every group is binned by the same arithmetic either way.
    """
    return torch.floor(samples / width.to(samples.dtype)).to(torch.int64)


def grouped_entropies(ids: Tensor) -> tuple[Tensor, Tensor]:
    """Plug-in entropies in bits of binned samples, pooled and averaged over groups.

    Args:
        ids: int64 bin ids ``[G, n, m, D]`` (group, sample, batch, dimension).

    Returns:
        float64 ``[m·D]`` pooled entropies (all ``G·n`` samples) and ``[m·D]`` mean over groups of
        the per-group entropies.
    """
    groups, n = ids.shape[0], ids.shape[1]
    low = ids.amin(dim=(0, 1))
    span = int((ids.amax(dim=(0, 1)) - low).max()) + 1
    columns = low.numel()
    if columns * span * groups <= DENSE_FACTOR * ids.numel():
        pooled_sum, group_sum = _dense_xlogx_sums(ids - low, span)
    else:
        pooled_sum, group_sum = _sorted_xlogx_sums(ids - low)
    total = math.log2(groups * n) - pooled_sum / (groups * n)
    mean_group = math.log2(n) - group_sum / (groups * n)
    return total, mean_group


def _dense_xlogx_sums(offsets: Tensor, span: int) -> tuple[Tensor, Tensor]:
    """Σ c·log2 c over pooled and per-group counts from ``bincount``; offsets in [0, span)."""
    groups, columns = offsets.shape[0], offsets[0, 0].numel()
    group = torch.arange(groups, device=offsets.device).view(groups, 1, 1, 1)
    column = torch.arange(columns, device=offsets.device).view(offsets.shape[2:])
    flat = offsets * groups + (column * (span * groups) + group)
    counts = torch.bincount(flat.view(-1), minlength=columns * span * groups)
    counts = counts.view(columns, span, groups).to(torch.float64)
    pooled = counts.sum(dim=-1)
    return _xlog2x(pooled).sum(dim=-1), _xlog2x(counts).sum(dim=(-2, -1))


def _sorted_xlogx_sums(offsets: Tensor) -> tuple[Tensor, Tensor]:
    """Σ c·log2 c over pooled and per-group counts from one sort of ``bin·G + group`` keys."""
    groups, n = offsets.shape[0], offsets.shape[1]
    group = torch.arange(groups, device=offsets.device).view(groups, 1, 1, 1)
    keys = (offsets * groups + group).permute(2, 3, 0, 1).reshape(-1, groups * n)
    keys = keys.sort(dim=1).values
    pooled = torch.div(keys, groups, rounding_mode="floor")
    return _run_xlog2x_sums(pooled), _run_xlog2x_sums(keys)


def _run_xlog2x_sums(sorted_keys: Tensor) -> Tensor:
    """Σ over runs of equal values of ``c·log2 c`` for each row of ``[C, L]`` -> ``[C]``.

    Every row ends a run, so in the flattened array consecutive run ends differ by exactly the
    run lengths, also across rows.
    """
    rows, length = sorted_keys.shape
    ends = torch.ones(rows, length, dtype=torch.bool, device=sorted_keys.device)
    ends[:, :-1] = sorted_keys[:, 1:] != sorted_keys[:, :-1]
    end_positions = ends.view(-1).nonzero().squeeze(1)
    counts = torch.diff(end_positions, prepend=end_positions.new_tensor([-1]))
    out = torch.zeros(rows, dtype=torch.float64, device=sorted_keys.device)
    return out.index_add_(0, end_positions // length, _xlog2x(counts.to(torch.float64)))


def _xlog2x(counts: Tensor) -> Tensor:
    """``c·log2 c`` with ``0·log 0 = 0``."""
    return torch.special.xlogy(counts, counts) / LN2
