"""What the study knows about dm_control's point_mass: env variants, the agent, the task.

The env is dm_control's own ``point_mass``/``easy`` through TorchRL's ``DMControlEnv`` (dict
observations ``position`` and ``velocity``, float64), prepared for the library with
:func:`~rcvae_torchrl.data.prepare_env`. Its target sits at the arena's centre, so the task is
reaching the centre: success when the mass is within ``radius`` of it within the deadline.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import DMControlEnv, EnvBase

from rcvae_torchrl.agent import draw_starts
from rcvae_torchrl.competency import SuccessBoundary
from rcvae_torchrl.data import ActionNoise, ObservationLayout, prepare_env

from .config import CONTROL_TIMESTEP, TaskConfig

__all__ = [
    "CONDITIONS",
    "WORLD_MODELS",
    "PDController",
    "boundary",
    "distance",
    "make_env",
    "make_real_env",
    "reward",
    "starts_in_region",
    "success",
]

WORLD_MODELS = ("deterministic", "stochastic")
#: condition -> (world model, real env variant, start region)
CONDITIONS = {
    "deterministic": ("deterministic", "deterministic", "inner"),
    "stochastic": ("stochastic", "stochastic", "inner"),
    "out-of-distribution": ("deterministic", "deterministic", "outer"),
}


def make_env(variant: str, task: TaskConfig) -> tuple[EnvBase, ObservationLayout]:
    """dm_control's point_mass as the library expects it; ``"stochastic"`` adds actuator noise."""
    env, layout = prepare_env(DMControlEnv("point_mass", "easy"))
    if variant == "stochastic":
        env.append_transform(ActionNoise(task.noise_std))
    return env, layout


def make_real_env(variant: str, task: TaskConfig) -> EnvBase:
    """:func:`make_env`'s env alone: a picklable factory of it (``functools.partial``) can
    build it in worker processes."""
    return make_env(variant, task)[0]


def distance(observation: torch.Tensor) -> torch.Tensor:
    """Distance of the mass from the target (the centre): ``[..., 4] -> [...]``."""
    return torch.linalg.vector_norm(observation[..., :2], dim=-1)


def success(observation: torch.Tensor, radius: float = 0.015) -> torch.Tensor:
    return distance(observation) <= radius


def reward(observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    return -distance(observation).unsqueeze(-1)


def boundary(task: TaskConfig) -> SuccessBoundary:
    """Success: within ``radius`` of the target within the deadline."""
    return SuccessBoundary.within_distance(
        distance, task.radius, time_limit_s=task.deadline_s, dt=CONTROL_TIMESTEP
    )


class PDController(nn.Module):
    """The agent: ``a = clip(-kp·position - kd·velocity, -1, 1)``, ``[..., 4] -> [..., 2]``."""

    def __init__(self, kp: float, kd: float) -> None:
        super().__init__()
        self.kp, self.kd = kp, kd

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return (-self.kp * observation[..., :2] - self.kd * observation[..., 2:]).clamp(-1, 1)

    def module(self) -> TensorDictModule:
        return TensorDictModule(self, in_keys=["observation"], out_keys=["action"])


def starts_in_region(
    env: EnvBase, task: TaskConfig, region: str, count: int, first_seed: int
) -> TensorDict:
    """``count`` starts drawn by the env's own seeded reset, kept when in the region:
    ``"inner"`` (both coordinates within ±inner) or ``"outer"`` (one beyond ±outer)."""
    kept, seed, drawn = [], first_seed, 0
    while len(kept) < count:
        if drawn >= _MAX_DRAWS * count:
            setting = "task.inner" if region == "inner" else "task.outer"
            raise ValueError(
                f"{setting}: expected a region the env's reset draws starts in, got "
                f"{getattr(task, region)} m: {len(kept)} of {drawn} seeded starts lay in it, "
                f"{count} were needed; widen it"
            )
        batch = draw_starts(env, range(seed, seed + 4 * count))
        reach = batch["observation"][:, :2].abs().amax(-1)
        inside = reach <= task.inner if region == "inner" else reach >= task.outer
        kept.extend(batch[i] for i in inside.nonzero().flatten().tolist())
        seed += 4 * count
        drawn += 4 * count
    return torch.stack(kept[:count])


#: draws per start needed at most before a region is said to hold too few of the env's starts
_MAX_DRAWS = 400
