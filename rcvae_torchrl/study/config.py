"""Typed configuration of the Pusher competency study, built from plain mappings (Hydra's YAML).

Unknown keys are errors that name the key and the keys allowed there, so a typo in a config file
or an override never passes silently.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar, get_type_hints

from rcvae_torchrl.agent import DistillConfig, PlannerConfig
from rcvae_torchrl.training import TrainConfig

__all__ = [
    "AgentStudyConfig",
    "AssessConfig",
    "DataConfig",
    "ModelConfig",
    "StudyConfig",
    "from_mapping",
]

T = TypeVar("T")


@dataclass(frozen=True)
class DataConfig:
    """World-model data per variant: scripted pushing with exploration noise, and random play."""

    scripted_episodes: int = 100
    random_episodes: int = 20
    exploration_std: float = 0.3
    time_limit: float = 15.0
    random_time_limit: float = 10.0
    stochastic_noise_std: float = 0.5


@dataclass(frozen=True)
class ModelConfig:
    """The RCVAE ensemble."""

    ensemble_size: int = 5
    hidden_dim: int = 64
    latent_dim: int = 8


@dataclass(frozen=True)
class AgentStudyConfig:
    """The agent: MPC episodes in the real env teach an amortised policy (behaviour cloning).

    ``action_noise`` perturbs the executed action (not the recorded label) during the MPC
    episodes, so the policy also learns to recover from states off the planner's path.
    """

    mpc_episodes: int = 10
    action_noise: float = 0.3
    eval_episodes: int = 20
    distill: DistillConfig = field(default_factory=DistillConfig)


@dataclass(frozen=True)
class AssessConfig:
    """The competency assessment and its ground truth."""

    start_states: int = 20
    samples_per_member: int = 20
    horizon_s: float = 30.0
    seeds_per_start: int = 1
    stochastic_seeds_per_start: int = 5
    success_radius: float = 0.03
    open_loop: bool = False
    forecast_panels: int = 3


@dataclass(frozen=True)
class StudyConfig:
    """Everything the study needs, with the default profile's budgets."""

    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(
        default_factory=lambda: TrainConfig(max_steps=1500, batch_windows=32, window=32)
    )
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    agent: AgentStudyConfig = field(default_factory=AgentStudyConfig)
    assess: AssessConfig = field(default_factory=AssessConfig)
    seed: int = 0


def from_mapping(cls: type[T], values: Mapping[str, Any] | None, where: str = "config") -> T:
    """Build dataclass ``cls`` from a nested mapping; unknown keys raise ``ValueError``."""
    values = dict(values or {})
    names = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; expected some of {sorted(names)}")
    hints = get_type_hints(cls)
    kwargs = {}
    for name, value in values.items():
        kind = hints[name]
        if dataclasses.is_dataclass(kind) and isinstance(value, Mapping):
            kwargs[name] = from_mapping(kind, value, f"{where}.{name}")
        else:
            kwargs[name] = value
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{where}: {err}") from err
