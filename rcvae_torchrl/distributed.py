"""Scale out on ``torch.distributed``: ranks from the launcher, shards of work, gathers.

The library's stages that have independent pieces of work (ensemble members in
:func:`~rcvae_torchrl.training.train_ensemble`, start states in
:class:`~rcvae_torchrl.competency.CompetencyAssessor`, real episodes in
:func:`~rcvae_torchrl.agent.real_outcomes`) split them over the ranks of a process group and
gather the results on every rank. Nothing changes in a single process: without a process group
and without a launcher's ``RANK`` / ``WORLD_SIZE``, every helper here acts as the only rank of
one (rank 0, world size 1). Before :func:`init`, :func:`rank` and :func:`world_size` read those
variables, so a process a launcher started knows its place (and does not write as rank 0) even
before the group is up.

Launch with ``torchrun`` (it sets ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR`` and
``MASTER_PORT``), call :func:`init` once at the start of the program (gloo on CPU, NCCL when the
ranks use GPUs) and :func:`teardown` at the end, or use :func:`session`::

    torchrun --nproc_per_node=4 my_script.py

Independent jobs (say, two ensembles to train) run side by side over the ranks with
:func:`parts`: each job on its own part of the ranks, whose ranks share that job's work.

Every piece of work is seeded by its index (a member, a chunk of start states, an episode), so
the gathered result equals the single-process one under the same seed, whatever the number of
ranks.
"""

from __future__ import annotations

import contextlib
import datetime
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import torch
import torch.distributed as dist

from rcvae_torchrl._checks import check_device, is_integer

__all__ = [
    "Part",
    "Replicas",
    "all_gather",
    "alone",
    "barrier",
    "broadcast",
    "init",
    "is_active",
    "is_main",
    "parts",
    "rank",
    "replicas",
    "session",
    "shard",
    "teardown",
    "work_generator",
    "world_size",
]

_T = TypeVar("_T")


#: The process group of the part of the ranks this rank works in (see :func:`parts`; or
#: :data:`_ALONE`, see :func:`alone`), or nothing: then every helper acts on all the ranks.
_PART: list[Any] = []


#: Stands for the group of this rank alone, within :func:`alone`.
_ALONE = object()


#: One entry per :func:`parts` block entered without a process group (the one process is the
#: only part): a :func:`parts` inside one is refused, as it is with a group.
_SINGLE_PARTS: list[None] = []


def _group() -> Any:
    """The process group the helpers act on: this rank's part, else ``None`` (all ranks)."""
    return _PART[-1] if _PART else None


def is_active() -> bool:
    """Whether a process group of more than one rank is up (within :func:`parts`: whether this
    rank's part has more than one; within :func:`alone`: no)."""
    if _group() is _ALONE:
        return False
    return dist.is_available() and dist.is_initialized() and dist.get_world_size(_group()) > 1


def rank() -> int:
    """This process's rank: the process group's (within :func:`parts`, its rank in its part;
    within :func:`alone`, 0), else ``RANK`` from the launcher, else 0."""
    if _group() is _ALONE:
        return 0
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(_group())
    rank_ = _environ_int("RANK", 0, 0)
    if "RANK" not in os.environ:
        return rank_
    if "WORLD_SIZE" not in os.environ:
        raise ValueError(
            f"RANK, WORLD_SIZE: RANK is {os.environ['RANK']!r} in the environment but "
            "WORLD_SIZE is not set; expected both (a launcher such as torchrun sets both) or "
            "neither (a single process)"
        )
    world = _environ_int("WORLD_SIZE", 1, 1)
    if rank_ >= world:
        raise ValueError(
            f"RANK, WORLD_SIZE: expected RANK < WORLD_SIZE in the environment, got RANK "
            f"{os.environ['RANK']!r} and WORLD_SIZE {os.environ['WORLD_SIZE']!r}"
        )
    return rank_


def world_size() -> int:
    """The number of ranks: the process group's (within :func:`parts`, this rank's part's;
    within :func:`alone`, 1), else ``WORLD_SIZE``, else 1."""
    if _group() is _ALONE:
        return 1
    if dist.is_available() and dist.is_initialized():
        return dist.get_world_size(_group())
    return _environ_int("WORLD_SIZE", 1, 1)


def _environ_int(name: str, default: int, low: int) -> int:
    """The launcher's variable ``name`` (``torchrun`` sets ``RANK`` and ``WORLD_SIZE``) as an
    int >= ``low``, ``default`` where unset; a clear error naming it otherwise."""
    text = os.environ.get(name)
    if text is None:
        return default
    try:
        value = int(text)
    except ValueError:
        value = low - 1
    if value < low:
        raise ValueError(f"{name}: expected an integer >= {low} in the environment, got {text!r}")
    return value


def is_main() -> bool:
    """Whether this is rank 0 (within :func:`parts`, of its part), the one that writes files
    and logs."""
    return rank() == 0


def init(backend: str | None = None, timeout_s: float = 6 * 3600.0) -> bool:
    """Join the process group the launcher describes (``WORLD_SIZE > 1``); returns whether a
    group of more than one rank is up.

    Args:
        backend: ``"gloo"`` or ``"nccl"``; default NCCL when CUDA is available, else gloo.
            With NCCL each rank takes the GPU ``LOCAL_RANK``.
        timeout_s: how long a rank waits for the others at a collective (long stages such as
            training an agent run on rank 0 while the others wait).
    """
    if backend not in (None, "gloo", "nccl"):
        raise ValueError(f"backend: expected 'gloo', 'nccl' or None, got {backend!r}")
    if world_size() <= 1 or (dist.is_available() and dist.is_initialized()):
        return is_active()
    if not dist.is_available():
        raise RuntimeError("WORLD_SIZE > 1 but torch.distributed is not available in this build")
    if backend is None:
        backend = "nccl" if torch.cuda.is_available() else "gloo"
    if backend not in ("gloo", "nccl"):
        raise ValueError(f"backend: expected 'gloo' or 'nccl', got {backend!r}")
    if backend == "nccl":
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", 0)))
    dist.init_process_group(backend, timeout=datetime.timedelta(seconds=timeout_s))
    return is_active()


def teardown() -> None:
    """Leave the process group (a no-op without one)."""
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


@contextlib.contextmanager
def session(backend: str | None = None) -> Iterator[bool]:
    """:func:`init` on entry, :func:`teardown` on exit; yields whether ranks are active."""
    try:
        yield init(backend)
    finally:
        teardown()


def shard(n: int, rank_: int | None = None, world: int | None = None) -> range:
    """The contiguous block of ``range(n)`` that rank ``rank_`` of ``world`` works on.

    Blocks are in rank order and differ in size by at most one (the first ``n % world`` ranks
    take one more); a rank beyond ``n`` gets an empty range.
    """
    if not is_integer(n) or n < 0:
        raise ValueError(f"n: expected a non-negative int, got {n!r}")
    rank_ = rank() if rank_ is None else rank_
    world = world_size() if world is None else world
    if not (is_integer(rank_) and is_integer(world)):
        raise ValueError(f"rank, world: expected ints, got {rank_!r}, {world!r}")
    n, rank_, world = int(n), int(rank_), int(world)
    if world < 1 or not 0 <= rank_ < world:
        raise ValueError(f"rank, world: expected 0 <= rank < world, got {rank_}, {world}")
    size, extra = divmod(n, world)
    start = rank_ * size + min(rank_, extra)
    return range(start, start + size + (rank_ < extra))


@dataclass(frozen=True)
class Part:
    """Which of :func:`parts`' parts of the ranks this rank is in: ``index`` of ``parts``."""

    index: int
    parts: int


@contextlib.contextmanager
def parts(n: int) -> Iterator[Part]:
    """Split the ranks into ``n`` parts of consecutive ranks (sizes differ by at most one, as
    :func:`shard` splits them) and, inside the block, make every helper here act on this rank's
    part alone: :func:`rank`, :func:`world_size`, :func:`is_main`, :func:`is_active`,
    :func:`shard`, :func:`all_gather`, :func:`broadcast`, :func:`barrier`. So independent jobs
    run side by side over the ranks, each job's ranks sharing its work (with one rank, the job
    runs as in a single process). Yields this rank's :class:`Part`; leaves through a barrier
    of all the ranks.

    Every rank must enter it, with the same ``n`` (it creates the parts' process groups).
    Without a process group the one process is the only part, whatever ``n``. Parts do not
    nest, and within a part of several ranks :func:`replicas` with ``size > 1`` (which splits
    all the ranks) raises.

    Example (two ensembles trained at once on 2 ranks, one each)::

        with distributed.parts(2) as part:
            train_ensemble(models[part.index], ...)  # each part's rank 0 writes its checkpoint

    Raises:
        ValueError: ``n`` is not an int from 1 to the number of ranks, or parts are nested.
    """
    if not is_integer(n) or n < 1:
        raise ValueError(f"n: expected a positive int (the number of parts), got {n!r}")
    n = int(n)
    if _SINGLE_PARTS or any(group is not _ALONE for group in _PART):
        raise ValueError("parts: already within parts of the ranks (parts do not nest)")
    if not is_active():
        _SINGLE_PARTS.append(None)
        try:
            yield Part(0, 1)
        finally:
            _SINGLE_PARTS.pop()
        return
    world, rank_ = world_size(), rank()
    if n > world:
        raise ValueError(f"n: expected at most the number of ranks, {world}, got {n}")
    blocks = [shard(world, k, n) for k in range(n)]
    groups = _made([dist.new_group(list(block)) for block in blocks])  # every rank: every group
    index = next(k for k, block in enumerate(blocks) if rank_ in block)
    _PART.append(groups[index])
    done = False
    try:
        yield Part(index, n)
        done = True
    finally:
        _PART.pop()
        if done:  # (after an error the launcher ends the other ranks: no one to wait for)
            dist.barrier()
        dist.destroy_process_group(groups[index])


def _made(groups: _T) -> _T:
    """``groups`` once every rank has made them (a barrier of all the ranks). Gloo connects a
    group's ranks while each makes it, and a rank that went on and destroyed the group (as
    parts do when their block raises) while a peer was still connecting broke the peer's
    connect ("Connection closed by peer"): within 100 such groups, in 3 of 3 tries on a loaded
    machine."""
    dist.barrier()
    return groups


@contextlib.contextmanager
def alone() -> Iterator[None]:
    """Inside the block this rank acts as the only rank of one: every helper here behaves as
    in a single process and makes no collective call. For work one rank does while the others
    wait for it (a stage that runs on rank 0 alone): a library call inside it that would share
    its work over the ranks (and wait for ranks that never come) does it all here."""
    _PART.append(_ALONE)
    try:
        yield
    finally:
        _PART.pop()


@dataclass(frozen=True)
class Replicas:
    """This rank's place when every block of work is shared by ``size`` ranks (data parallel).

    Consecutive ranks form a block's group: ranks ``block * size`` to ``block * size + size -
    1`` hold the same block and each computes its share of it; ``group`` is their process
    group (``None`` when ``size`` is 1), e.g. for ``DistributedDataParallel``.
    """

    block: int
    blocks: int
    index: int
    size: int
    group: Any = None


def replicas(size: int) -> Replicas:
    """Split the ranks into ``world_size() / size`` groups of ``size`` consecutive ranks.

    Every rank must call it, in the same order (it creates the process groups). Without a
    process group the one process is the only replica of the only block, whatever ``size``.

    Raises:
        ValueError: ``size`` is not a positive int dividing the world size.
    """
    if not is_integer(size) or size < 1:
        raise ValueError(f"size: expected a positive int, got {size!r}")
    size = int(size)
    if not is_active():
        return Replicas(0, 1, 0, 1)
    world, rank_ = world_size(), rank()
    if size > 1 and _PART:
        raise ValueError(
            f"size: groups of {size} ranks cannot be made within parts of the ranks (making "
            "them takes all the ranks); use size 1 there, or no parts"
        )
    if world % size:
        raise ValueError(
            f"size: expected a divisor of the world size {world} (ranks per block), got {size}"
        )
    group = _made(dist.new_subgroups(group_size=size))[0] if size > 1 else None
    return Replicas(rank_ // size, world // size, rank_ % size, size, group)


def work_generator(*keys: int, device: str | torch.device = "cpu") -> torch.Generator:
    """A generator seeded by ``keys`` alone (e.g. the run's seed, a work item's index and a
    stream number), so a piece of work draws the same numbers on whichever rank runs it.

    The keys go through NumPy's ``SeedSequence``: nearby keys give unrelated streams, but keys
    that differ only by trailing zeros give the same one (``(5, 3)`` and ``(5, 3, 0)``), and
    the keys carry no purpose: the training's window stream of member m (``(seed, m, 0)``)
    and the forecast's noise stream of start chunk m (also ``(seed, m, 0)``) are the same
    numbers when both use one seed. Their uses differ (window positions against imagination
    noise), so nothing here depends on the coincidence; give a new use its own stream number
    (not 0) or its own seed.
    """
    if not keys or any(not is_integer(k) or k < 0 for k in keys):
        raise ValueError(f"keys: expected one or more non-negative ints, got {keys!r}")
    check_device(device)
    words = np.random.SeedSequence([int(k) for k in keys]).generate_state(2, np.uint32)
    generator = torch.Generator(device=device)
    generator.manual_seed(int(words[0]) << 31 | int(words[1]) >> 1)
    return generator


def all_gather(obj: Any) -> list[Any]:
    """Every rank's ``obj``, in rank order, on every rank (``[obj]`` without a group).

    Objects are pickled; put tensors on the CPU first (NCCL moves the pickled bytes through
    the rank's GPU).
    """
    if not is_active():
        return [obj]
    out: list[Any] = [None] * world_size()
    dist.all_gather_object(out, obj, group=_group())
    return out


def broadcast(obj: Any, src: int = 0) -> Any:
    """Rank ``src``'s ``obj`` on every rank (``obj`` itself without a group; within
    :func:`parts`, ``src`` is a rank of the part)."""
    if not is_active():
        return obj
    box = [obj]
    group = _group()
    if group is None:
        dist.broadcast_object_list(box, src=src)
    else:  # src is a rank of the part
        dist.broadcast_object_list(box, group=group, group_src=src)
    return box[0]


def barrier() -> None:
    """Wait for every rank (a no-op without a group)."""
    if is_active():
        dist.barrier(group=_group())
