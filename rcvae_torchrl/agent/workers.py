"""Real episodes in worker processes, with TorchRL's ``ParallelEnv``.

A ``ParallelEnv`` runs one env per worker process and steps them all at once, so a policy is
called once per step for every worker. To run *given* episodes there (each with its own seed,
from its own start state), each worker holds an :class:`EpisodeStartEnv`: the user's env, whose
``reset(episodes=(seeds, starts))`` seeds it (:func:`~rcvae_torchrl.data.seed_env`, transforms
with their own noise included) and puts it in the start state with a ``reset_to_state``
function (:mod:`rcvae_torchrl.agent.starts`), inside the worker, where the simulator lives.
``ParallelEnv.reset(list_of_kwargs=...)`` ships each worker its own episodes in one round trip
(:func:`start_worker_episodes`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, ParallelEnv, TransformedEnv

from rcvae_torchrl._checks import check_positive_int

from .episodes import ResetToState
from .starts import start_episodes

__all__ = ["EpisodeStartEnv", "episode_workers", "start_worker_episodes"]


class EpisodeStartEnv(TransformedEnv):
    """``env`` (unchanged) whose reset can start given episodes: what a worker process runs.

    ``reset(episodes=(seeds, starts))`` calls
    :func:`~rcvae_torchrl.agent.start_episodes` on ``env``: one seed and one start row for an
    env with ``batch_size=[]``; ``N`` seeds and starts ``[N, ...]`` for a batched env
    ``[N]``. A reset without ``episodes`` is ``env``'s own (e.g. an auto-reset after done).

    Args:
        env: any TorchRL env; its transforms stay its own (``seed_env`` reseeds them).
        reset_to_state: ``(env, start) -> tensordict``, e.g.
            :func:`~rcvae_torchrl.agent.reset_to_physics`.
    """

    def __init__(self, env: EnvBase, reset_to_state: ResetToState) -> None:
        super().__init__(env, auto_unwrap=False)
        self.reset_to_state = reset_to_state

    def _reset(self, tensordict: TensorDictBase | None = None, *, episodes=None, **kwargs):
        if episodes is None:
            return super()._reset(tensordict, **kwargs)
        seeds, starts = episodes
        return start_episodes(self.base_env, seeds, starts, self.reset_to_state)


def _worker_env(make_env: Callable[[], EnvBase], reset_to_state: ResetToState) -> EpisodeStartEnv:
    return EpisodeStartEnv(make_env(), reset_to_state)


def episode_workers(
    make_env: Callable[[], EnvBase], workers: int, reset_to_state: ResetToState
) -> ParallelEnv:
    """A ``ParallelEnv`` of ``workers`` processes, each with ``EpisodeStartEnv(make_env())``.

    ``make_env`` and ``reset_to_state`` are sent to the worker processes, so they must be
    picklable (module-level functions or ``functools.partial`` of them, not lambdas). The
    ``ParallelEnv`` has ``batch_size=[workers, *make_env().batch_size]``; it leaves this
    process's torch threads as they are, and each worker uses one. Close it when done.

    The workers exchange each step's data through pipes (``use_buffers=False``): TorchRL's
    shared-memory buffers make this process spin-wait for the workers, which holds a whole
    core; with as many workers as cores that left the workers one core between them (on 2
    cores, 2 workers of 128 batched MuJoCo envs took 20 s where the pipes take 5.5 s, start-up
    included).
    """
    check_positive_int("workers", workers)
    return ParallelEnv(
        workers,
        partial(_worker_env, make_env, reset_to_state),
        num_threads=torch.get_num_threads(),
        num_sub_threads=1,
        use_buffers=False,
    )


def start_worker_episodes(
    env: ParallelEnv, seeds: Sequence[int], starts: torch.Tensor | TensorDictBase
) -> TensorDictBase:
    """Start one chunk of episodes in :func:`episode_workers`, in one round trip.

    ``seeds`` and ``starts`` ``[n, ...]`` (``n = env.batch_size.numel()``, in the order of the
    flattened batch) go to the workers in blocks: worker ``k`` of ``K`` starts rows
    ``k·m .. (k+1)·m - 1`` (``m = n / K`` envs per worker) with
    :func:`~rcvae_torchrl.agent.start_episodes`. Returns the reset tensordict
    ``env.batch_size``.
    """
    workers, batched = env.batch_size[0], len(env.batch_size) > 1
    m = env.batch_size[1:].numel()
    if len(seeds) != workers * m or len(starts) != workers * m:
        raise ValueError(
            f"seeds, starts: expected {workers * m} of each (one per env), "
            f"got {len(seeds)} and {len(starts)}"
        )
    blocks = starts.unflatten(0, (workers, m))
    kwargs = [
        {"episodes": (list(seeds[k * m : (k + 1) * m]), blocks[k] if batched else blocks[k, 0])}
        for k in range(workers)
    ]
    return env.reset(list_of_kwargs=kwargs)
