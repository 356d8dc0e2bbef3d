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

    ``width`` is ``[]`` or ``[D]``. The division is done in the samples' dtype (float32 is several
    times faster than float64 here): a value within one rounding error of a bin edge may land in
    the neighbouring bin, but every group is binned by the same arithmetic, so bins stay shared.
    Bin ids must fit in int64 (``|x / width| < 2**62``).
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
    low, high = torch.aminmax(ids.flatten(0, 1), dim=0)
    spans = (high - low + 1).view(-1)
    if int(spans.sum()) * groups <= DENSE_FACTOR * ids.numel():
        pooled_sum, group_sum = _dense_xlogx_sums(ids - low, spans)
    else:
        pooled_sum, group_sum = _sorted_xlogx_sums(ids - low)
    total = math.log2(groups * n) - pooled_sum / (groups * n)
    mean_group = math.log2(n) - group_sum / (groups * n)
    return total, mean_group


def _dense_xlogx_sums(offsets: Tensor, spans: Tensor) -> tuple[Tensor, Tensor]:
    """Σ c·log2 c over pooled and per-group counts from one ``bincount``.

    Column ``j`` owns the cells ``[start_j, start_j + span_j)`` (times ``G`` groups) of one flat
    count array, so its size is the total number of bins the columns span.
    """
    groups = offsets.shape[0]
    start = torch.cumsum(spans, dim=0) - spans
    group = torch.arange(groups, device=offsets.device).view(groups, 1, 1, 1)
    flat = (offsets + start.view(offsets.shape[2:])) * groups + group
    bins = int(spans.sum())
    counts = torch.bincount(flat.view(-1), minlength=bins * groups)
    pooled = counts.view(bins, groups).sum(dim=-1)
    max_count = offsets.shape[0] * offsets.shape[1]
    pooled_sum = _segment_sums(_xlog2x_counts(pooled, max_count), spans)
    group_sum = _segment_sums(_xlog2x_counts(counts, max_count), spans * groups)
    return pooled_sum, group_sum


def _segment_sums(values: Tensor, lengths: Tensor) -> Tensor:
    """Sums of consecutive segments of ``values`` with the given lengths (``[C]`` -> ``[C]``)."""
    return torch.segment_reduce(values, "sum", lengths=lengths)


def _xlog2x_counts(counts: Tensor, max_count: int) -> Tensor:
    """``c·log2 c`` of integer counts in ``[0, max_count]``; a table lookup when that is cheaper."""
    if max_count + 1 > counts.numel():
        return _xlog2x(counts.to(torch.float64))
    table = torch.arange(max_count + 1, dtype=torch.float64, device=counts.device)
    return _xlog2x(table)[counts]


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
