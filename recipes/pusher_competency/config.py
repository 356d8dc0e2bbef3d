"""Typed settings of the Pusher competency study: one source of defaults, checked up front.

The dataclasses below are the schema and the defaults (the default profile). They are
registered as Hydra structured configs (:func:`register_configs`), so every key can be
overridden from the command line without ``+``, and Hydra/OmegaConf reject unknown keys and
values of the wrong type before anything runs; :func:`study_config` then builds the typed
config, whose ``__post_init__`` checks ranges (the library's own configs check theirs). The
profiles under ``conf/profile/`` hold only their differences from these defaults.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from typing import Any

from omegaconf import DictConfig, OmegaConf

from rcvae_torchrl.agent import DistillConfig, PlannerConfig
from rcvae_torchrl.envs import CONTROL_TIMESTEP
from rcvae_torchrl.training import TrainConfig

__all__ = [
    "AgentStudyConfig",
    "AssessConfig",
    "DataConfig",
    "ModelConfig",
    "RecipeConfig",
    "StudyConfig",
    "register_configs",
    "study_config",
]


def _at_least(obj: object, names: tuple[str, ...], low: float) -> None:
    for name in names:
        value = getattr(obj, name)
        if (
            not isinstance(value, (int, float))
            or isinstance(value, bool)
            or not math.isfinite(value)
            or value < low
        ):
            raise ValueError(f"{name}: expected a finite number >= {low}, got {value!r}")


def _whole_steps(obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(obj, name)
        steps = value / CONTROL_TIMESTEP if isinstance(value, (int, float)) else -1
        if not (math.isfinite(steps) and steps >= 1 and abs(steps - round(steps)) < 1e-6):
            raise ValueError(
                f"{name}: expected a positive whole number of {CONTROL_TIMESTEP} s control "
                f"steps, got {value!r}"
            )


@dataclass(frozen=True)
class DataConfig:
    """World-model data per variant: scripted pushing with exploration noise, and random play.

    ``stochastic_noise_std``: the std of the stochastic variant's action noise (with 1.5 a
    scripted pusher reaches the target within 12 s in about half of the episodes, and the
    chance varies from task to task).
    """

    scripted_episodes: int = 300
    random_episodes: int = 20
    exploration_std: float = 0.3
    time_limit: float = 15.0
    random_time_limit: float = 10.0
    stochastic_noise_std: float = 1.5

    def __post_init__(self) -> None:
        _at_least(self, ("scripted_episodes", "random_episodes"), 0)
        if self.scripted_episodes + self.random_episodes < 1:
            raise ValueError("scripted_episodes, random_episodes: expected at least one episode")
        _at_least(self, ("exploration_std", "stochastic_noise_std"), 0.0)
        _whole_steps(self, ("time_limit", "random_time_limit"))


@dataclass(frozen=True)
class ModelConfig:
    """The RCVAE ensemble.

    ``state_constraint`` / ``input_features`` name the Pusher's known functions (``"pusher"``:
    unit-circle angles, forward kinematics and the ball in the arena; the fingertip-ball contact
    geometry), or ``None``. ``stochastic_open_loop_steps``, when not None, replaces
    ``train.open_loop_steps`` for the stochastic variant's ensemble only (open-loop training
    widens the deterministic ensemble's spread).
    """

    ensemble_size: int = 5
    hidden_dim: int = 64
    latent_dim: int = 8
    state_constraint: str | None = "pusher"
    input_features: str | None = "pusher"
    stochastic_open_loop_steps: int | None = None

    def __post_init__(self) -> None:
        _at_least(self, ("ensemble_size",), 2)
        _at_least(self, ("hidden_dim", "latent_dim"), 1)
        for name in ("state_constraint", "input_features"):
            if getattr(self, name) not in (None, "pusher"):
                raise ValueError(
                    f"{name}: expected 'pusher' or None (the study's known functions), got "
                    f"{getattr(self, name)!r}"
                )
        if self.stochastic_open_loop_steps is not None:
            _at_least(self, ("stochastic_open_loop_steps",), 0)


@dataclass(frozen=True)
class AgentStudyConfig:
    """The agent: MPC episodes in the real env teach an amortised policy (behaviour cloning).

    ``action_noise`` perturbs the executed action (not the recorded label) during the MPC
    episodes, so the policy also learns to recover from states off the planner's path;
    ``dagger_rounds`` rounds of ``dagger_episodes`` policy episodes then relabel the policy's own
    states with the planner.
    """

    mpc_episodes: int = 15
    action_noise: float = 0.3
    dagger_rounds: int = 1
    dagger_episodes: int = 10
    eval_episodes: int = 20
    distill: DistillConfig = field(default_factory=DistillConfig)

    def __post_init__(self) -> None:
        _at_least(self, ("mpc_episodes", "eval_episodes", "dagger_episodes"), 1)
        _at_least(self, ("dagger_rounds",), 0)
        _at_least(self, ("action_noise",), 0.0)


@dataclass(frozen=True)
class AssessConfig:
    """The competency assessment and its ground truth.

    ``horizon_s``: the task's deadline and the forecast's horizon; 12 s binds (a training task
    takes a scripted pusher about 4.5 s, an out-of-distribution one about 9 s).
    ``seeds_per_start`` / ``stochastic_seeds_per_start``: real episodes per start state in the
    deterministic envs (whose outcome per start is fixed) and in the stochastic env (30 give a
    per-start success rate a standard error of at most 0.09); ``real_envs`` of them run at a
    time in one batched env. ``surface_radii`` (m) x ``surface_deadlines_s``: the grid of
    success boundaries of the competency surface, answered by the same imagined and real
    episodes. ``episode_end``: measure the uncertainty of the episode, which ends at success as
    in the real env (ended samples share a terminal bin). ``bias_correction``: ``"none"`` or
    ``"shuffle"`` (the histogram's epistemic part corrected for its sampling bias, see
    :func:`~rcvae_torchrl.competency.decompose_uncertainty`). ``start_chunk``: start states
    imagined together, each chunk seeded by the study's seed and its index (the unit of work
    shared over ``torchrun`` ranks).
    """

    start_states: int = 40
    start_chunk: int = 10
    samples_per_member: int = 50
    horizon_s: float = 12.0
    seeds_per_start: int = 1
    stochastic_seeds_per_start: int = 30
    real_envs: int = 400
    success_radius: float = 0.03
    surface_radii: list[float] = field(default_factory=lambda: [0.02, 0.03, 0.05, 0.08])
    surface_deadlines_s: list[float] = field(default_factory=lambda: [4.0, 6.0, 8.0, 10.0, 12.0])
    open_loop: bool = False
    episode_end: bool = True
    bias_correction: str = "shuffle"
    forecast_panels: int = 3

    def __post_init__(self) -> None:
        _at_least(
            self,
            (
                "start_states",
                "start_chunk",
                "samples_per_member",
                "seeds_per_start",
                "stochastic_seeds_per_start",
                "real_envs",
                "forecast_panels",
            ),
            1,
        )
        _whole_steps(self, ("horizon_s",))
        _at_least(self, ("success_radius",), 0.0)
        if not self.success_radius > 0:
            raise ValueError(f"success_radius: expected > 0 m, got {self.success_radius!r}")
        if not self.surface_radii or not all(
            isinstance(r, (int, float)) and math.isfinite(r) and r > 0 for r in self.surface_radii
        ):
            raise ValueError(
                f"surface_radii: expected positive radii in m, got {list(self.surface_radii)!r}"
            )
        deadlines = list(self.surface_deadlines_s)
        steps = [d / CONTROL_TIMESTEP if isinstance(d, (int, float)) else -1 for d in deadlines]
        if (
            not deadlines
            or not all(
                math.isfinite(n) and 1 <= round(n) and abs(n - round(n)) < 1e-6 for n in steps
            )
            or max(deadlines) > self.horizon_s + 1e-9
        ):
            raise ValueError(
                f"surface_deadlines_s: expected whole numbers of {CONTROL_TIMESTEP} s control "
                f"steps up to horizon_s={self.horizon_s}, got {deadlines!r}"
            )
        if self.bias_correction not in ("none", "shuffle"):
            raise ValueError(
                f"bias_correction: expected 'none' or 'shuffle', got {self.bias_correction!r}"
            )


def _study_train() -> TrainConfig:
    return TrainConfig(
        max_steps=5000,
        batch_windows=32,
        window=32,
        lr=3e-3,
        lr_final_fraction=0.05,
        nll_beta=0.5,
        val_every=250,
        patience=6,
    )


@dataclass(frozen=True)
class StudyConfig:
    """Everything the study computes with (the default profile's budgets)."""

    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=_study_train)
    planner: PlannerConfig = field(default_factory=lambda: PlannerConfig(policy_prior=True))
    agent: AgentStudyConfig = field(default_factory=AgentStudyConfig)
    assess: AssessConfig = field(default_factory=AssessConfig)
    seed: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed: expected an integer >= 0, got {self.seed!r}")
        longest = max(self.data.time_limit, self.data.random_time_limit)
        if self.train.window > round(longest / CONTROL_TIMESTEP):
            raise ValueError(
                f"train.window: expected at most the longest data episode "
                f"({round(longest / CONTROL_TIMESTEP)} steps of data.time_limit / "
                f"data.random_time_limit), got {self.train.window}"
            )


@dataclass(frozen=True)
class RecipeConfig(StudyConfig):
    """The study plus how to run it: where, on which device, with how many threads."""

    profile: str = "default"
    run_dir: str = "outputs/pusher_competency/${profile}"
    device: str = "auto"
    threads: int | None = None
    progress: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        if not re.fullmatch(r"auto|cpu|cuda(:\d+)?", str(self.device)):
            raise ValueError(
                f"device: expected 'auto', 'cpu', 'cuda' or 'cuda:N', got {self.device!r}"
            )
        if self.threads is not None and (
            isinstance(self.threads, bool) or not isinstance(self.threads, int) or self.threads < 1
        ):
            raise ValueError(f"threads: expected a positive integer or null, got {self.threads!r}")
        if not str(self.run_dir).strip():
            raise ValueError(f"run_dir: expected a directory path, got {self.run_dir!r}")


def _writable(node: Any) -> None:
    """Clear the read-only flag frozen dataclasses give their nodes, so overrides apply."""
    OmegaConf.set_readonly(node, None)
    for key in node:
        child = node._get_node(key)
        if isinstance(child, DictConfig):
            _writable(child)


def register_configs() -> None:
    """Register :class:`RecipeConfig` as the structured config ``pusher_competency_schema``."""
    from hydra.core.config_store import ConfigStore

    node = OmegaConf.structured(RecipeConfig)
    _writable(node)
    ConfigStore.instance().store(name="pusher_competency_schema", node=node)


def study_config(cfg: DictConfig | dict) -> RecipeConfig:
    """The typed config of a composed Hydra config (or a plain mapping of overrides).

    Every section is built and range-checked before anything is created or written; an error
    names the section and the setting.
    """
    schema = OmegaConf.structured(RecipeConfig)
    _writable(schema)
    merged = OmegaConf.merge(schema, cfg)
    sections = {}
    for f in dataclasses.fields(RecipeConfig):
        node = merged[f.name]
        if isinstance(node, DictConfig):
            try:
                sections[f.name] = OmegaConf.to_object(node)
            except (ValueError, TypeError) as err:
                raise ValueError(f"{f.name}.{err}") from None
        else:
            sections[f.name] = node
    return RecipeConfig(**sections)
