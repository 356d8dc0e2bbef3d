"""The histogram decomposition as it was before the counting was rewritten (benchmark only).

Kept verbatim (less the checks) so that ``benchmarks/competency.py`` can time the library's
histogram estimator against it in the same run and check that both give the same numbers: each
shuffle permutation re-binned the permuted samples from scratch, and the counts came from a
``bincount`` over per-column offsets (few bins) or from sorting (many bins).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from rcvae_torchrl.competency._binning import batch_chunks, bin_ids

LN2 = math.log(2.0)
CHUNK_ELEMENTS = 1 << 19
DENSE_FACTOR = 4


def histogram_decomposition_before(
    samples: Tensor,
    width: Tensor,
    ended: Tensor | None = None,
    shuffles: int = 0,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """Total and aleatoric bits ``[*batch, D]`` of ``[E, N, *batch, D]`` samples."""
    members, n, dim = samples.shape[0], samples.shape[1], samples.shape[-1]
    flat = samples.reshape(members, n, -1, dim)
    flat_ended = None if ended is None else ended.reshape(members, n, -1, 1)
    perms = [torch.randperm(members * n, generator=generator) for _ in range(shuffles)]
    parts = []
    for part in batch_chunks(flat.shape[2], members * n * dim, CHUNK_ELEMENTS):
        ids = bin_ids(flat[:, :, part], width)
        if flat_ended is not None:
            terminal = ids.amin(dim=(0, 1), keepdim=True) - 1
            ids = torch.where(flat_ended[:, :, part], terminal, ids)
        total, aleatoric = _grouped_entropies(ids)
        if perms:
            aleatoric = _shuffle_corrected(ids, total, aleatoric, perms)
        parts.append((total, aleatoric))
    return tuple(torch.cat(p).reshape(samples.shape[2:]).to(samples.dtype) for p in zip(*parts))


def _shuffle_corrected(
    ids: Tensor, total: Tensor, aleatoric: Tensor, perms: list[Tensor]
) -> Tensor:
    members, n = ids.shape[0], ids.shape[1]
    pooled = ids.reshape(members * n, *ids.shape[2:])
    null = torch.zeros_like(total)
    for perm in perms:
        _, shuffled = _grouped_entropies(pooled[perm].reshape(ids.shape))
        null += (total - shuffled) / len(perms)
    epistemic = (total - aleatoric - null).clamp(0.0, math.log2(members))
    return total - epistemic


def _grouped_entropies(ids: Tensor) -> tuple[Tensor, Tensor]:
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
    groups = offsets.shape[0]
    start = torch.cumsum(spans, dim=0) - spans
    group = torch.arange(groups, device=offsets.device).view(groups, 1, 1, 1)
    flat = (offsets + start.view(offsets.shape[2:])) * groups + group
    bins = int(spans.sum())
    counts = torch.bincount(flat.view(-1), minlength=bins * groups)
    pooled = counts.view(bins, groups).sum(dim=-1)
    max_count = offsets.shape[0] * offsets.shape[1]
    pooled_sum = torch.segment_reduce(_xlog2x_counts(pooled, max_count), "sum", lengths=spans)
    group_sum = torch.segment_reduce(
        _xlog2x_counts(counts, max_count), "sum", lengths=spans * groups
    )
    return pooled_sum, group_sum


def _xlog2x_counts(counts: Tensor, max_count: int) -> Tensor:
    if max_count + 1 > counts.numel():
        return _xlog2x(counts.to(torch.float64))
    table = torch.arange(max_count + 1, dtype=torch.float64, device=counts.device)
    return _xlog2x(table)[counts]


def _sorted_xlogx_sums(offsets: Tensor) -> tuple[Tensor, Tensor]:
    groups, n = offsets.shape[0], offsets.shape[1]
    group = torch.arange(groups, device=offsets.device).view(groups, 1, 1, 1)
    keys = (offsets * groups + group).permute(2, 3, 0, 1).reshape(-1, groups * n)
    keys = keys.sort(dim=1).values
    pooled = torch.div(keys, groups, rounding_mode="floor")
    return _run_xlog2x_sums(pooled), _run_xlog2x_sums(keys)


def _run_xlog2x_sums(sorted_keys: Tensor) -> Tensor:
    rows, length = sorted_keys.shape
    ends = torch.ones(rows, length, dtype=torch.bool, device=sorted_keys.device)
    ends[:, :-1] = sorted_keys[:, 1:] != sorted_keys[:, :-1]
    end_positions = ends.view(-1).nonzero().squeeze(1)
    counts = torch.diff(end_positions, prepend=end_positions.new_tensor([-1]))
    out = torch.zeros(rows, dtype=torch.float64, device=sorted_keys.device)
    return out.index_add_(0, end_positions // length, _xlog2x(counts.to(torch.float64)))


def _xlog2x(counts: Tensor) -> Tensor:
    return torch.special.xlogy(counts, counts) / LN2
