"""The Pusher competency study, stage by stage.

1. ``data``: world-model data in the deterministic and the stochastic Pusher.
2. ``models``: an RCVAE ensemble trained on each.
3. ``agent``: MPC episodes with the deterministic model teach the agent's amortised policy.
4. ``forecast``: the paper's three conditions, forecast in imagination with the agent's policy
   (:class:`~rcvae_torchrl.competency.CompetencyAssessor`).
5. ``truth``: the same agent in the real env from the same start states.
6. ``report``: the paper's table plus calibration, the figures, a GIF and ``report.md``, with
   the world models' checks as far ahead as the forecast and the forecasts checked from start
   states not scored (against the agent's real episodes from them), with the scored forecasts
   through the Platt map fitted on those episodes beside them, and each condition's env
   checked to move as its world model learned (the agent's one-step errors there against its
   errors in the model's own env).

Every stage writes its outputs atomically under the run directory and a marker when done
(:class:`~rcvae_torchrl.stages.StageRunner`); running again with the same directory reuses
finished stages (and training resumes from its last checkpoint).
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger

from rcvae_torchrl import distributed
from rcvae_torchrl import envs as pusher_domain
from rcvae_torchrl.agent import (
    EpisodeStats,
    FixedRowsPolicy,
    PerturbedPolicy,
    RealOutcomes,
    dagger,
    load_policy,
    make_policy_module,
    real_outcomes,
    run_episodes,
    save_policy,
)
from rcvae_torchrl.competency import AleatoricShare, CompetencyAssessor, fit_platt
from rcvae_torchrl.data import (
    episode_spans,
    load_episodes,
    save_episodes,
    seed_env,
    split_episodes,
)
from rcvae_torchrl.envs import (
    CONTROL_TIMESTEP,
    OBSERVATION_NAMES,
    ball_to_target,
    make_batched_pusher_env,
    pusher_reward,
    reset_to_state,
    resolution_tensor,
)
from rcvae_torchrl.envs.scripted import ScriptedPusher
from rcvae_torchrl.io import CHECKSUM_KEY, load_torch, read_json, save_torch
from rcvae_torchrl.model_env import make_rcvae_env
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.processes import choose_workers, map_in_processes, worker_pool
from rcvae_torchrl.stages import StageRunner, code_digest, library_digest
from rcvae_torchrl.training import (
    DynamicsCheck,
    DynamicsNovelty,
    ModelChecks,
    OutcomeCheck,
    TrainConfig,
    check_dynamics,
    check_model,
    load_ensemble,
    log_history,
    save_ensemble,
    train_ensemble,
)

from .._settings import CHECKPOINTS, REPORT_FILES, resolve_device
from . import pusher as pusher_module
from .config import StudyConfig, study_config
from .data import collect_pusher_data, replay_episodes
from .pusher import (
    CONDITIONS,
    MODEL_FUNCTIONS,
    WORLD_MODELS,
    make_env,
    make_planner,
    rcvae_config,
    success_boundary,
    success_fn,
    variant_randomness,
)
from .report import write_report

__all__ = [
    "FAR_FRACTIONS",
    "SHARDED_STAGES",
    "STAGES",
    "STAGE_SETTINGS",
    "Study",
    "run_study",
    "study_of_run",
    "training_op_flop",
]

#: The far coverage check's horizons, as fractions of the forecast's: a world model that passes
#: 1 s ahead can be overconfident while the ball is pushed, seconds later.
FAR_FRACTIONS = (0.25, 0.5, 1.0)
#: The far check's level over all its horizons (the self-check's own level).
_FAR_ALPHA = 0.01
#: Seeds of the far check's replays: ``_REPLAY_SEED + 1000 * seed`` (env ``i``: + i).
_REPLAY_SEED = 90_000
#: The conditions whose env is the one their world model's data came from (not out of
#: distribution): their held-out episodes' first states start the forecast check (topped up, as
#: the other conditions' starts are drawn, by their env's reset with HELD_OUT_START_SEEDS), and
#: their recorded actions can be replayed (benchmarks/held_out_checks.py).
CHECKED_CONDITIONS = tuple(c for c, (model, variant) in CONDITIONS.items() if model == variant)

# Each stage and the files it writes (their sizes and hashes go into its marker); the report's
# named one by one (see REPORT_FILES).
REPORT_FILES = (
    *REPORT_FILES,
    "start_reliability.png",
    "surface.png",
    "forecast_vs_reality.png",
    "episode.gif",
)
STAGES = {
    "data": ("data/*.pt",),
    "models": ("models/*.pt",),
    "agent": ("agent/*.pt",),
    "forecast": ("forecast/*.pt",),
    "truth": ("truth/*.pt",),
    "report": REPORT_FILES,
}
# Stages that share their work over torch.distributed ranks (the others run on rank 0).
SHARDED_STAGES = ("data", "models", "forecast", "truth", "report")
#: The settings each stage reads (sections, or one key of a section); the later stages read
#: them all. Another run's finished stage is reused (``reuse_from``) when these and every
#: earlier stage's files are the same: a run that changes only how forecasts are made or
#: scored keeps the data, the world models and the agent. The agent acts within the horizon and
#: success radius of the assessment (its episodes' length, its planner's goal).
STAGE_SETTINGS = {
    "data": ("seed", "data"),
    "models": ("seed", "data", "model", "train"),
    "agent": (
        "seed",
        "data",
        "model",
        "train",
        "planner",
        "agent",
        "assess.horizon_s",
        "assess.success_radius",
    ),
}


def stage_code() -> dict[str, str]:
    """The code every stage runs whose change the settings do not show, per stage (the
    ``stage_code`` of :class:`~rcvae_torchrl.stages.StageRunner`): the Pusher domain's sources
    (its dynamics and MJCF model, the scripted pusher, the known functions the world models
    read), this study's use of them (``pusher.py``) and the simulator's versions. Every stage
    depends on them: the data and real outcomes through the real env, the models, agent and
    forecasts through the known functions. A run resumed after they changed runs its stages
    again."""
    digest = code_digest(
        [Path(pusher_domain.__file__).parent, Path(pusher_module.__file__)],
        packages=("mujoco", "dm_control"),
    )
    return dict.fromkeys(STAGES, digest)


# Disjoint seed ranges of the real episodes, per purpose (offset by 1000 per study seed).
DEMONSTRATION_SEEDS = 50_000
EVALUATION_SEEDS = 70_000
DAGGER_SEEDS = 80_000
# Real episodes of the truth stage: seeds REAL_SEEDS + 10·seed + c, each run its own stream;
# those from held-out episodes' first states (the report's forecast check): HELD_OUT_SEEDS + ...
REAL_SEEDS = 9_000
# The real episodes whose spread is measured: SPREAD_SEEDS + 10·seed + c; those from held-out
# start states that calibrate the split: SHARE_SEEDS + 10·seed + c.
SPREAD_SEEDS = 9_500
SHARE_SEEDS = 9_700
HELD_OUT_SEEDS = 8_000
# The dynamics check's real episodes (Study.dynamics_check): episode i of condition c seeded
# (DYNAMICS_SEEDS + 10·seed + c)·100_003 + i, as real_outcomes seeds its runs; those it ranks
# them against (Study.dynamics_reference), of the world model of condition c's own env:
# DYNAMICS_REFERENCE_SEEDS + ..., from start states drawn with seeds DYNAMICS_START_SEEDS higher
# than the scored ones' (mod 2**32).
DYNAMICS_SEEDS = 8_500
DYNAMICS_REFERENCE_SEEDS = 8_600
DYNAMICS_START_SEEDS = 2**30
# Start states that top up the dynamics check's (Study.dynamics_check) where the forecast
# check's are fewer: seeds this much higher than the scored ones' (mod 2**32), past the
# reference's DYNAMICS_REFERENCE.
DYNAMICS_TOP_UP_SEEDS = 2**30 + 500
# Start states of condition c are drawn with seeds seed·START_SEED_STRIDE + 1000·c + i (those
# whose state begins a data episode passed over: Study.starts); those the forecast check draws
# (Study.held_out_starts), HELD_OUT_START_SEEDS higher (mod 2**32).
START_SEED_STRIDE = 7919
HELD_OUT_START_SEEDS = 2**31
#: The real episodes' policy calls are made on blocks of this many rows (FixedRowsPolicy), so
#: an episode comes out the same whatever the batched env's size, the workers or the ranks.
POLICY_ROWS = 64
#: The dynamics check's real episodes per condition (:meth:`Study.dynamics_check`): one per
#: start state of the forecast check where it has as many.
DYNAMICS_EPISODES = 40
#: The agent's episodes in a world model's own env that its dynamics checks rank against
#: (:meth:`Study.dynamics_reference`).
DYNAMICS_REFERENCE = 60


def training_op_flop(config: StudyConfig) -> float:
    """FLOP of the study's typical op: one GRU gate matmul of a training step, all members."""
    m, t = config.model, config.train
    return 2.0 * m.ensemble_size * t.batch_windows * m.hidden_dim * 3 * m.hidden_dim


class Study:
    """The stages of one study in one run directory (see the module docstring)."""

    def __init__(
        self,
        config: StudyConfig,
        run_dir: Path,
        device: torch.device,
        progress: bool,
        logger: Logger | None = None,
        *,
        workers: int | str = 1,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.cfg, self.dir, self.device, self.progress = config, run_dir, device, progress
        self.logger = logger
        # "auto" resolved now, at the start of the run: the load is then the other jobs', not
        # this run's own workers of a stage before (the load average lags by a minute)
        self.workers = choose_workers(len(CONDITIONS), workers)
        # jobs on an accelerator (models, forecasts): side by side there only when a count
        # asks for it ("auto" cannot tell whether processes sharing one GPU pay); jobs on the
        # host (the data) take self.workers on any device
        self.device_workers = self.workers if device.type == "cpu" or workers != "auto" else 1
        self.say = log or (lambda line: None)
        self._dynamics_references: dict[str, DynamicsNovelty] = {}
        self._first_states: torch.Tensor | None = None  # the data's (Study._data_first_states)

    # ------------------------------------------------------------------ helpers
    @property
    def max_steps(self) -> int:
        return round(self.cfg.assess.horizon_s / CONTROL_TIMESTEP)

    def env(self, variant: str, **kwargs: Any) -> EnvBase:
        """The real Pusher of ``variant`` with the study's randomness and success radius."""
        return make_env(variant, self.cfg.data, self.cfg.assess.success_radius, **kwargs)

    def batched_env(
        self, variant: str, num_envs: int, *, terminate_on_success: bool = False
    ) -> Callable[[], EnvBase]:
        """A function that makes ``num_envs`` real Pushers of ``variant`` in one batched env,
        episodes of the horizon's length that go on after success unless
        ``terminate_on_success`` (picklable, so worker processes can build it)."""
        d, s = self.cfg.data, self.cfg.assess
        return functools.partial(
            make_batched_pusher_env,
            num_envs,
            variant,
            success_radius=s.success_radius,
            time_limit=s.horizon_s,
            terminate_on_success=terminate_on_success,
            **variant_randomness(variant, d),
        )

    def load_model(self, name: str) -> RCVAEEnsemble:
        """The trained world model ``name`` (``"deterministic"`` or ``"stochastic"``)."""
        return load_ensemble(
            self.dir / "models" / f"{name}.pt", map_location=self.device, functions=MODEL_FUNCTIONS
        )

    def load_policy(self) -> torch.nn.Module:
        """The agent: the distilled MLP, or the scripted prior plus the distilled correction."""
        base = ScriptedPusher() if self.cfg.planner.policy_prior else None
        return load_policy(self.dir / "agent" / "policy.pt", base=base)

    def planner(self, model: RCVAEEnsemble, env: EnvBase) -> Callable:
        """The MPC planner over ``model`` acting in ``env`` (guided by the scripted pusher)."""
        return make_planner(
            model, env, self.cfg.planner, radius=self.cfg.assess.success_radius, seed=self.cfg.seed
        )

    def starts(self, condition: str, count: int | None = None, offset: int = 0) -> torch.Tensor:
        """The condition's start states ``[B, 14]``, drawn by the real env's own reset:
        ``assess.start_states`` of them (the scored ones), or ``count`` with seeds ``offset``
        higher. A draw that is the first state of a world-model data episode (of either
        variant, training or held-out) is passed over for the next seed: the data's collection
        seeds the same env with small seeds, and a scored task must be none the models learned
        from or the split was calibrated on."""
        env = self.env(CONDITIONS[condition][1])
        index = list(CONDITIONS).index(condition)
        seen = self._data_first_states()
        wanted = self.cfg.assess.start_states if count is None else count
        starts, i = [], 0
        while len(starts) < wanted:
            seed_env(env, (offset + self.cfg.seed * START_SEED_STRIDE + 1000 * index + i) % 2**32)
            i += 1
            state = env.reset()["observation"]
            if not (state.to(seen.dtype) == seen).all(-1).any():
                starts.append(state)
        return torch.stack(starts)

    def _data_first_states(self) -> torch.Tensor:
        """The first states ``[N, 14]`` of every world-model data episode (both variants)."""
        if self._first_states is None:
            firsts = []
            for variant in WORLD_MODELS:
                data = load_episodes(self.dir / "data" / f"{variant}.pt")
                firsts.append(data.get("observation")[episode_spans(data)[0]])
            self._first_states = torch.cat(firsts)
        return self._first_states

    def held_out_starts(self, condition: str) -> torch.Tensor:
        """Start states of ``condition`` that are not scored: the first states of its world
        model's held-out episodes where the condition's env is the one the model's data came
        from, then, up to ``assess.check_episodes`` real episodes (with
        :meth:`runs_per_start` each), start states drawn by the condition's env's reset with
        seeds no scored start uses."""
        model_name, variant = CONDITIONS[condition]
        starts = torch.empty(0, 14)
        if model_name == variant:
            _, held_out = self.episodes(model_name)
            starts = held_out.get("observation")[episode_spans(held_out)[0]]
        check = self.cfg.assess.check_episodes
        missing = -(-check // self.runs_per_start(variant)) - len(starts)
        if missing <= 0:
            return starts
        drawn = self.starts(condition, missing, offset=HELD_OUT_START_SEEDS)
        return torch.cat([starts.to(drawn.dtype), drawn])

    def runs_per_start(self, variant: str) -> int:
        """Real episodes per start state in the Pusher of ``variant``:
        ``assess.seeds_per_start`` where it is deterministic (1 by default: more would repeat
        it), ``assess.stochastic_seeds_per_start`` in the stochastic one."""
        s = self.cfg.assess
        return s.stochastic_seeds_per_start if variant == "stochastic" else s.seeds_per_start

    # ------------------------------------------------------------------ stages
    def data(self) -> dict[str, Any]:
        if distributed.is_active():  # the two variants side by side on parts of the ranks
            self.over_ranks("data", WORLD_MODELS, "collect", shared=False)
        else:
            self.side_by_side("data", WORLD_MODELS, "collect", host=True)  # the real env alone
        return {
            f"{variant}_frames": int(load_episodes(self.dir / "data" / f"{variant}.pt").shape[0])
            for variant in WORLD_MODELS
        }

    def collect(self, variant: str) -> None:
        """Collect and save the world-model data of Pusher ``variant``."""
        d = self.cfg.data
        data = collect_pusher_data(
            variant,
            scripted_episodes=d.scripted_episodes,
            random_episodes=d.random_episodes,
            exploration_std=d.exploration_std,
            time_limit=d.time_limit,
            random_time_limit=d.random_time_limit,
            seed=self.cfg.seed,
            progress=self.progress,
            **variant_randomness(variant, d),
        )
        save_episodes(data, self.dir / "data" / f"{variant}.pt")

    def side_by_side(
        self, stage: str, names: Sequence[str], method: str, *, host: bool = False
    ) -> tuple[dict[str, Any], bool]:
        """``self.<method>(name)`` for each of ``names`` whose ``<stage>/<name>.pt`` is missing:
        independent jobs, run side by side in up to ``self.workers`` worker processes (jobs
        that run on the ``host`` alone) or ``self.device_workers`` (jobs on the study's
        device), else here one after the other (one worker, or ranks sharing each job's work).
        Returns each job's result by name, and whether they ran in workers (where this study's
        logger could not go)."""
        pending = self._missing(stage, names)
        done = [f"{stage}/{n}.pt" for n in names if n not in pending]
        if done:  # the stage runs again for its other files: say what it keeps
            self.say(f"[{stage}] {', '.join(done)} written earlier: taken as they are")
        most = self.workers if host else self.device_workers
        workers = 1 if distributed.is_active() else max(1, min(most, len(pending)))
        if workers == 1:
            return {name: getattr(self, method)(name) for name in pending}, False
        self.say(f"[{stage}] {', '.join(pending)} in {workers} worker processes")
        jobs = [(self.cfg, str(self.dir), str(self.device), method, name) for name in pending]
        return dict(zip(pending, map_in_processes(_study_job, jobs, workers))), True

    def _missing(self, stage: str, names: Sequence[str]) -> list[str]:
        """The jobs of ``names`` whose ``<stage>/<name>.pt`` is not written yet."""
        return [n for n in names if not (self.dir / stage / f"{n}.pt").is_file()]

    def over_ranks(
        self, stage: str, names: Sequence[str], method: str, *, shared: bool = True
    ) -> tuple[dict[str, Any], list[str]]:
        """Under torch.distributed, in a sharded stage (every rank calls it):
        ``self.<method>(name)`` for each of ``names`` whose ``<stage>/<name>.pt`` is missing,
        the jobs side by side on parts of the ranks (:func:`~rcvae_torchrl.distributed.parts`;
        part p runs jobs p, p + n, ... of ``names``, so a job resumed after a kill runs on the
        ranks it ran on before), each part's ranks sharing its jobs' work (``shared``) or its
        first rank running them alone (jobs that share nothing out). Returns each job's result
        by name (from its part's first rank, on every rank) and the jobs that ran without this
        run's rank 0 (and its logger)."""
        names = list(names)
        # rank 0's view of what is missing: every rank runs the same jobs
        missing = distributed.broadcast(self._missing(stage, names))
        n = max(1, min(len(names), distributed.world_size()))
        mine: dict[str, Any] = {}
        with distributed.parts(n) as part:
            if n > 1:
                self.say(f"[{stage}] {', '.join(missing)} side by side on {n} parts of the ranks")
            leader = distributed.is_main()
            for name in names[part.index :: part.parts] if shared or leader else ():
                if name in missing:
                    mine[name] = getattr(self, method)(name)
        results = {}
        for theirs in distributed.all_gather(mine if leader else {}):
            results.update(theirs)
        elsewhere = [name for i, name in enumerate(names) if i % n and name in missing]
        return results, elsewhere

    def _train_config(self, name: str) -> TrainConfig:
        """The training settings of world model ``name``, seeded by the study's seed."""
        train = dataclasses.replace(self.cfg.train, seed=self.cfg.train.seed + self.cfg.seed)
        steps = self.cfg.model.stochastic_open_loop_steps
        if name != "stochastic" or steps is None:
            return train
        return dataclasses.replace(train, open_loop_steps=steps)

    def models(self) -> dict[str, Any]:
        if distributed.is_active() and self.cfg.train.data_parallel == 1:
            histories, elsewhere = self.over_ranks("models", WORLD_MODELS, "train_world_model")
        else:  # one process (worker processes), or ranks sharing each member's windows
            histories, workers = self.side_by_side("models", WORLD_MODELS, "train_world_model")
            elsewhere = list(histories) if workers else []
        for name in elsewhere:  # training curves made without this run's logger, into it
            log_history(self.logger, histories[name], prefix=f"models/{name}/")
        distributed.barrier()
        summary = {}
        for name in WORLD_MODELS:
            saved = load_torch(self.dir / "models" / f"{name}.pt", "model checkpoint")
            summary[name] = saved["extra"].get("training", {})
        return summary

    def episodes(self, name: str) -> tuple[Any, Any]:
        """World model ``name``'s training and held-out episodes (90 % / 10 %, by episode)."""
        data = load_episodes(self.dir / "data" / f"{name}.pt")
        return split_episodes(data, 0.1, seed=self.cfg.seed)

    def train_world_model(self, name: str) -> list[dict[str, Any]]:
        """Train world model ``name`` (resuming its checkpoint) and save it; its history."""
        m = self.cfg.model
        torch.manual_seed(self.cfg.seed)
        ensemble = RCVAEEnsemble(rcvae_config(m), m.ensemble_size, functions=MODEL_FUNCTIONS)
        ensemble = ensemble.to(self.device)
        train, val = self.episodes(name)
        result = train_ensemble(
            ensemble,
            train,
            val,
            self._train_config(name),
            checkpoint_path=self.dir / "models" / CHECKPOINTS / f"{name}.pt",
            resume=True,
            logger=self.logger,
            log_prefix=f"models/{name}/",
            progress=self.progress,
        )
        info = {
            "steps": result.steps,
            "stopped_early": result.stopped_early,
            "best_val_loss": result.best_val.mean().item(),
        }
        if distributed.is_main():
            path = self.dir / "models" / f"{name}.pt"
            save_ensemble(result.ensemble, path, extra={"variant": name, "training": info})
        return result.history

    def _demonstrations(self, model: RCVAEEnsemble, env: EnvBase) -> dict[str, Any]:
        """MPC episodes with the executed action perturbed: observations and planner labels
        (``agent.demo_envs`` of them side by side in a batched env)."""
        a, seed = self.cfg.agent, self.cfg.seed
        behaviour = PerturbedPolicy(self.planner(model, env), a.action_noise, seed=seed)
        if a.demo_envs > 1:
            side_by_side = min(a.demo_envs, a.mpc_episodes)
            env = self.batched_env("deterministic", side_by_side, terminate_on_success=True)()
        stats = run_episodes(
            env,
            behaviour,
            seeds=[DEMONSTRATION_SEEDS + seed * 1000 + i for i in range(a.mpc_episodes)],
            max_steps=self.max_steps,
            progress=self.progress,
            desc="MPC demos",
        )
        info = {
            "mpc_noisy_success_rate": stats.success_rate,
            "mpc_median_steps": stats.steps.float().median().item(),
            "pairs": float(stats.data.shape[0]),
        }
        return {
            "observations": stats.data["observation"],
            "labels": stats.data["label"],
            "info": info,
        }

    def agent(self) -> dict[str, Any]:
        a, seed = self.cfg.agent, self.cfg.seed
        env = self.env("deterministic", time_limit=self.cfg.assess.horizon_s)
        model = self.load_model("deterministic")  # the planner's device; the Pusher's is the CPU
        demos_path = self.dir / "agent" / "demonstrations.pt"
        if not demos_path.is_file():
            save_torch(demos_path, self._demonstrations(model, env))
        demos = load_torch(demos_path, "demonstrations")
        policy, obs, labels, rounds = dagger(
            self.planner(model, env),
            env,
            demos["observations"],
            demos["labels"],
            a.distill,
            rounds=a.dagger_rounds,
            episode_seeds=lambda k: [
                DAGGER_SEEDS + seed * 1000 + 100 * k + i for i in range(a.dagger_episodes)
            ],
            max_steps=self.max_steps,
            base=ScriptedPusher() if self.cfg.planner.policy_prior else None,
            progress=self.progress,
        )
        save_torch(self.dir / "agent" / "dagger_data.pt", {"observations": obs, "labels": labels})
        evaluation = run_episodes(
            env,
            make_policy_module(policy),
            seeds=[EVALUATION_SEEDS + seed * 1000 + i for i in range(a.eval_episodes)],
            max_steps=self.max_steps,
            progress=self.progress,
            desc="policy eval",
        )
        save_policy(policy, self.dir / "agent" / "policy.pt")
        return {
            **demos["info"],
            **{k: v for k, v in rounds[-1].items() if k != "round"},
            "dagger": rounds,
            "policy_success_rate": evaluation.success_rate,
            "policy_median_steps": evaluation.steps.float().median().item(),
        }

    def assessor(
        self, model_name: str, variant: str, samples_per_member: int | None = None
    ) -> CompetencyAssessor:
        """The competency assessor of a condition: the agent's closed-loop forecast, with
        ``assess.samples_per_member`` imagined samples per member (or ``samples_per_member``,
        as many trajectories per chunk of start states: more starts per chunk)."""
        s = self.cfg.assess
        samples = s.samples_per_member if samples_per_member is None else samples_per_member
        chunk = max(1, s.start_chunk * s.samples_per_member // samples)
        model_env = make_rcvae_env(
            self.load_model(model_name),
            self.env(variant),
            pusher_reward,
            success_fn(s.success_radius),
            terminate_on_success=True,
            seed=self.cfg.seed,
        )
        return CompetencyAssessor(
            model_env,
            success_boundary(s.success_radius, s.horizon_s),
            bin_width=resolution_tensor(),
            dim_names=OBSERVATION_NAMES,
            samples_per_member=samples,
            start_chunk=chunk,
            episode_end=s.episode_end,
            bias_correction=s.bias_correction,
            per_sample={"ball_to_target": ball_to_target},
        )

    def forecast(self) -> dict[str, Any]:
        """Sharded: chunks of start states over the ranks (each chunk seeded by the study's
        seed and its index), one report gathered; rank 0 writes it. In one process the
        conditions are forecast side by side where cores are idle, each in as many parts as
        there are workers (:meth:`forecast_parts`), the parts' rows then put together: the
        same forecast."""
        if distributed.is_active():
            for condition in CONDITIONS:
                if not distributed.broadcast((self.dir / "forecast" / f"{condition}.pt").is_file()):
                    self.forecast_condition(condition)
                distributed.barrier()
        else:
            parts = self.forecast_parts()
            self.side_by_side("forecast", list(parts), "forecast_part")
            for condition in CONDITIONS:
                own = [n for n, (c, *_) in parts.items() if c == condition and n != condition]
                self._join_forecast(condition, own)
        summary = {}
        for condition in CONDITIONS:
            saved = load_torch(self.dir / "forecast" / f"{condition}.pt", "forecast")
            summary[condition] = {"p_success": saved["p_success"].mean().item()}
        return summary

    def forecast_parts(self) -> dict[str, tuple[str, int, int]]:
        """The forecast's jobs in one process, by the name of the file each writes in
        ``forecast/``: per condition not forecast yet, its whole forecast (``<condition>``),
        or, where the stage has more than one worker, as many parts of consecutive chunks of
        start states (``<condition>.chunks<first>-<end>``; closed-loop forecasts only: an
        open-loop plan is drawn for all start states at once), each as (condition, first
        chunk, end chunk). A part's chunks draw as they do in the whole
        (``CompetencyAssessor.assess(first_chunk=...)``), so its rows are the whole's; equal
        parts keep the workers busy until the stage ends."""
        s = self.cfg.assess
        chunks = -(-s.start_states // s.start_chunk)  # the assessor's chunks of start states
        count = 1 if s.open_loop else max(1, min(self.device_workers, chunks))
        parts = {}
        for condition in self._missing("forecast", list(CONDITIONS)):
            if count == 1:
                parts[condition] = (condition, 0, chunks)
                continue
            for i in range(count):
                first, end = i * chunks // count, (i + 1) * chunks // count
                parts[f"{condition}.chunks{first}-{end}"] = (condition, first, end)
        return parts

    def forecast_part(self, name: str) -> None:
        """Forecast the part ``name`` of a condition (:meth:`forecast_parts`: the job's name
        says which chunks of start states it holds) and save it."""
        condition, dot, chunks = name.partition(".chunks")
        if not dot:
            self.forecast_condition(condition)
            return
        first, end = (int(k) for k in chunks.split("-"))
        self.forecast_condition(condition, (first, end), name)

    def _join_forecast(self, condition: str, parts: Sequence[str]) -> None:
        """Put a condition's forecast parts (their names, in order) together into its
        forecast, row after row; then remove every part file of the condition (those of a
        run stopped with another split too)."""
        folder = self.dir / "forecast"
        whole = folder / f"{condition}.pt"
        if parts and not whole.is_file():
            loaded = [load_torch(folder / f"{name}.pt", "forecast part") for name in parts]
            keys = [k for k in loaded[0] if k != CHECKSUM_KEY]  # each part's own digest
            save_torch(whole, {k: torch.cat([part[k] for part in loaded]) for k in keys})
        for path in folder.glob(f"{condition}.chunks*.pt"):
            path.unlink()

    def forecast_condition(
        self, condition: str, chunks: tuple[int, int] | None = None, name: str | None = None
    ) -> None:
        """Forecast the agent from ``condition``'s start states in imagination; save it (as
        ``forecast/<name>.pt``, by default the condition's). ``chunks``: only the start states
        of chunks ``first`` to ``end`` (exclusive) of the assessor's, each drawing as in the
        whole forecast."""
        s = self.cfg.assess
        model_name, variant = CONDITIONS[condition]
        policy = self.load_policy().to(self.device)
        starts = self.starts(condition)
        assessor = self.assessor(model_name, variant)
        first = 0
        if chunks is not None:
            first, end = chunks
            starts = starts[first * assessor.start_chunk : end * assessor.start_chunk]
        start = starts.to(self.device)
        if s.open_loop:
            generator = torch.Generator(device=self.device).manual_seed(self.cfg.seed)
            plan = assessor.model_env.plan_actions(
                start, policy, assessor.horizon, generator=generator
            )
            report = assessor.assess(start, actions=plan, seed=self.cfg.seed)
        else:
            report = assessor.assess(start, policy=policy, seed=self.cfg.seed, first_chunk=first)
        if distributed.is_main():
            path = self.dir / "forecast" / f"{name or condition}.pt"
            record = _forecast_record(report.data.cpu())
            if report.novel is not None:  # a model trained with its novelty check
                record.update(novelty_start=report.data["novelty", "start"].cpu())
                record.update(novel=report.novel.cpu())
            save_torch(path, {"starts": starts, **record})

    def truth(self) -> dict[str, Any]:
        """The agent in the real env from each forecast's start states, many runs per start in
        a batched env (or spread over ``assess.real_workers`` worker processes); episodes go
        on after success, so every boundary of the competency surface is answered by the
        same episodes. In one process its jobs (:meth:`truth_jobs`) run side by side where
        cores are idle, the longest first. Sharded: the real episodes over the ranks; rank 0
        writes the outcomes."""
        if not distributed.is_active():
            self.side_by_side("truth", list(self.truth_jobs()), "truth_job")
        summary = {}
        policy = make_policy_module(self.load_policy())
        for index, condition in enumerate(CONDITIONS):
            self.real_truth(condition, index, policy)
            saved = load_torch(self.dir / "truth" / f"{condition}.pt", "real outcomes")
            summary[condition] = {"success_rate": saved["success"].float().mean().item()}
            if self.cfg.assess.spread_starts:
                summary[condition]["spread"] = self.real_spread(condition, index, policy)
                if condition in CHECKED_CONDITIONS:
                    summary[condition]["share"] = self.aleatoric_share(condition, index, policy)
        return summary

    def truth_jobs(self) -> dict[str, tuple[str, str]]:
        """The truth stage's independent jobs, by the name of the file each writes in
        ``truth/``: per condition its real outcomes (``<condition>``,
        :meth:`real_truth`), and with ``assess.spread_starts`` its real spread
        (``<condition>_spread``, :meth:`real_spread`) and, where the condition is its world
        model's own env, the split's calibration (``<condition>_share``,
        :meth:`aleatoric_share`); each as (method, condition), the most real episodes first
        (worker processes that take them in turn then end them about together)."""
        s = self.cfg.assess
        jobs, episodes = {}, {}
        for condition, (_, variant) in CONDITIONS.items():
            jobs[condition] = ("real_truth", condition)
            episodes[condition] = s.start_states * self.runs_per_start(variant)
            if not s.spread_starts:
                continue
            kept = s.spread_starts * s.samples_per_member
            jobs[f"{condition}_spread"] = ("real_spread", condition)
            episodes[f"{condition}_spread"] = kept
            if condition in CHECKED_CONDITIONS:
                jobs[f"{condition}_share"] = ("aleatoric_share", condition)
                episodes[f"{condition}_share"] = kept + 1  # and a forecast: before a spread
        return {name: jobs[name] for name in sorted(jobs, key=episodes.get, reverse=True)}

    def truth_job(self, name: str) -> None:
        """Run the truth stage's job ``name`` (one of :meth:`truth_jobs`); it saves its file."""
        method, condition = self.truth_jobs()[name]
        index = list(CONDITIONS).index(condition)
        getattr(self, method)(condition, index, make_policy_module(self.load_policy()))

    def real_truth(self, condition: str, index: int, policy: Callable) -> None:
        """The agent's real episodes from ``condition``'s scored start states (those of its
        forecast), as many per start as :meth:`runs_per_start`, with the ball's distance to
        the target traced; saved (where not saved yet)."""
        path = self.dir / "truth" / f"{condition}.pt"
        if not distributed.broadcast(path.is_file()):
            starts = load_torch(self.dir / "forecast" / f"{condition}.pt", "forecast")["starts"]
            result = self.real_runs(
                CONDITIONS[condition][1],
                policy,
                starts,
                seed=REAL_SEEDS + self.cfg.seed * 10 + index,
                desc=f"real: {condition}",
                trace=ball_to_target,
            )
            if distributed.is_main():
                save_torch(path, result.as_dict())
        distributed.barrier()

    def aleatoric_share(self, condition: str, index: int, policy: Callable) -> dict[str, Any]:
        """The share of ``condition``'s world model's aleatoric bits that the agent's real
        episodes show (:class:`~rcvae_torchrl.competency.AleatoricShare`), fitted on
        ``assess.spread_starts`` of its held-out start states (none of them scored),
        ``assess.samples_per_member`` real episodes each (as many as each member's imagined
        samples); saved, and its shares and real bits returned."""
        path = self.dir / "truth" / f"{condition}_share.pt"
        if not distributed.broadcast(path.is_file()):
            s = self.cfg.assess
            model_name, variant = CONDITIONS[condition]
            held_out = self.held_out_starts(condition)
            starts = held_out[_evenly(len(held_out), s.spread_starts)]
            assessor = self.assessor(model_name, variant)
            report = assessor.assess(
                starts.to(self.device),
                policy=self.load_policy().to(self.device),
                seed=self.cfg.seed,
            )
            outcomes = self.kept_runs(
                variant,
                policy,
                starts,
                seed=SHARE_SEEDS + self.cfg.seed * 10 + index,
                desc=f"real spread, held-out starts: {condition}",
            )
            share = AleatoricShare.fit(report, assessor.real_spread(outcomes))
            if distributed.is_main():
                save_torch(path, share.as_dict())
            distributed.barrier()
        share = AleatoricShare.from_dict(load_torch(path, "aleatoric share"))
        return {"share": share.share.tolist(), "real": float(share.real.sum())}

    def real_spread(self, condition: str, index: int, policy: Callable) -> dict[str, float]:
        """The spread of the agent's real episodes from ``assess.spread_starts`` of the
        condition's start states (evenly spread over them), ``assess.samples_per_member`` each, in
        the bits of the forecast (:meth:`~rcvae_torchrl.competency.CompetencyAssessor
        .real_spread`), saved with the forecast's aleatoric bits of the same start states."""
        path = self.dir / "truth" / f"{condition}_spread.pt"
        if not distributed.broadcast(path.is_file()):
            s = self.cfg.assess
            model_name, variant = CONDITIONS[condition]
            forecast = load_torch(self.dir / "forecast" / f"{condition}.pt", "forecast")
            starts = forecast["starts"]
            picked = _evenly(len(starts), s.spread_starts)
            outcomes = self.kept_runs(
                variant,
                policy,
                starts[picked],
                seed=SPREAD_SEEDS + self.cfg.seed * 10 + index,
                desc=f"real spread: {condition}",
            )
            spread = self.assessor(model_name, variant).real_spread(outcomes).bits
            if distributed.is_main():
                save_torch(path, _spread_record(spread, forecast, picked))
            distributed.barrier()
        saved = load_torch(path, "real spread")
        return {k: float(saved[k].mean()) for k in ("real", "imagined")}

    def kept_runs(
        self, variant: str, policy: Callable, starts: torch.Tensor, *, seed: int, desc: str
    ) -> RealOutcomes:
        """The real episodes whose spread is measured: ``assess.samples_per_member`` from each
        of ``starts`` (as many as each member's imagined samples), their observations kept."""
        with warnings.catch_warnings():
            # in a deterministic Pusher the runs repeat one episode: the 0 bits measured
            warnings.filterwarnings("ignore", "runs_per_start: each of the", UserWarning)
            return self.real_runs(
                variant,
                policy,
                starts,
                seed=seed,
                desc=desc,
                runs=self.cfg.assess.samples_per_member,
                keep_observations=True,
            )

    def real_runs(
        self,
        variant: str,
        policy: Callable,
        starts: torch.Tensor,
        *,
        seed: int,
        desc: str,
        runs: int | None = None,
        **kw,
    ) -> RealOutcomes:
        """The agent (``policy``, a policy module) in the real Pusher of ``variant`` from each
        of ``starts``: ``runs`` times, by default once per start in a deterministic env and
        ``assess.stochastic_seeds_per_start`` times in the stochastic one, in batched envs over
        ``assess.real_workers`` workers; ``kw`` goes to
        :func:`~rcvae_torchrl.agent.real_outcomes`."""
        s = self.cfg.assess
        runs = self.runs_per_start(variant) if runs is None else runs
        per_worker = -(-min(s.real_envs, len(starts) * runs) // s.real_workers)
        return real_outcomes(
            self.batched_env(variant, per_worker),
            policy,
            starts,
            runs_per_start=runs,
            workers=s.real_workers,
            policy_rows=POLICY_ROWS,
            reset_to_state=reset_to_state,
            max_steps=self.max_steps,
            seed=seed,
            progress=self.progress,
            desc=desc,
            **kw,
        )

    def report(self) -> dict[str, Any]:
        # the forecast checks' forecasts and real episodes, the conditions side by side (the
        # report writes no per-condition file, so all of them run), and in one process the
        # world models' checks beside them; under torchrun every rank takes its share of each
        # condition's start states and real episodes, and rank 0 checks the world models
        by_model = {}
        if distributed.is_active():
            held_out, _ = self.side_by_side("report", list(CONDITIONS), "held_out_outcomes")
        else:
            done, _ = self.side_by_side("report", list(self.report_jobs()), "report_job")
            held_out = {c: done[c] for c in CONDITIONS}
            by_model = {m: done[f"{m} {_CHECKS_JOB}"] for m in WORLD_MODELS}
        if not distributed.is_main():
            return {}  # rank 0 writes the report
        forecasts = {
            c: load_torch(self.dir / "forecast" / f"{c}.pt", "forecast") for c in CONDITIONS
        }
        truths = {
            c: load_torch(self.dir / "truth" / f"{c}.pt", "real outcomes") for c in CONDITIONS
        }
        spread_paths = {c: self.dir / "truth" / f"{c}_spread.pt" for c in CONDITIONS}
        spreads = {
            c: load_torch(path, "real spread") for c, path in spread_paths.items() if path.is_file()
        }
        share_paths = {c: self.dir / "truth" / f"{c}_share.pt" for c in CHECKED_CONDITIONS}
        shares = {
            c: AleatoricShare.from_dict(load_torch(path, "aleatoric share"))
            for c, path in share_paths.items()
            if path.is_file()
        }
        fitted = {CONDITIONS[c][0]: share for c, share in shares.items()}  # by world model
        episode_env = self.env("deterministic", time_limit=self.cfg.assess.horizon_s)
        policy = make_policy_module(self.load_policy())
        models = {name: self.load_model(name) for name in WORLD_MODELS}
        checks = {name: model.checks for name, model in models.items()}
        for name, model in models.items():
            if name not in by_model:  # under torchrun: here, on rank 0
                by_model[name] = self.world_model_checks(name, model)
        far = {name: by_model[name][0] for name in WORLD_MODELS}
        dynamics = {c: by_model[model][1][c] for c, (model, _) in CONDITIONS.items()}
        return write_report(
            self.dir,
            forecasts,
            truths,
            self.cfg,
            policy,
            episode_env,
            model_checks=checks,
            far_checks=far,
            forecast_checks={c: self.forecast_check(c, held_out[c]) for c in held_out},
            dynamics_checks=dynamics,
            held_out_maps={c: fit_platt(*held_out[c]) for c in held_out},
            real_spreads=spreads,
            split_shares={c: fitted[m] for c, (m, _) in CONDITIONS.items() if m in fitted},
        )

    def report_jobs(self) -> dict[str, tuple[str, str]]:
        """The report stage's independent jobs (in one process), by name: per condition the
        forecast check's forecasts and real episodes (``<condition>``,
        :meth:`held_out_outcomes`), the longest first; then per world model its far
        self-checks and the dynamics checks of the conditions it forecasts
        (``<world model> model's checks``, :meth:`world_model_checks`). Each as (method,
        argument)."""
        jobs = {c: ("held_out_outcomes", c) for c in CONDITIONS}
        jobs.update({f"{m} {_CHECKS_JOB}": ("world_model_checks", m) for m in WORLD_MODELS})
        return jobs

    def report_job(self, name: str) -> Any:
        """The result of the report stage's job ``name`` (one of :meth:`report_jobs`)."""
        method, argument = self.report_jobs()[name]
        return getattr(self, method)(argument)

    def world_model_checks(
        self, name: str, model: RCVAEEnsemble | None = None
    ) -> tuple[list[ModelChecks], dict[str, DynamicsCheck]]:
        """World model ``name``'s far self-checks (:meth:`far_checks`) and the dynamics
        checks (:meth:`dynamics_check`) of the conditions it forecasts, by condition.
        ``model``: the world model where it is loaded already."""
        model = self.load_model(name) if model is None else model
        far = self.far_checks(name, model)
        own = [c for c, (m, _) in CONDITIONS.items() if m == name]
        return far, {c: self.dynamics_check(c, model) for c in own}

    def forecast_check(
        self, condition: str, outcomes: tuple[torch.Tensor, torch.Tensor] | None = None
    ) -> OutcomeCheck:
        """The agent's forecasts in ``condition`` from start states it is not scored on
        against its real episodes from them (:meth:`held_out_outcomes`, or ``outcomes``
        made by it)."""
        forecast, success = self.held_out_outcomes(condition) if outcomes is None else outcomes
        return OutcomeCheck.from_outcomes(
            forecast,
            success,
            what=f"the {condition} forecasts from start states they are not scored on",
        )

    def held_out_outcomes(self, condition: str) -> tuple[torch.Tensor, torch.Tensor]:
        """The agent's forecasts ``[n]`` in ``condition`` from start states it is not scored
        on (:meth:`held_out_starts`), and the outcomes ``[n, R]`` of its real episodes from
        each (as many per start as the truth stage runs). Where each start is run once, the
        forecasts are made with ``assess.check_samples_per_member`` samples per member (or
        the study's, where fewer)."""
        model_name, variant = CONDITIONS[condition]
        starts = self.held_out_starts(condition)
        s = self.cfg.assess
        samples = None
        if self.runs_per_start(variant) == 1:
            samples = min(s.check_samples_per_member, s.samples_per_member)
        report = self.assessor(model_name, variant, samples).assess(
            starts.to(self.device), policy=self.load_policy().to(self.device), seed=self.cfg.seed
        )
        real = self.real_runs(
            variant,
            make_policy_module(self.load_policy()),  # the real Pusher runs on the CPU
            starts,
            seed=HELD_OUT_SEEDS + self.cfg.seed * 10 + list(CONDITIONS).index(condition),
            desc=f"held-out starts: {condition}",
        )
        return report.data["competency", "p_success"].cpu(), real.success

    def dynamics_check(self, condition: str, model: RCVAEEnsemble | None = None) -> DynamicsCheck:
        """Does ``condition``'s real env move as its world model learned? The agent run
        :data:`DYNAMICS_EPISODES` times from the forecast check's start states
        (:meth:`held_out_starts`, spread evenly over them; where they are fewer, topped up
        with start states drawn by the condition's env's reset with seeds no other start uses:
        in a deterministic env a start run twice repeats its episode, which the rank tests
        would count twice), episodes of the horizon's length; their one-step errors over the
        horizon (or as much of it as the training episodes cover) ranked against those of the
        agent's own episodes in the world model's env (:meth:`dynamics_reference`;
        :func:`~rcvae_torchrl.training.check_dynamics`), their size and which way they lean
        (``shift=True``). ``model``: the condition's world model where it is loaded already."""
        model_name = CONDITIONS[condition][0]
        starts = self.held_out_starts(condition)
        count = DYNAMICS_EPISODES
        if count <= len(starts):
            starts = starts[_evenly(len(starts), count)]
        else:
            more = self.starts(condition, count - len(starts), offset=DYNAMICS_TOP_UP_SEEDS)
            starts = torch.cat([starts.to(more.dtype), more])
        index = list(CONDITIONS).index(condition)
        episodes = self.agent_episodes(condition, starts, DYNAMICS_SEEDS + index).data
        model = self.load_model(model_name) if model is None else model
        reference = self.dynamics_reference(model_name, model)
        # the agent's own episodes on both sides: a shift of its errors is the env's
        return check_dynamics(model, episodes, novelty=reference, shift=True)

    def dynamics_reference(self, model_name: str, model: RCVAEEnsemble) -> DynamicsNovelty:
        """What the dynamics checks of world model ``model_name`` (``model``) rank against:
        its one-step errors on :data:`DYNAMICS_REFERENCE` episodes of the agent in the
        model's own env, from start states drawn by its reset with seeds no other start
        uses, over the horizon's transitions, or as many as its longest training episodes
        have (in units of its errors on its training episodes). The agent's episodes, not
        the model's held-out ones: a policy other than the one that collected the training
        data visits other states, where the model can predict otherwise although the env is
        the same; against the agent's own episodes only the env, or the start states, can
        tell the two apart."""
        found = self._dynamics_references.get(model_name)
        if found is None:
            index = list(CONDITIONS).index(model_name)  # the model's own env's condition
            starts = self.starts(model_name, DYNAMICS_REFERENCE, offset=DYNAMICS_START_SEEDS)
            block = DYNAMICS_REFERENCE_SEEDS + index
            episodes = self.agent_episodes(model_name, starts, block).data
            train, _ = self.episodes(model_name)
            # the horizon's transitions, or as many as the longest training episodes have
            steps = min(self.max_steps, int(episode_spans(train)[1].max()))
            found = DynamicsNovelty.fit(model, train, episodes, steps=steps)
            self._dynamics_references[model_name] = found
        return found

    def agent_episodes(self, condition: str, starts: torch.Tensor, block: int) -> EpisodeStats:
        """The agent's real episodes in ``condition``'s env, one from each of ``starts``,
        the horizon's length: their outcomes and their flat frames with the actions (on the
        study's device); episode ``i`` seeded ``(block + 10·seed)·100_003 + i``, as
        :meth:`real_runs` seeds."""
        first = (block + self.cfg.seed * 10) * 100_003
        stats = run_episodes(
            self.batched_env(CONDITIONS[condition][1], len(starts))(),
            FixedRowsPolicy(make_policy_module(self.load_policy()), POLICY_ROWS),
            seeds=[first + i for i in range(len(starts))],
            starts=starts,
            reset_to_state=reset_to_state,
            max_steps=self.max_steps,
            progress=self.progress,
            desc=f"agent episodes: {condition}",
        )
        return dataclasses.replace(stats, data=stats.data.to(self.device))

    def far_checks(self, name: str, model: RCVAEEnsemble) -> list[ModelChecks]:
        """World model ``name``'s (``model``'s) self-checks with their coverage at
        :data:`FAR_FRACTIONS` of the forecast's horizon, against replays of its held-out
        episodes' actions in the real env (new noise); none when no held-out episode is that
        long. The coverage test's level is shared out over the horizons (Bonferroni, as the
        check shares it over dimensions)."""
        steps = [max(1, round(f * self.max_steps)) for f in FAR_FRACTIONS]
        _, held_out = self.episodes(name)
        if int(episode_spans(held_out)[1].max()) <= max(steps):
            return []
        truth = replay_episodes(
            held_out,
            max(steps) + 1,
            name,
            seed=_REPLAY_SEED + 1000 * self.cfg.seed,
            **variant_randomness(name, self.cfg.data),
        )
        alpha = _FAR_ALPHA / len(steps)
        return [
            check_model(model, truth, coverage_steps=k, alpha=alpha, seed=self.cfg.seed, warn=False)
            for k in steps
        ]


#: The name of a world model's checks among the report stage's jobs (Study.report_jobs).
_CHECKS_JOB = "model's checks"


def _evenly(count: int, most: int) -> torch.Tensor:
    """Up to ``most`` indices spread evenly over ``range(count)``, first and last included."""
    return torch.linspace(0, count - 1, min(most, count)).round().long().unique()


def _spread_record(spread, forecast: dict, picked: torch.Tensor) -> dict[str, torch.Tensor]:
    """The real spread of start states ``picked`` (of the forecast's) as stored: per start
    ``[n]`` (and per dimension ``[n, D]``), the real bits and the forecast's aleatoric bits,
    per live step where the episodes end (else as time means)."""
    aleatoric = forecast["aleatoric"][picked]  # [n, T, D]
    real = spread["total"]
    if "live" in spread.keys():
        imagined_steps = forecast["live"][picked].sum(-1, keepdim=True)
        real_steps = spread["live"].sum(-1, keepdim=True)
    else:
        imagined_steps = real_steps = torch.full((len(picked), 1), float(real.shape[1]))
    by_dim = {
        "real_by_dim": real.sum(1) / real_steps,
        "imagined_by_dim": aleatoric.sum(1) / imagined_steps,
    }
    return {
        "index": picked,
        "real": by_dim["real_by_dim"].sum(-1),
        "imagined": by_dim["imagined_by_dim"].sum(-1),
        **by_dim,
        "per_live_step": torch.tensor("live" in spread.keys()),
    }


def _forecast_record(data) -> dict[str, torch.Tensor]:
    """The forecast of a condition as stored: the report's entries the later stages read."""
    u, c = data["uncertainty"], data["competency"]
    # with episode_end: the share of imagined episodes still running [B, T]
    live = {"live": u["live"]} if "live" in u.keys() else {}
    return {
        **live,
        "total": u["total"],
        "aleatoric": u["aleatoric"],
        "epistemic": u["epistemic"],
        "p_success": c["p_success"],
        "p_success_low": c["p_success_low"],
        "p_success_high": c["p_success_high"],
        "p_success_member": c["p_success_member"],
        "outcome_total": c["outcome_uncertainty", "total"],
        "outcome_aleatoric": c["outcome_uncertainty", "aleatoric"],
        "outcome_epistemic": c["outcome_uncertainty", "epistemic"],
        "success": c["success"],
        "median_time_s": c["time_to_success", "median_s"],
        "ball_to_target": data["per_sample", "ball_to_target"].flatten(1, 2),
    }


def run_study(
    config: StudyConfig,
    run_dir: str | Path,
    *,
    device: str | torch.device = "cpu",
    progress: bool = True,
    log: Callable[[str], None] = print,
    logger: Logger | None = None,
    stage_workers: int | str = 1,
    reuse_from: str | Path | None = None,
) -> dict[str, Any]:
    """Run (or resume) the study in ``run_dir``; returns every stage's summary.

    ``logger`` (a TorchRL logger) gets the training curves (``models/<name>/...``) and every
    stage's numbers (``stages/<stage>/...``); without one, training writes CSV beside its
    checkpoints. ``stage_workers``: processes that run a stage's independent jobs side by
    side (the two variants' data, the two world models, the three conditions' forecasts, the
    truth stage's real episodes, the report's checks): an int, or ``"auto"``: as many as idle
    cores allow (see :func:`~rcvae_torchrl.processes.choose_workers`), kept from stage to stage
    (:func:`~rcvae_torchrl.processes.worker_pool`: each pays its imports once). The results
    are the same either way. A worker's training curves reach ``logger`` when it finishes (and
    CSV beside its checkpoint as it trains). ``reuse_from``: another run directory whose
    finished stages are taken (hard-linked) where the settings they read
    (:data:`STAGE_SETTINGS`) and the files before them are this run's.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    runner = StageRunner(
        run_dir,
        log,
        settings=study_settings(config),
        logger=logger,
        stage_settings=STAGE_SETTINGS,
        reuse_from=reuse_from,
        stage_code=stage_code(),
        library_code=library_digest(),
    )
    study = Study(
        config,
        run_dir,
        torch.device(device),
        progress and distributed.is_main(),
        logger,
        workers=stage_workers,
        log=log,
    )
    with worker_pool(1 if distributed.is_active() else study.workers):
        for name, outputs in STAGES.items():
            runner.run(name, getattr(study, name), outputs, sharded=name in SHARDED_STAGES)
    return runner.summaries


def study_of_run(
    run_dir: str | Path,
    device: str | torch.device = "cpu",
    *,
    changes: Mapping[str, Mapping[str, Any]] | None = None,
    settings_from: str | Path | None = None,
) -> Study:
    """The study of the run in ``run_dir`` with the settings it recorded
    (``study_config.json``; or those of the run in ``settings_from``), each section's keys
    in ``changes`` replaced (e.g. ``{"agent": {"demo_envs": 8}}``): for scripts that measure
    or extend a finished run. No progress bars, one worker."""
    run_dir = Path(run_dir)
    saved = read_json(Path(settings_from or run_dir) / "study_config.json", "run config")
    for section, values in (changes or {}).items():  # unknown names: study_config names them
        saved[section] = {**saved.get(section, {}), **values}
    config = study_config({**saved, "run_dir": str(run_dir)})
    if not isinstance(device, torch.device):  # a name: present on this machine, or refused
        device = resolve_device(device)
    return Study(config, run_dir, torch.device(device), progress=False)


def _study_job(config: StudyConfig, run_dir: str, device: str, method: str, name: str) -> Any:
    """``Study.<method>(name)`` of the study in ``run_dir``, in a worker process (no progress
    bars, no logger: training writes CSV beside its checkpoint)."""
    study = Study(config, Path(run_dir), torch.device(device), progress=False)
    return getattr(study, method)(name)


def study_settings(config: StudyConfig) -> dict[str, Any]:
    """The settings a run directory records (``study_config.json``) and reuses results under."""
    return {f.name: v for f, v in zip(dataclasses.fields(StudyConfig), _values(config))}


def _values(config: StudyConfig) -> list[Any]:
    """The study settings of ``config`` (a recipe config's run settings are left out)."""
    values = asdict(config)
    return [values[f.name] for f in dataclasses.fields(StudyConfig)]
