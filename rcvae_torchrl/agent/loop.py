"""The model-based RL loop: collect, train the ensemble, act with MPC, add the data, retrain.

Every stage writes its result atomically under ``out_dir`` (data, per-round training checkpoints
and models, MPC episodes, ``history.json``), so a run that is stopped, even by ``kill -9``,
resumes where it was and never redoes finished rounds.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from rcvae_torchrl.data import TRAJ_KEY, load_episodes, save_episodes, split_episodes
from rcvae_torchrl.envs import CONTROL_TIMESTEP, make_pusher_env, obs_indices
from rcvae_torchrl.envs.datasets import collect_pusher_data
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.training import TrainConfig, load_ensemble, save_ensemble, train_ensemble
from rcvae_torchrl.training.atomic import atomic_write

from .mpc import PlannerConfig, make_mpc_policy, run_episodes

__all__ = ["AgentConfig", "AgentResult", "run_model_based_agent"]


@dataclass(frozen=True)
class AgentConfig:
    """Budget of :func:`run_model_based_agent` on the Pusher.

    Args:
        variant: Pusher variant the agent acts in (``"deterministic"``, ``"stochastic"``).
        rounds: K rounds of train -> act -> add data.
        scripted_episodes, random_episodes: initial data (scripted pusher with Gaussian
            exploration noise ``exploration_std``, and random play).
        data_time_limit: length (s) of the initial scripted episodes (they run past success).
        mpc_episodes: real episodes acted with MPC per round (their data is added).
        mpc_time_limit: length (s) of those episodes.
        ensemble_size, hidden_dim: the world model.
        train: training budget per round (later rounds continue from the previous weights).
        planner: the MPC budget.
        seed: seeds everything.
    """

    variant: str = "deterministic"
    rounds: int = 2
    scripted_episodes: int = 100
    random_episodes: int = 20
    exploration_std: float = 0.3
    data_time_limit: float = 15.0
    mpc_episodes: int = 5
    mpc_time_limit: float = 30.0
    ensemble_size: int = 5
    hidden_dim: int = 64
    train: TrainConfig = field(
        default_factory=lambda: TrainConfig(
            max_steps=1500, batch_windows=32, window=32, val_every=100
        )
    )
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    seed: int = 0


@dataclass
class AgentResult:
    """The last round's ensemble, all data gathered, and one history row per round."""

    ensemble: RCVAEEnsemble
    data: TensorDict
    history: list[dict[str, float]] = field(default_factory=list)


def _new_ensemble(config: AgentConfig) -> RCVAEEnsemble:
    model = RCVAEConfig(
        14,
        2,
        hidden_dim=config.hidden_dim,
        mlp_dim=config.hidden_dim,
        passthrough_dims=tuple(obs_indices("target")),
    )
    torch.manual_seed(config.seed)
    return RCVAEEnsemble(model, config.ensemble_size)


def _initial_data(config: AgentConfig, path: Path, progress: bool) -> TensorDict:
    if path.is_file():
        return load_episodes(path)
    data = collect_pusher_data(
        config.variant,
        scripted_episodes=config.scripted_episodes,
        random_episodes=config.random_episodes,
        exploration_std=config.exploration_std,
        time_limit=config.data_time_limit,
        seed=config.seed,
        progress=progress,
    )
    save_episodes(data, path)
    return data


def _train_round(
    config: AgentConfig,
    data: TensorDict,
    previous: RCVAEEnsemble | None,
    round_dir: Path,
    progress: bool,
) -> tuple[RCVAEEnsemble, dict]:
    model_path = round_dir / "model.pt"
    if model_path.is_file():
        return load_ensemble(model_path), {}
    ensemble = _new_ensemble(config)
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


def _record_config(path: Path, config: dict) -> None:
    """Write the loop's config; an output folder made with other settings is an error (more
    ``rounds`` is fine: a run can be extended)."""
    if path.is_file():
        saved, current = json.loads(path.read_text()), json.loads(json.dumps(config))
        saved.pop("rounds", None)
        if saved != {k: v for k, v in current.items() if k != "rounds"}:
            raise ValueError(
                f"out_dir: {str(path.parent)!r} holds a run made with other settings; "
                "finished rounds would be reused: use a new out_dir"
            )
    atomic_write(path, lambda f: f.write(json.dumps(config, indent=2).encode()))


def run_model_based_agent(
    config: AgentConfig, out_dir: str | Path, *, progress: bool = True
) -> AgentResult:
    """Run K rounds of model-based RL on the Pusher; resumable from ``out_dir``.

    Round k trains the ensemble on all data so far (continuing from round k-1's weights), acts
    ``mpc_episodes`` episodes with the CEM planner in the real env, and adds them to the data.
    """
    out = Path(out_dir)
    _record_config(out / "config.json", dataclasses.asdict(config))
    history_path = out / "history.json"
    history = json.loads(history_path.read_text()) if history_path.is_file() else []
    data = _initial_data(config, out / "data_initial.pt", progress)
    env = make_pusher_env(config.variant, time_limit=config.mpc_time_limit)
    max_steps = round(config.mpc_time_limit / CONTROL_TIMESTEP)
    ensemble = None
    for k in tqdm(range(config.rounds), desc="agent rounds", disable=not progress):
        round_dir = out / f"round_{k}"
        ensemble, train_info = _train_round(config, data, ensemble, round_dir, progress)
        episodes_path = round_dir / "mpc_episodes.pt"
        if episodes_path.is_file():
            data = torch.cat([data, load_episodes(episodes_path)])
            continue
        policy = make_mpc_policy(ensemble, env, config.planner, seed=config.seed + k)
        seeds = [10_000 * (k + 1) + config.seed * 100 + i for i in range(config.mpc_episodes)]
        stats = run_episodes(
            env,
            policy,
            seeds=seeds,
            max_steps=max_steps,
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
        text = json.dumps(history, indent=2).encode()
        atomic_write(history_path, lambda f, text=text: f.write(text))
        save_episodes(episodes, episodes_path)
        data = torch.cat([data, episodes])
    return AgentResult(ensemble, data, history)
