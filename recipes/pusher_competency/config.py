"""Typed settings of the Pusher competency study: one source of defaults, checked up front.

The dataclasses below are the schema and the defaults (the default profile). They are
registered as Hydra structured configs (:func:`register_configs`), so every key can be
overridden from the command line without ``+``, and Hydra/OmegaConf reject unknown keys and
values of the wrong type before anything runs; :func:`study_config` then builds the typed
config, whose ``__post_init__`` checks ranges (the library's own configs check theirs). The
profiles under ``conf/profile/`` hold only their differences from these defaults.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from rcvae_torchrl.agent import DistillConfig, PlannerConfig
from rcvae_torchrl.competency.decomposition import check_shuffle_samples
from rcvae_torchrl.envs import CONTROL_TIMESTEP, check_strength
from rcvae_torchrl.loggers import check_logger_backend
from rcvae_torchrl.processes import check_workers
from rcvae_torchrl.training import TrainConfig

from .._settings import (
    at_least,
    build_config,
    check_device_name,
    check_field_types,
    check_profile,
    check_run_dir_name,
    check_seed,
    check_sequences,
    check_threads,
    register_schema,
    whole_steps,
)

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

#: The profiles (``<name>.yaml``: each one's differences from the defaults below).
PROFILES = Path(__file__).parent / "conf" / "profile"

#: The largest study seed: the real episodes' seeds grow with it (the pipeline's REAL_SEEDS,
#: SPREAD_SEEDS, SHARE_SEEDS, HELD_OUT_SEEDS and DYNAMICS_SEEDS + 10·seed + condition, times
#: 100_003 per episode as ``real_outcomes`` takes them) and an env's seed stays below 2**32
MAX_SEED = 3_000


def _at_least(obj: object, names: tuple[str, ...], low: float, kind: type = float) -> None:
    for name in names:
        at_least(name, getattr(obj, name), low, kind)


def _whole_steps(obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        whole_steps(name, getattr(obj, name), CONTROL_TIMESTEP)


@dataclass(frozen=True)
class DataConfig:
    """World-model data per variant: scripted pushing with exploration noise, and random play.

    The stochastic variant's randomness: ``stochastic_strength = [low, high]``, the range of the
    arm's actuator strength drawn once per episode (a fraction of the deterministic arm's;
    ``None``: full strength), and ``stochastic_noise_std``, the std of per-step Gaussian action
    noise. The default, a weak arm of unknown strength (0.2-0.4) with a little per-step noise
    (0.1, a quarter of the weak arm's largest command), spreads the tasks' chances from 0 to 1,
    so a forecast can rank them, while the noise spreads the states from the first steps. The
    ``action_noise`` profile's design, a full-strength arm with noise std 1.5 (a scripted pusher
    then reaches the target within 12 s in about half of the episodes), leaves the tasks'
    chances alike (see the tutorial).
    """

    scripted_episodes: int = 300
    random_episodes: int = 20
    exploration_std: float = 0.3
    time_limit: float = 15.0
    random_time_limit: float = 10.0
    stochastic_noise_std: float = 0.1
    stochastic_strength: list[float] | None = field(default_factory=lambda: [0.2, 0.4])

    def __post_init__(self) -> None:
        _at_least(self, ("scripted_episodes", "random_episodes"), 0, int)
        check_strength("stochastic", self.stochastic_strength, "stochastic_strength")
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
    widens the deterministic ensemble's spread). ``episode_latent_dim``: the size of the
    models' latent drawn once per episode (0: none), for randomness fixed per episode such as
    ``data.stochastic_strength``.
    """

    ensemble_size: int = 5
    hidden_dim: int = 64
    latent_dim: int = 8
    state_constraint: str | None = "pusher"
    input_features: str | None = "pusher"
    stochastic_open_loop_steps: int | None = None
    episode_latent_dim: int = 4

    def __post_init__(self) -> None:
        _at_least(self, ("ensemble_size",), 2, int)
        _at_least(self, ("hidden_dim", "latent_dim"), 1, int)
        _at_least(self, ("episode_latent_dim",), 0, int)
        for name in ("state_constraint", "input_features"):
            if getattr(self, name) not in (None, "pusher"):
                raise ValueError(
                    f"{name}: expected 'pusher' or None (the study's known functions), got "
                    f"{getattr(self, name)!r}"
                )
        if self.stochastic_open_loop_steps is not None:
            _at_least(self, ("stochastic_open_loop_steps",), 0, int)


@dataclass(frozen=True)
class AgentStudyConfig:
    """The agent: MPC episodes in the real env teach an amortised policy (behaviour cloning).

    ``action_noise`` perturbs the executed action (not the recorded label) during the MPC
    episodes, so the policy also learns to recover from states off the planner's path;
    ``dagger_rounds`` rounds of ``dagger_episodes`` policy episodes then relabel the policy's own
    states with the planner. ``demo_envs``: the MPC episodes run this many at a time, side by
    side in a batched env, with one plan of all their states per step (1, the default: one at
    a time). On a GPU, where the plan of one state is bound by kernel launches, that is far
    faster; the episodes differ from the one-at-a-time run's (the planner and the noise draw
    for all of them at once).
    """

    mpc_episodes: int = 15
    demo_envs: int = 1
    action_noise: float = 0.3
    dagger_rounds: int = 1
    dagger_episodes: int = 10
    eval_episodes: int = 20
    distill: DistillConfig = field(default_factory=DistillConfig)

    def __post_init__(self) -> None:
        _at_least(self, ("mpc_episodes", "eval_episodes", "dagger_episodes", "demo_envs"), 1, int)
        _at_least(self, ("dagger_rounds",), 0, int)
        _at_least(self, ("action_noise",), 0.0)


@dataclass(frozen=True)
class AssessConfig:
    """The competency assessment and its ground truth.

    ``start_states``: the scored start states per condition; 100 give each condition's gap
    (forecast minus real) a standard error of at most 0.05 where a start has one real outcome
    (0.5 / √100, whatever the success rate), as the report's forecast check has (with 40 the
    sampling error alone moved a gap by more than 0.05 between start sets).
    ``horizon_s``: the task's deadline and the forecast's horizon; 12 s binds (a training task
    takes a scripted pusher about 4.5 s, an out-of-distribution one about 9 s).
    ``seeds_per_start`` / ``stochastic_seeds_per_start``: real episodes per start state in the
    deterministic envs (whose outcome per start is fixed) and in the stochastic env (30 give a
    per-start success rate a standard error of at most 0.09); ``real_envs`` of them run at a
    time in one batched env, or spread over ``real_workers`` worker processes (a TorchRL
    ``ParallelEnv``, ``real_envs / real_workers`` Pushers each; 1: all in this process), which
    give the same outcomes. ``surface_radii`` (m) x ``surface_deadlines_s``: the grid of
    success boundaries of the competency surface, answered by the same imagined and real
    episodes. ``episode_end``: measure the uncertainty of the episode, which ends at success as
    in the real env (ended samples share a terminal bin). ``bias_correction``: ``"none"`` or
    ``"shuffle"`` (the histogram's epistemic part corrected for its sampling bias, see
    :func:`~rcvae_torchrl.competency.decompose_uncertainty`). ``start_chunk``: start states
    imagined together, each chunk seeded by the study's seed and its index (the unit of work
    shared over ``torchrun`` ranks). ``spread_starts`` start states of each condition (spread
    evenly over the scored ones; 0: none) are run ``samples_per_member`` times more, their
    observations kept, to measure the real episodes' spread in the bits the forecast's
    aleatoric part claims (the report compares them), and as many start states of each world
    model's own env that no score uses, to calibrate the split (``AleatoricShare``).
    ``spread_runs``: ``None`` (the default) or ``samples_per_member``, the only count allowed:
    the plug-in entropy of fewer samples reads lower, so the real spread is measured from as
    many samples as each member's.
    ``check_episodes``: the real episodes, at least, of the report's forecast check of each
    condition (the agent from start states no score uses, one run each in a deterministic env,
    ``stochastic_seeds_per_start`` in the stochastic one): 375 find a bias of 0.10 (the largest
    the study's targets allow a condition's forecast) at the check's level (0.01, two-sided)
    with power 0.9 by the normal approximation (``OutcomeCheck.episodes_to_find(0.10)``: 372;
    simulated 0.875 at a chance of 0.5, 0.96 with chances spread over 0.05-0.95;
    with 100, the out-of-distribution forecasts' bias of six seeds, +0.06 to +0.14, was named
    in one run; with 375, in all six). ``check_samples_per_member``: that check's imagined
    samples per member where its start states are run once each (at most
    ``samples_per_member``): the check judges the forecasts' mean, to which the samples' chance
    then adds at most 0.5 / √(10 · 5 · 375) = 0.004 with 5 members, against the real episodes'
    0.026; each start's forecast is noisier than a scored one's (at most 0.07), which its one
    real outcome cannot tell. Where a start is run several times the check also judges each
    start's forecast against its runs' rate, and the forecasts are made as the scored ones.
    """

    start_states: int = 100
    start_chunk: int = 4
    samples_per_member: int = 50
    horizon_s: float = 12.0
    seeds_per_start: int = 1
    stochastic_seeds_per_start: int = 30
    real_envs: int = 400
    real_workers: int = 1
    success_radius: float = 0.03
    surface_radii: list[float] = field(default_factory=lambda: [0.02, 0.03, 0.05, 0.08])
    surface_deadlines_s: list[float] = field(default_factory=lambda: [4.0, 6.0, 8.0, 10.0, 12.0])
    open_loop: bool = False
    episode_end: bool = True
    bias_correction: str = "shuffle"
    forecast_panels: int = 3
    spread_starts: int = 12
    spread_runs: int | None = None
    check_episodes: int = 375
    check_samples_per_member: int = 10

    def __post_init__(self) -> None:
        check_sequences(self)
        _at_least(
            self,
            (
                "start_states",
                "check_episodes",
                "start_chunk",
                "seeds_per_start",
                "stochastic_seeds_per_start",
                "real_envs",
                "real_workers",
                "forecast_panels",
            ),
            1,
            int,
        )
        _at_least(self, ("spread_starts",), 0, int)
        # a member's aleatoric part is its own spread: from one sample it is 0
        _at_least(self, ("samples_per_member", "check_samples_per_member"), 2, int)
        if self.spread_runs is not None and self.spread_runs != self.samples_per_member:
            raise ValueError(
                f"spread_runs: expected None or samples_per_member={self.samples_per_member} "
                "(the real spread is measured from as many runs per start as each member's "
                f"imagined samples: the plug-in entropy of fewer reads lower), got "
                f"{self.spread_runs!r}"
            )
        _whole_steps(self, ("horizon_s",))
        _at_least(self, ("success_radius",), 0.0)
        if not self.success_radius > 0:
            raise ValueError(f"success_radius: expected > 0 m, got {self.success_radius!r}")
        if not self.surface_radii:
            raise ValueError("surface_radii: expected at least one radius (m), got none")
        for i, radius in enumerate(self.surface_radii):
            at_least(f"surface_radii[{i}]", radius, 1e-9)
        if not self.surface_deadlines_s:
            raise ValueError("surface_deadlines_s: expected at least one deadline (s), got none")
        for i, deadline in enumerate(self.surface_deadlines_s):
            whole_steps(f"surface_deadlines_s[{i}]", deadline, CONTROL_TIMESTEP)
            if deadline > self.horizon_s + 1e-9:
                raise ValueError(
                    f"surface_deadlines_s[{i}]: expected at most horizon_s={self.horizon_s} s, "
                    f"got {deadline!r}"
                )
        if self.bias_correction not in ("none", "shuffle"):
            raise ValueError(
                f"bias_correction: expected 'none' or 'shuffle', got {self.bias_correction!r}"
            )
        check_shuffle_samples(self.bias_correction, self.samples_per_member)


def _study_train() -> TrainConfig:
    return TrainConfig(
        max_steps=10000,
        batch_windows=32,
        window=32,
        lr=3e-3,
        lr_final_fraction=0.05,
        nll_beta=0.5,
        val_every=250,
        patience=6,
        episode_start_fraction=0.25,
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
        check_field_types(self)
        check_seed("seed", self.seed, MAX_SEED)
        longest = max(self.data.time_limit, self.data.random_time_limit)
        if self.train.window > round(longest / CONTROL_TIMESTEP):
            raise ValueError(
                f"train.window: expected at most the longest data episode "
                f"({round(longest / CONTROL_TIMESTEP)} steps of data.time_limit / "
                f"data.random_time_limit), got {self.train.window}"
            )


@dataclass(frozen=True)
class RecipeConfig(StudyConfig):
    """The study plus how to run it: where, on which device, with how many threads.

    ``stage_workers``: processes that run a stage's independent jobs side by side, each on
    ``threads`` threads (the two variants' data, the two world models, the three conditions'
    forecasts, the real outcomes, spreads and split calibrations of the truth stage, the
    report's forecast checks and world-model checks): ``"auto"`` (one per job, up to the cores
    the machine's load leaves idle: 2 on an idle 2-core machine, 1 beside another run; on a GPU
    only the data, which runs on the CPU, while the jobs that use the device run in turn) or a
    count (every stage, on any device). The results are the same either way.

    ``logger``: where training curves and stage summaries go, under ``<run_dir>/logs``:
    ``"csv"``, ``"tensorboard"``, ``"wandb"`` (offline), ``"mlflow"`` (a local file store) or
    ``"none"`` (see :func:`~rcvae_torchrl.loggers.make_logger`).

    ``reuse_from``: a finished (or partly finished) run directory whose stages this run takes,
    hard-linked, where the settings they read are the same (``pipeline.STAGE_SETTINGS``): e.g.
    ``reuse_from=outputs/pusher_competency/default assess.start_states=200`` in a new
    ``run_dir`` keeps that run's data, world models and agent and forecasts anew.
    """

    profile: str = "default"
    run_dir: str = "outputs/pusher_competency/${profile}"
    device: str = "auto"
    threads: Any = "auto"
    stage_workers: Any = "auto"
    progress: bool = True
    logger: str = "csv"
    reuse_from: str | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        check_profile(self.profile, PROFILES)
        check_device_name(self.device)
        check_threads(self.threads)
        check_workers("stage_workers", self.stage_workers)
        check_run_dir_name(self.run_dir)
        check_logger_backend(self.logger)


def register_configs() -> None:
    """Register :class:`RecipeConfig` as the structured config ``pusher_competency_schema``."""
    register_schema("pusher_competency_schema", RecipeConfig)


def study_config(cfg: DictConfig | dict) -> RecipeConfig:
    """The typed config of a composed Hydra config (or a plain mapping of overrides).

    Every section is built and range-checked, then the device and the run directory are
    checked against this machine, before anything is created or written; an error names the
    section and the setting.
    """
    return build_config(RecipeConfig, cfg, PROFILES)
