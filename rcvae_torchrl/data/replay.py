"""Trajectory replay: episodes in a TorchRL replay buffer, windows sampled without crossing them."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer, TensorStorage
from torchrl.data.replay_buffers.samplers import SliceSampler

from rcvae_torchrl._checks import (
    check_non_negative_int,
    check_open_unit_interval,
    check_positive_int,
    check_positive_int_or_none,
    check_seed,
)

from .collection import TRAJ_KEY, check_episode_ids, check_frames_type, episode_ids

__all__ = [
    "episode_spans",
    "make_window_buffer",
    "resample_episodes",
    "sample_windows",
    "split_episodes",
]


def episode_spans(data: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """The first frame and the length of every episode of flat episodes ``data`` ``[frames]``
    (consecutive frames of one :data:`TRAJ_KEY`)."""
    lengths = torch.unique_consecutive(episode_ids(data), return_counts=True)[1]
    return torch.cumsum(lengths, 0) - lengths, lengths


def make_window_buffer(
    data: TensorDictBase, window: int, max_size: int | None = None
) -> TensorDictReplayBuffer:
    """A replay buffer holding ``data`` ``[frames]``, sampling windows of ``window`` steps.

    ``SliceSampler`` finds episodes by :data:`TRAJ_KEY`, so windows never cross an episode
    boundary; episodes shorter than ``window`` are never drawn (``strict_length``).
    ``max_size``: the storage's capacity, at least the frames of ``data`` (a smaller one would
    keep only the last frames, and the episodes' recorded starts would point at frames gone);
    None: exactly those frames.
    """
    if isinstance(window, bool) or not isinstance(window, int) or window < 2:
        raise ValueError(f"window: expected >= 2 steps (an integer), got {window!r}")
    _check_flat(data)
    if max_size is not None:
        check_positive_int("max_size", max_size)
        if max_size < data.shape[0]:
            raise ValueError(
                f"max_size: expected at least the {data.shape[0]} frames of data (a smaller "
                f"storage would drop the first ones), got {max_size}"
            )
    first, lengths = episode_spans(data)
    if int(lengths.max()) < window:
        raise ValueError(
            f"window: expected at most the longest episode ({int(lengths.max())} steps), "
            f"got {window}"
        )
    sampler = SliceSampler(
        slice_len=window,
        traj_key=TRAJ_KEY,
        strict_length=True,
        truncated_key=None,
        cache_values=True,
    )
    if max_size is None or max_size == data.shape[0]:
        # a storage made of a copy of the frames: the same buffer as a lazy storage extended
        # with them, without TorchRL's INFO line for every storage it initialises
        buffer = TensorDictReplayBuffer(storage=TensorStorage(data.clone()), sampler=sampler)
    else:
        buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(max_size), sampler=sampler)
        buffer.extend(data)
    # the first frame of every episode long enough for a window (``sample_windows``' starts)
    buffer.episode_starts = first[lengths >= window]
    return buffer


def resample_episodes(data: TensorDictBase, generator: torch.Generator | None = None) -> TensorDict:
    """A bootstrap resample of the episodes of ``data`` ``[frames]``: as many episodes as it
    holds, drawn uniformly with replacement (Efron 1979), whole and in the order drawn, each
    copy with its own episode id (0, 1, ...). About 1 - 1/e = 63 % of the episodes are in it,
    some several times."""
    _check_flat(data)
    first, lengths = episode_spans(data)
    chosen = torch.randint(len(first), (len(first),), generator=generator)
    starts, counts = first[chosen], lengths[chosen]
    offsets = torch.cumsum(counts, 0) - counts
    total = int(counts.sum())
    frames = torch.repeat_interleave(starts - offsets, counts) + torch.arange(total)
    out = data[frames]
    out.set(TRAJ_KEY, torch.repeat_interleave(torch.arange(len(first)), counts).to(data[TRAJ_KEY]))
    return out


def sample_windows(
    buffer: TensorDictReplayBuffer | Sequence[TensorDictReplayBuffer],
    num_windows: int,
    window: int,
    members: int | None = None,
    generators: Sequence[torch.Generator] | None = None,
    start_windows: int = 0,
) -> TensorDict:
    """Windows ``[W, L]``, or ``[E, W, L]`` with independent draws for each of ``members``,
    from a buffer of :func:`make_window_buffer`.

    Independent draws give each ensemble member its own windows at each step (drawn with
    replacement); over many steps every member sees all of the buffer's data. For members
    that differ in the data they see, give each its own buffer (below). With
    ``generators`` (one per member), member ``m``'s windows come from the ``m``-th alone, so a
    member's data does not depend on which other members are drawn with it; otherwise all
    draws come from torch's global generator.

    ``start_windows`` (with ``generators``): the first ``start_windows`` windows of each member
    begin at the first step of an episode drawn uniformly, as every imagined episode begins;
    uniform window positions put few windows there (one in about episode length − L).

    ``buffer`` may also be one buffer per member (with ``generators``): member ``m`` draws from
    the ``m``-th, e.g. its own bootstrap resample of the episodes (:func:`resample_episodes`).
    """
    buffers = None
    if not isinstance(buffer, TensorDictReplayBuffer):
        if isinstance(buffer, (str, bytes)) or not isinstance(buffer, Sequence):
            raise TypeError(
                "buffer: expected a buffer of make_window_buffer, or a sequence of them (one "
                f"per member), got {type(buffer).__name__}"
            )
        buffers = list(buffer)
        for m, own in enumerate(buffers):
            if not isinstance(own, TensorDictReplayBuffer):
                raise TypeError(
                    f"buffer[{m}]: expected a buffer of make_window_buffer, got "
                    f"{type(own).__name__}"
                )
        if generators is None or len(buffers) != len(generators):
            raise ValueError(
                f"buffer: expected one buffer, or one per member with generators, got "
                f"{len(buffers)} buffers and "
                f"{'no' if generators is None else len(generators)} generators"
            )
    check_positive_int("num_windows", num_windows)
    check_positive_int_or_none("members", members)
    check_non_negative_int("start_windows", start_windows)
    if generators is not None:
        if isinstance(generators, torch.Generator) or not isinstance(generators, Sequence):
            raise TypeError(
                f"generators: expected a sequence of torch.Generator (one per member), got "
                f"{type(generators).__name__}"
            )
        for m, generator in enumerate(generators):
            if not isinstance(generator, torch.Generator):
                raise TypeError(
                    f"generators[{m}]: expected a torch.Generator, got {type(generator).__name__}"
                )
    for own in [buffer] if buffers is None else buffers:
        if own.sampler.slice_len != window:
            raise ValueError(
                f"window: expected the buffer's window of {own.sampler.slice_len} steps (the "
                f"window given to make_window_buffer: its sampler keeps windows inside an "
                f"episode for that length only), got {window}"
            )
    if start_windows and generators is None:
        raise ValueError("start_windows: expected generators (one per member) with it")
    if not 0 <= start_windows <= num_windows:
        raise ValueError(
            f"start_windows: expected 0..num_windows={num_windows}, got {start_windows}"
        )
    if generators is not None:
        if members is None or len(generators) != members:
            raise ValueError(
                f"generators: expected one per member ({members}), got {len(generators)}"
            )
        draws = []
        for m, generator in enumerate(generators):
            own = buffer if buffers is None else buffers[m]
            own.set_rng(generator)
            draw = own.sampler.sample(own.storage, (num_windows - start_windows) * window)[0]
            if start_windows:
                draw = _with_episode_starts(own, draw, start_windows, window, generator)
            own.set_rng(None)
            draws.append(draw)
        if buffers is not None:  # a read of each member's own storage
            reads = [b.storage.get(d) for b, d in zip(buffers, draws, strict=True)]
            return torch.stack(reads).reshape(members, num_windows, window)
        # one read of the storage for all members: a buffer.sample per member costs almost as
        # much again as its draw (its own read, its metadata, a stack)
        index = tuple(torch.cat(rows) for rows in zip(*draws, strict=True))
        return buffer.storage.get(index).reshape(members, num_windows, window)
    draws = num_windows * (members or 1)
    flat = buffer.sample(draws * window)
    shape = (draws, window) if members is None else (members, num_windows, window)
    return flat.reshape(*shape)


def _with_episode_starts(
    buffer: TensorDictReplayBuffer,
    draw: tuple[torch.Tensor, ...],
    count: int,
    window: int,
    generator: torch.Generator,
) -> tuple[torch.Tensor, ...]:
    """``count`` windows from episode starts put before the sampler's ``draw`` (flat frame
    indices of a 1-D storage)."""
    starts = buffer.episode_starts
    chosen = starts[torch.randint(len(starts), (count,), generator=generator)]
    frames = (chosen[:, None] + torch.arange(window)).reshape(-1).to(draw[0])
    return (torch.cat([frames, draw[0]]), *draw[1:])


def split_episodes(
    data: TensorDictBase, val_fraction: float, seed: int = 0
) -> tuple[TensorDict, TensorDict]:
    """Split ``data`` ``[frames]`` into (train, validation) by whole episodes."""
    check_open_unit_interval("val_fraction", val_fraction, "a fraction")
    _check_flat(data)
    ids = episode_ids(data)
    episodes = torch.unique(ids)
    if episodes.numel() < 2:
        raise ValueError(f"data: expected >= 2 episodes to split, got {episodes.numel()}")
    g = torch.Generator().manual_seed(check_seed("seed", seed))
    n_val = min(max(1, round(val_fraction * episodes.numel())), episodes.numel() - 1)
    val_ids = episodes[torch.randperm(episodes.numel(), generator=g)[:n_val]]
    is_val = torch.isin(ids, val_ids)
    return data[~is_val], data[is_val]


def _check_flat(data: object) -> None:
    check_frames_type(data)
    if data.ndim != 1 or TRAJ_KEY not in data.keys(True):
        raise ValueError(
            f"data: expected a flat TensorDict [frames] with {TRAJ_KEY} episode ids, "
            f"got batch {tuple(data.shape)} with keys {sorted(map(str, data.keys(True)))[:6]}"
        )
    if data.shape[0] == 0:
        raise ValueError("data: expected at least one frame, got an empty TensorDict")
    check_episode_ids(data)
