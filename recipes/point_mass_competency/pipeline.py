"""The point-mass study, stage by stage, on the library's public API.

1. ``data``: PD episodes with exploration noise from training starts, in the deterministic and
   the stochastic env.
2. ``models``: an RCVAE ensemble trained on each (with the model's self-checks).
3. ``forecast``: the agent's success and uncertainty in three conditions, imagined by the
   :class:`~rcvae_torchrl.competency.CompetencyAssessor`.
4. ``truth``: the same agent in the real env from the same start states, several runs each.
5. ``check``: each condition's outcome check (:class:`~rcvae_torchrl.training.OutcomeCheck`):
   the agent forecast and run in the real env from other start states of the condition's
   region, none of them scored, as a user checks a forecast before reading it.
6. ``report``: forecast against reality per condition, each report with its outcome check
   attached (the verdict, and whether the report is to be trusted), the uncertainty pattern and
   the plain-language summaries (against the deterministic condition as the in-distribution
   reference), ``report.md`` and ``summary.json``.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torchrl.record.loggers import Logger

from rcvae_torchrl.agent import (
    RealOutcomes,
    real_outcomes,
    reset_by_seed,
    run_episodes,
    score_forecast,
)
from rcvae_torchrl.competency import CompetencyAssessor, CompetencyReport
from rcvae_torchrl.data import (
    GaussianExploration,
    load_episodes,
    make_policy_module,
    merge_episodes,
    save_episodes,
    split_episodes,
)
from rcvae_torchrl.io import load_torch, read_json, save_torch, write_json
from rcvae_torchrl.model_env import make_rcvae_env
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.stages import StageRunner, code_digest, library_digest
from rcvae_torchrl.training import (
    DynamicsCheck,
    OutcomeCheck,
    check_dynamics,
    load_ensemble,
    save_ensemble,
    train_ensemble,
)

from .._settings import CHECKPOINTS, REPORT_FILES
from . import task as task_module
from .config import CONTROL_TIMESTEP, StudyConfig
from .report import write_report
from .task import (
    CONDITIONS,
    WORLD_MODELS,
    PDController,
    boundary,
    distance,
    make_env,
    make_real_env,
    reward,
    starts_in_region,
    success,
)

__all__ = ["STAGES", "STAGE_SETTINGS", "Study", "run_study"]

# Each stage and the files it writes (their sizes and hashes go into its marker).
STAGES = {
    "data": ("data/*.pt",),
    "models": ("models/*.pt",),
    "forecast": ("forecast/*.pt",),
    "truth": ("truth/*.pt",),
    "check": ("check/*.json",),
    "report": REPORT_FILES,  # named one by one (see REPORT_FILES)
}


def stage_code() -> dict[str, str]:
    """The code every stage runs whose change the settings do not show, per stage (the
    ``stage_code`` of :class:`~rcvae_torchrl.stages.StageRunner`): this study's task
    (``task.py``: the env, its observation layout, the agent and the success predicate) and
    the versions of dm_control (whose ``point_mass`` is the env) and MuJoCo. A run resumed
    after they changed runs its stages again."""
    digest = code_digest([Path(task_module.__file__)], packages=("mujoco", "dm_control"))
    return dict.fromkeys(STAGES, digest)


#: The settings each stage reads (the later stages read them all): another run's finished data
#: and models are reused (``reuse_from``) when these and the earlier stages' files are the same.
#: The data read the task's agent, training region, success radius and noise, not its deadline
#: or its out-of-distribution region, which only the forecast and the check read.
_DATA_TASK = ("task.kp", "task.kd", "task.inner", "task.radius", "task.noise_std")
STAGE_SETTINGS = {
    "data": ("seed", *_DATA_TASK, "data"),
    "models": ("seed", *_DATA_TASK, "data", "model", "train"),
}
# disjoint seed ranges per purpose: data starts, condition c's starts, real episodes; a
# condition's check starts lie past its scored ones (CHECK_SEEDS on), its check's real
# episodes past the scored ones' (CHECK_REAL_SEEDS on); the dynamics checks' episodes take
# their seeds as they are (DYNAMICS_SEEDS on, a block per seed and condition), past the data's
# and the starts' seeds and below the real episodes' (REAL_SEEDS and on, times 100_003)
DATA_SEEDS, START_SEEDS, REAL_SEEDS = 0, 1_000_000, 2_000
CHECK_SEEDS, CHECK_REAL_SEEDS = 500_000, 20_000
DYNAMICS_SEEDS, DYNAMICS_BLOCK = 100_000_000, 100_000


class Study:
    """The stages of one study in one run directory."""

    def __init__(
        self,
        config: StudyConfig,
        run_dir: Path,
        progress: bool,
        logger: Logger | None = None,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.cfg, self.dir, self.progress, self.logger = config, Path(run_dir), progress, logger
        self.say = log or (lambda line: None)
        self.agent = PDController(config.task.kp, config.task.kd)

    def steps(self, seconds: float) -> int:
        return round(seconds / CONTROL_TIMESTEP)

    def success_fn(self) -> Callable[..., torch.Tensor]:
        return functools.partial(success, radius=self.cfg.task.radius)

    def load_model(self, name: str) -> RCVAEEnsemble:
        return load_ensemble(self.dir / "models" / f"{name}.pt")

    # ------------------------------------------------------------------ stages
    def data(self) -> dict[str, Any]:
        summary = {}
        for variant in WORLD_MODELS:
            path = self.dir / "data" / f"{variant}.pt"
            if not path.is_file():
                save_episodes(self._collect(variant), path)
            summary[f"{variant}_frames"] = int(load_episodes(path).shape[0])
        return summary

    def _collect(self, variant: str):
        d, seed = self.cfg.data, self.cfg.seed
        env, _ = make_env(variant, self.cfg.task)
        per_level = -(-d.episodes // len(d.exploration_std))
        parts = []
        for level, std in enumerate(d.exploration_std):
            first = DATA_SEEDS + 10_000 * seed + 1000 * level
            starts = starts_in_region(env, self.cfg.task, "inner", per_level, first)
            behaviour = make_policy_module(GaussianExploration(self.agent, std, seed=first))
            stats = run_episodes(
                env,
                behaviour,
                seeds=[first + i for i in range(per_level)],
                starts=starts,
                reset_to_state=reset_by_seed,
                max_steps=self.steps(d.time_limit_s),
                success=self.success_fn(),
                progress=self.progress,
                desc=f"{variant} data (exploration {std})",
            )
            parts.append(stats.data.exclude("position", "velocity", "label"))
        return merge_episodes(*parts)

    def models(self) -> dict[str, Any]:
        m, summary = self.cfg.model, {}
        _, layout = make_env("deterministic", self.cfg.task)
        config = RCVAEConfig(
            layout.dim,
            2,
            hidden_dim=m.hidden_dim,
            mlp_dim=m.hidden_dim,
            latent_dim=m.latent_dim,
            observation_names=layout.names,
            control_step=CONTROL_TIMESTEP,
        )
        done = [
            f"models/{n}.pt" for n in WORLD_MODELS if (self.dir / "models" / f"{n}.pt").is_file()
        ]
        if done:  # the stage runs again for its other files: say what it keeps
            self.say(f"[models] {', '.join(done)} written earlier: taken as they are")
        for name in WORLD_MODELS:
            path = self.dir / "models" / f"{name}.pt"
            if not path.is_file():
                torch.manual_seed(self.cfg.seed)
                ensemble = RCVAEEnsemble(config, m.ensemble_size)
                train, val = split_episodes(
                    load_episodes(self.dir / "data" / f"{name}.pt"), 0.1, seed=self.cfg.seed
                )
                result = train_ensemble(
                    ensemble,
                    train,
                    val,
                    dataclasses.replace(self.cfg.train, seed=self.cfg.seed),
                    checkpoint_path=self.dir / "models" / CHECKPOINTS / f"{name}.pt",
                    resume=True,
                    logger=self.logger,
                    log_prefix=f"models/{name}/",
                    progress=self.progress,
                )
                save_ensemble(result.ensemble, path, extra={"steps": result.steps})
            checks = self.load_model(name).checks
            summary[name] = {"flagged": [] if checks is None else checks.as_dict()["flagged"]}
        return summary

    def assessor(self, model_name: str, variant: str) -> CompetencyAssessor:
        task, a = self.cfg.task, self.cfg.assess
        env, _ = make_env(variant, task)
        model_env = make_rcvae_env(
            self.load_model(model_name), env, reward, self.success_fn(), seed=self.cfg.seed
        )
        widths = torch.tensor([a.bins[0]] * 2 + [a.bins[1]] * 2)
        return CompetencyAssessor(
            model_env,
            boundary(task),
            bin_width=widths,
            samples_per_member=a.samples_per_member,
            episode_end=True,
            bias_correction="shuffle",
            generator=torch.Generator().manual_seed(self.cfg.seed),
            policy=self.agent,
        )

    def starts(self, condition: str, count: int | None = None, offset: int = 0):
        """``count`` (default ``assess.start_states``) start states of ``condition``'s region;
        ``offset``: where their seeds begin past the scored ones' (the check's)."""
        _, variant, region = CONDITIONS[condition]
        env, _ = make_env(variant, self.cfg.task)
        first = START_SEEDS * (1 + list(CONDITIONS).index(condition)) + 10_000 * self.cfg.seed
        count = self.cfg.assess.start_states if count is None else count
        return starts_in_region(env, self.cfg.task, region, count, first + offset)

    def forecast(self) -> dict[str, Any]:
        summary = {}
        for condition, (model_name, variant, _) in CONDITIONS.items():
            path = self.dir / "forecast" / f"{condition}.pt"
            if not path.is_file():
                starts = self.starts(condition)
                report = self.assessor(model_name, variant).assess(
                    starts["observation"], generator=torch.Generator().manual_seed(self.cfg.seed)
                )
                # the whole report: its task, agent and deadline travel with its data
                save_torch(path, {"starts": starts.to_dict(), "report": report.as_dict()})
            saved = load_torch(path, "forecast")
            summary[condition] = float(saved["report"]["data"]["competency"]["p_success"].mean())
        return summary

    def truth(self) -> dict[str, Any]:
        summary = {}
        for index, condition in enumerate(CONDITIONS):
            path = self.dir / "truth" / f"{condition}.pt"
            if not path.is_file():
                starts = load_torch(self.dir / "forecast" / f"{condition}.pt", "forecast")
                starts = _tensordict(starts["starts"], "seed")
                seed = REAL_SEEDS + 100 * self.cfg.seed + index
                runs = self.cfg.assess.runs_per_start
                save_torch(path, self._real(condition, starts, seed, runs).as_dict())
            saved = load_torch(path, "real outcomes")
            summary[condition] = float(saved["success"].float().mean())
        return summary

    def _real(self, condition: str, starts: TensorDict, seed: int, runs: int) -> RealOutcomes:
        """The agent in ``condition``'s real env from ``starts``: ``runs`` episodes each in the
        stochastic env, one in a deterministic one (where the env and the controller repeat
        the same episode)."""
        variant = CONDITIONS[condition][1]
        return real_outcomes(
            functools.partial(make_real_env, variant, self.cfg.task),
            self.agent.module(),
            starts,
            runs_per_start=runs if variant == "stochastic" else 1,
            workers=self.cfg.assess.real_workers,
            reset_to_state=reset_by_seed,
            max_steps=self.steps(self.cfg.task.deadline_s),
            success=self.success_fn(),
            trace=distance,
            seed=seed,
            progress=self.progress,
            desc=f"real: {condition}",
        )

    def check(self) -> dict[str, Any]:
        """Each condition's outcome check: the agent forecast, then run in the real env, from
        ``assess.check_starts`` start states of the condition's region that no score uses
        (their seeds past the scored starts'), ``assess.check_runs`` times each in the
        stochastic env; saved as ``check/<condition>.json``."""
        summary = {}
        for index, (condition, (model_name, variant, _)) in enumerate(CONDITIONS.items()):
            path = self.dir / "check" / f"{condition}.json"
            if not path.is_file():
                starts = self.starts(condition, self.cfg.assess.check_starts, CHECK_SEEDS)
                report = self.assessor(model_name, variant).assess(
                    starts["observation"], generator=torch.Generator().manual_seed(self.cfg.seed)
                )
                seed = REAL_SEEDS + CHECK_REAL_SEEDS + 100 * self.cfg.seed + index
                outcomes = self._real(condition, starts, seed, self.cfg.assess.check_runs)
                check = OutcomeCheck.from_outcomes(report, outcomes)
                write_json(path, check.as_dict(), checksum=True)  # an edit is refused
            check, found = self.load_check(condition), self.load_dynamics(condition)
            summary[condition] = {
                "verdict": check.verdict,
                "passed": check.passed,
                "dynamics": None if found is None else found.passed,
            }
        return summary

    def _dynamics(self, condition: str, model_name: str) -> DynamicsCheck | None:
        """Does the condition's real env move as its world model learned? The controller run
        once from each check start (no outcome needed), its episodes' one-step errors ranked
        against the model's held-out episodes' (:func:`~rcvae_torchrl.training.check_dynamics`);
        ``None`` where the model has no such check (too few validation episodes)."""
        model = self.load_model(model_name)
        if model.dynamics is None:
            return None
        variant = CONDITIONS[condition][1]
        starts = self.starts(condition, self.cfg.assess.check_starts, CHECK_SEEDS)
        index = list(CONDITIONS).index(condition)
        seed = DYNAMICS_SEEDS + (self.cfg.seed * len(CONDITIONS) + index) * DYNAMICS_BLOCK
        stats = run_episodes(
            make_real_env(variant, self.cfg.task),
            self.agent.module(),
            seeds=[seed + i for i in range(starts.shape[0])],
            starts=starts,
            reset_to_state=reset_by_seed,
            max_steps=self.steps(self.cfg.task.deadline_s),
            success=self.success_fn(),
            progress=self.progress,
            desc=f"dynamics: {condition}",
        )
        return check_dynamics(model, stats.data)

    def load_dynamics(self, condition: str) -> DynamicsCheck | None:
        """The condition's dynamics check (``None`` where its model has none), made and saved
        as ``check/<condition>_dynamics.json`` where the run has none yet: the check stage
        makes it, and the report stage of a run whose check stage ran before dynamics checks
        were made."""
        path = self.dir / "check" / f"{condition}_dynamics.json"
        if not path.is_file():
            found = self._dynamics(condition, CONDITIONS[condition][0])
            record = None if found is None else found.as_dict()
            write_json(path, {"check": record}, checksum=True)  # an edit is refused
        record = read_json(path, "dynamics check")["check"]
        return None if record is None else DynamicsCheck.from_dict(record)

    def load_check(self, condition: str) -> OutcomeCheck:
        return OutcomeCheck.from_dict(read_json(self.dir / "check" / f"{condition}.json", "check"))

    def reports(self) -> dict[str, CompetencyReport]:
        """The reports of the three conditions, read back from the run whole (with the task,
        agent and deadline they answered)."""
        out = {}
        for condition in CONDITIONS:
            saved = load_torch(self.dir / "forecast" / f"{condition}.pt", "forecast")
            out[condition] = CompetencyReport.from_dict(saved["report"])
        return out

    def report(self) -> dict[str, Any]:
        reports = self.reports()
        truths = {
            c: load_torch(self.dir / "truth" / f"{c}.pt", "real outcomes") for c in CONDITIONS
        }
        scores = {
            # the report itself: its agent, boundary, start states and deadline are checked
            c: score_forecast(reports[c], RealOutcomes.from_dict(truths[c]))
            for c in CONDITIONS
        }
        checked = {c: reports[c].with_forecast_check(self.load_check(c)) for c in CONDITIONS}
        for c in CONDITIONS:
            if (moves := self.load_dynamics(c)) is not None:
                checked[c] = checked[c].with_dynamics_check(moves)
        return write_report(self.dir, checked, truths, scores, self.cfg)


def _tensordict(values: dict, first: str) -> TensorDict:
    """A TensorDict ``[B]`` of a stored dict, ``B`` read from its ``first`` entry."""
    return TensorDict(values, batch_size=[len(values[first])])


def study_settings(config: StudyConfig) -> dict[str, Any]:
    """The settings a run directory records (``study_config.json``) and reuses results under."""
    settings = {f.name: getattr(config, f.name) for f in dataclasses.fields(StudyConfig)}
    return dataclasses.asdict(StudyConfig(**settings))


def run_study(
    config: StudyConfig,
    run_dir: str | Path,
    *,
    progress: bool = True,
    log: Callable[[str], None] = print,
    logger: Logger | None = None,
    reuse_from: str | Path | None = None,
) -> dict[str, Any]:
    """Run (or resume) the study in ``run_dir``; returns every stage's summary.

    ``logger`` (a TorchRL logger) gets the training curves and every stage's numbers.
    ``reuse_from``: another run directory whose finished stages are taken where the settings
    they read (:data:`STAGE_SETTINGS`) and the files before them are this run's.
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
    study = Study(config, run_dir, progress, logger, log)
    for name, outputs in STAGES.items():
        runner.run(name, getattr(study, name), outputs)
    return runner.summaries
