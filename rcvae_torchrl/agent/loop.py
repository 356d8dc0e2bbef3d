"""The model-based RL loop: train the ensemble, act with MPC, add the data, retrain.

Every stage writes its result atomically under ``out_dir`` (per-round training checkpoints and
models, MPC episodes, ``history.json``), so a run that is stopped, even by ``kill -9``, resumes
where it was and never redoes finished rounds.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.envs import EnvBase
from tqdm.auto import tqdm

from rcvae_torchrl.data import TRAJ_KEY, load_episodes, save_episodes, split_episodes
from rcvae_torchrl.io import read_json, record_run_config, write_json
from rcvae_torchrl.models import ModelFunctions, RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.rollout import ImaginePolicy, RewardFn, SuccessFn
from rcvae_torchrl.training import TrainConfig, load_ensemble, save_ensemble, train_ensemble

from .episodes import run_episodes
from .mpc import PlannerConfig, make_mpc_policy

__all__ = ["AgentConfig", "AgentResult", "AgentTask", "run_model_based_agent"]


@dataclass(frozen=True)
class AgentConfig:
    """Budget of :func:`run_model_based_agent`.

    Args:
        rounds: K rounds of train -> act -> add data.
        mpc_episodes: real episodes acted with MPC per round (their data is added).
        max_steps: length of those episodes (steps).
        ensemble_size: members of the world model.
        train: training budget per round (later rounds continue from the previous weights).
        planner: the MPC budget.
        seed: seeds everything.
    """

    rounds: int = 2
    mpc_episodes: int = 5
    max_steps: int = 600
    ensemble_size: int = 5
    train: TrainConfig = field(
        default_factory=lambda: TrainConfig(
            max_steps=1500, batch_windows=32, window=32, val_every=100
        )
    )
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    seed: int = 0


@dataclass(frozen=True)
class AgentTask:
    """What the loop needs of the problem: the env, the model's shape and the task.

    Args:
        make_env: a factory of the real env the agent acts in.
        model: the config of one ensemble member.
        reward_fn, success_fn: the task (:class:`~rcvae_torchrl.rollout.Task`).
        terminate_on_success: whether success ends the real env's episodes.
        functions: the state constraint and input features ``model`` names.
        prior: the planner's prior policy (with ``PlannerConfig.policy_prior``).
    """

    make_env: Callable[[], EnvBase]
    model: RCVAEConfig
    reward_fn: RewardFn
    success_fn: SuccessFn
    terminate_on_success: bool = False
    functions: ModelFunctions | None = None
    prior: ImaginePolicy | None = None


@dataclass
class AgentResult:
    """The last round's ensemble, all data gathered, and one history row per round."""

    ensemble: RCVAEEnsemble
    data: TensorDict
    history: list[dict[str, float]] = field(default_factory=list)


def _train_round(
    config: AgentConfig,
    task: AgentTask,
    data: TensorDict,
    previous: RCVAEEnsemble | None,
    round_dir: Path,
    progress: bool,
) -> tuple[RCVAEEnsemble, dict]:
    model_path = round_dir / "model.pt"
    if model_path.is_file():
        return load_ensemble(model_path, functions=task.functions), {}
    torch.manual_seed(config.seed)
    ensemble = RCVAEEnsemble(task.model, config.ensemble_size, functions=task.functions)
    if previous is not None:
        ensemble.load_state_dict(previous.state_dict())
    train, val = split_episodes(data, 0.1, seed=config.seed)
    result = train_ensemble(
        ensemble,
        train,
        val,
        config.train,
        checkpoint_path=round_dir / "train.pt",
        resume=True,
        progress=progress,
    )
    save_ensemble(result.ensemble, model_path)
    return result.ensemble, {"train_steps": result.steps, "val_loss": result.best_val.mean().item()}


def _episode_seeds(config: AgentConfig, k: int) -> Sequence[int]:
    return [10_000 * (k + 1) + config.seed * 100 + i for i in range(config.mpc_episodes)]


def run_model_based_agent(
    config: AgentConfig,
    task: AgentTask,
    initial_data: TensorDict,
    out_dir: str | Path,
    *,
    progress: bool = True,
) -> AgentResult:
    """Run K rounds of model-based RL; resumable from ``out_dir``.

    Round k trains the ensemble on all data so far (continuing from round k-1's weights), acts
    ``mpc_episodes`` episodes with the CEM planner in the real env, and adds them to the data.
    ``out_dir`` records the config; a directory made with other settings is an error (more
    ``rounds`` is fine: a run can be extended).
    """
    out = Path(out_dir)
    record_run_config(out / "config.json", dataclasses.asdict(config), may_change=("rounds",))
    history_path = out / "history.json"
    history = read_json(history_path, "agent history") if history_path.is_file() else []
    data = initial_data
    env = task.make_env()
    ensemble = None
    for k in tqdm(range(config.rounds), desc="agent rounds", disable=not progress):
        round_dir = out / f"round_{k}"
        ensemble, train_info = _train_round(config, task, data, ensemble, round_dir, progress)
        episodes_path = round_dir / "mpc_episodes.pt"
        if episodes_path.is_file():
            data = torch.cat([data, load_episodes(episodes_path)])
            continue
        policy = make_mpc_policy(
            ensemble,
            env,
            config.planner,
            reward_fn=task.reward_fn,
            success_fn=task.success_fn,
            terminate_on_success=task.terminate_on_success,
            prior=task.prior,
            seed=config.seed + k,
        )
        stats = run_episodes(
            env,
            policy,
            seeds=_episode_seeds(config, k),
            max_steps=config.max_steps,
            first_id=int(data[TRAJ_KEY].max()) + 1,
            progress=progress,
            desc=f"round {k}: MPC",
        )
        episodes = stats.data.select(*data.keys(True, True))
        # The history row first: a kill before the episodes are saved redoes the round, and
        # the row (keyed by round) is then replaced.
        history = [row for row in history if row["round"] != k]
        history.append(
            {
                "round": k,
                **train_info,
                "mpc_success_rate": stats.success_rate,
                "mpc_median_steps": stats.steps.float().median().item(),
                "frames": int(data.shape[0] + episodes.shape[0]),
            }
        )
        write_json(history_path, history)
        save_episodes(episodes, episodes_path)
        data = torch.cat([data, episodes])
    return AgentResult(ensemble, data, history)
