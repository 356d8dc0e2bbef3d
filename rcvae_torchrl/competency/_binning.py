"""Grouped histogram entropies on a fixed grid, vectorised and memory-bounded (private).

Shared by :func:`~rcvae_torchrl.competency.histogram_entropy` (one group) and the histogram
estimator of :func:`~rcvae_torchrl.competency.decompose_uncertainty` (one group per ensemble
member, optionally re-labelled by random permutations for the shuffle correction). For each
column (one batch element and dimension) it needs the pooled bin counts and the per-group bin
counts, for the groups as given and for every relabelling.

Counting works on integer cell codes: each column owns a contiguous block of cells (one per bin
it spans, plus one for ended samples), so one ``torch.bincount`` over ``cell·G + group`` counts
every column and group at once, without sorting. The codes are computed once per chunk and reused
by every relabelling, which only changes the ``group`` term; before they are reused they are
renumbered over the occupied cells (one more ``bincount``), so each relabelling touches no empty
bin. Only when the columns span far more bins than they hold samples are the codes the ranks of
the samples' bins among the column's distinct bins (one sort per chunk), so memory stays
proportional to the samples.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import torch
from torch import Tensor

LN2 = math.log(2.0)

#: Default bound on the number of sample entries processed at once by the histogram estimators.
#: The peak working memory is a few tens of bytes per entry, so the default keeps it well under
#: 100 MB whatever the input size; 2**18 was the fastest of 2**16..2**20 on 2 CPU cores (the
#: cell counts of a chunk then stay in the core's cache).
CHUNK_ELEMENTS = 1 << 18

#: Without relabellings, the bins spanned are counted in place while (bins spanned × groups)
#: <= this factor × entries; beyond that, or when relabellings reuse the codes, the codes are
#: first renumbered over the occupied bins only (one ``bincount``).
DENSE_FACTOR = 4

#: When the columns span more than this factor × entries bins, the codes are the ranks among
#: the column's distinct bins instead (one sort; memory proportional to the samples).
SORT_FACTOR = 16

#: Stand-in bin id of ended samples while the live samples' lowest bin is found.
_ABOVE_ALL_BINS = 1 << 62

#: Bin ids must lie within ±this, so that they, their spans and the ended samples' stand-in
#: all fit in int64.
MAX_BIN = 1 << 61


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
    Bin ids must lie within ±:data:`MAX_BIN` (``|x / width| < 2**61``); farther samples are
    refused, since int64 cannot count their bins (they would all share one).
    """
    scaled = samples / width.to(samples.dtype)
    if scaled.numel() > 0:
        largest = scaled.abs().amax()
        if not bool(largest < MAX_BIN):
            raise ValueError(
                f"bin_width: expected samples within 2**61 bin widths of 0 to be binned, got "
                f"|sample / bin_width| up to {largest.item():.3g} (samples up to "
                f"{samples.abs().amax().item():.3g}, bin width down to "
                f"{width.amin().item():.3g}): samples this far out usually mean the imagined "
                "states diverged (a horizon far beyond the training episodes' length, a model "
                "unstable there); check the samples, or use a wider bin_width"
            )
    return torch.floor(scaled).to(torch.int64)


def shuffled_labels(perms: Tensor, n: int) -> Tensor:
    """Group labels of the pooled samples under random permutations.

    Permutation ``perm`` of the ``G·n`` pooled samples puts sample ``perm[j]`` in group ``j // n``
    (the pooled samples reordered by ``perm`` and cut into ``G`` groups of ``n``).

    Args:
        perms: int64 ``[S, G·n]`` permutations.
        n: samples per group.

    Returns:
        int64 ``[S, G·n]``: the group of every pooled sample under each permutation.
    """
    groups_of_positions = torch.arange(perms.shape[1], device=perms.device) // n
    labels = torch.empty_like(perms)
    return labels.scatter_(1, perms, groups_of_positions.expand_as(perms))


def grouped_entropies(
    ids: Tensor, ended: Tensor | None = None, relabels: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Plug-in entropies in bits of binned samples, pooled and averaged over groups.

    Args:
        ids: int64 bin ids ``[G, n, m, D]`` (group, sample, batch, dimension).
        ended: optional bool ``[G, n, m, 1]`` or ``[G, n, m, D]``: samples counted in one extra
            bin per column, whatever their ids.
        relabels: optional int64 ``[S, G·n]``: other group labels of the pooled samples (each
            label used ``n`` times), see :func:`shuffled_labels`.

    Returns:
        float64 ``[m·D]`` pooled entropies (all ``G·n`` samples), ``[m·D]`` mean over groups of
        the per-group entropies, and ``[S, m·D]`` the same mean under each relabelling (None
        without ``relabels``).
    """
    groups, n = ids.shape[0], ids.shape[1]
    flat = ids.reshape(groups * n, -1)
    flat_ended = None if ended is None else ended.expand_as(ids).reshape(groups * n, -1)
    codes, spans = _cell_codes(flat, flat_ended, groups, relabels is not None)
    codes = codes.mul_(groups)
    table = _xlog2x_table(groups * n, ids.device)
    labels = torch.arange(groups, device=ids.device).repeat_interleave(n)
    group_sum, counts = _group_xlogx_sums(codes, spans, labels, groups, table)
    pooled = counts.view(-1, groups).sum(dim=1)
    pooled_sum = _segment_sums(table.take(pooled), spans)
    # log2 N - Σ c·log2 c / N: entropies, >= 0, whose rounding can leave -4e-16 where all
    # samples share a bin
    total = (math.log2(groups * n) - pooled_sum / (groups * n)).clamp_min(0.0)
    mean_group = (math.log2(n) - group_sum / (groups * n)).clamp_min(0.0)
    relabelled = None
    if relabels is not None:
        sums = [_group_xlogx_sums(codes, spans, r, groups, table)[0] for r in relabels]
        relabelled = (math.log2(n) - torch.stack(sums) / (groups * n)).clamp_min(0.0)
    return total, mean_group, relabelled


def _cell_codes(
    flat: Tensor, ended: Tensor | None, groups: int, reused: bool
) -> tuple[Tensor, Tensor]:
    """Cell index of every sample ``[S, C]`` and the cells each column owns ``[C]``.

    Column ``j`` owns cells ``[start_j, start_j + span_j)``: first the ended samples' cell, then
    the bins from the column's lowest live bin up (all of them, only the occupied ones, or the
    column's distinct bins in order; see :data:`DENSE_FACTOR` and :data:`SORT_FACTOR`).
    """
    if ended is not None:
        flat = torch.where(ended, _ABOVE_ALL_BINS, flat)
    low = flat.amin(dim=0)
    offsets = flat - (low - 1)
    if ended is not None:
        offsets = offsets.masked_fill_(ended, 0)
    spans = offsets.amax(dim=0) + 1
    cells = float(spans.sum(dtype=torch.float64))  # a float: int64 spans may sum past 2**63
    if cells > SORT_FACTOR * flat.numel():
        offsets, spans = _ranks(offsets)
        return offsets.add_(torch.cumsum(spans, dim=0) - spans), spans
    codes = offsets.add_(torch.cumsum(spans, dim=0) - spans)
    if reused or cells * groups > DENSE_FACTOR * flat.numel():
        codes, spans = _occupied_cells(codes, spans)
    return codes, spans


def _occupied_cells(codes: Tensor, spans: Tensor) -> tuple[Tensor, Tensor]:
    """Codes renumbered over the occupied cells only (same order), and the columns' counts."""
    occupied = torch.bincount(codes.view(-1), minlength=int(spans.sum())) > 0
    renumbered = occupied.cumsum(dim=0) - 1
    occupied_up_to_end = renumbered[torch.cumsum(spans, dim=0) - 1] + 1
    return renumbered.take(codes), torch.diff(occupied_up_to_end, prepend=spans.new_zeros(1))


def _ranks(offsets: Tensor) -> tuple[Tensor, Tensor]:
    """Offsets ``[S, C]`` replaced by their rank among the column's distinct values, and the
    number of distinct values ``[C]``."""
    values, order = offsets.sort(dim=0)
    new_value = torch.ones_like(values, dtype=torch.bool)
    new_value[1:] = values[1:] != values[:-1]
    rank = new_value.cumsum(dim=0) - 1
    return torch.empty_like(rank).scatter_(0, order, rank), rank[-1] + 1


def _group_xlogx_sums(
    codes: Tensor, spans: Tensor, labels: Tensor, groups: int, table: Tensor
) -> tuple[Tensor, Tensor]:
    """Σ c·log2 c over the per-group counts of every column ``[C]``, and the counts.

    ``codes`` are ``cell·G``; one ``bincount`` over ``cell·G + label``: column ``j``'s counts
    fill ``G·span_j`` consecutive entries.
    """
    keys = codes + labels.view(-1, 1)
    counts = torch.bincount(keys.view(-1), minlength=int(spans.sum()) * groups)
    return _segment_sums(table.take(counts), spans * groups), counts


def _segment_sums(values: Tensor, lengths: Tensor) -> Tensor:
    """Sums of consecutive segments of ``values`` with the given lengths (``[C]`` -> ``[C]``)."""
    return torch.segment_reduce(values, "sum", lengths=lengths)


def _xlog2x_table(max_count: int, device: torch.device) -> Tensor:
    """``c·log2 c`` for ``c = 0..max_count`` (float64, ``0·log 0 = 0``)."""
    counts = torch.arange(max_count + 1, dtype=torch.float64, device=device)
    return torch.special.xlogy(counts, counts) / LN2
