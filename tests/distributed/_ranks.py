"""Run a function on gloo ranks spawned from pytest (``torch.multiprocessing``)."""

from __future__ import annotations

import os
import socket
from collections.abc import Callable
from typing import Any

import torch
import torch.multiprocessing as mp

from rcvae_torchrl import distributed


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _entry(rank: int, world: int, port: int, fn: Callable, args: tuple) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(rank),
        LOCAL_RANK=str(rank),
        WORLD_SIZE=str(world),
        OMP_NUM_THREADS="1",
    )
    torch.set_num_threads(1)
    with distributed.session("gloo"):
        fn(*args)


def run_ranks(fn: Callable, *args: Any, world: int = 2) -> None:
    """``fn(*args)`` on ``world`` ranks of one gloo group; raises if a rank fails or dies."""
    mp.spawn(_entry, args=(world, free_port(), fn, args), nprocs=world, join=True)
