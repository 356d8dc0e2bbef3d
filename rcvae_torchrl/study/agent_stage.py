"""The study's agent: MPC in the real env teaches an amortised policy that is then forecast.

With the default policy-guided planner (CEM around the scripted pusher's plan), the amortised
agent is that prior plus a small MLP correction distilled from the planner (a
:class:`~rcvae_torchrl.agent.ResidualPolicy`); with plain CEM it is an MLP on its own.

Planning at every step of thousands of imagined particles over 600 steps is far beyond a CPU
budget, so the agent that acts and is forecast is an :class:`~rcvae_torchrl.agent.MLPPolicy`
distilled from the CEM planner's actions in MPC episodes (behaviour cloning). The executed
action is perturbed during those episodes (the recorded label is the planner's), so the policy
also sees states off the planner's own path and learns to recover from them. DAgger rounds
(Ross, Gordon & Bagnell 2011) then run the policy itself, label the states it visits with the
planner (all of a round's states planned at once, as one batch) and retrain on everything.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs import EnvBase

from rcvae_torchrl.agent import (
    DistillConfig,
    MLPPolicy,
    PlannerConfig,
    ResidualPolicy,
    distill_policy,
    make_mpc_policy,
    make_policy_module,
    run_episodes,
)
from rcvae_torchrl.models import RCVAEEnsemble

__all__ = [
    "PerturbedPolicy",
    "collect_mpc_demonstrations",
    "dagger",
    "label_states",
    "train_agent_policy",
]


class PerturbedPolicy:
    """Records ``policy``'s action as the label and executes it plus Gaussian noise."""

    def __init__(
        self, policy: Callable[[TensorDictBase], TensorDictBase], noise_std: float, seed: int = 0
    ) -> None:
        self.policy, self.noise_std = policy, noise_std
        self.generator = torch.Generator().manual_seed(seed)

    def reset(self) -> None:
        if hasattr(type(self.policy), "reset"):
            self.policy.reset()

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td = self.policy(td)
        label = td["action"]
        noise = torch.randn(label.shape, generator=self.generator) * self.noise_std
        td["label"] = label
        td["action"] = (label + noise).clamp(-1.0, 1.0)
        return td


def collect_mpc_demonstrations(
    ensemble: RCVAEEnsemble,
    env: EnvBase,
    planner: PlannerConfig,
    *,
    episodes: int,
    action_noise: float,
    seed: int,
    progress: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
    """Observations ``[M, S]`` and planner actions ``[M, A]`` from MPC episodes in ``env``."""
    mpc = make_mpc_policy(ensemble, env, planner, seed=seed)
    behaviour = PerturbedPolicy(mpc, action_noise, seed=seed)
    seeds = [50_000 + seed * 1000 + i for i in range(episodes)]
    stats = run_episodes(env, behaviour, seeds=seeds, progress=progress, desc="MPC demos")
    info = {
        "mpc_noisy_success_rate": stats.success_rate,
        "mpc_median_steps": stats.steps.float().median().item(),
        "pairs": float(stats.data.shape[0]),
    }
    return stats.data["observation"], stats.data["label"], info


def train_agent_policy(
    observations: torch.Tensor,
    labels: torch.Tensor,
    distill: DistillConfig,
    env: EnvBase,
    *,
    eval_episodes: int,
    seed: int,
    progress: bool = True,
) -> tuple[MLPPolicy, dict[str, float]]:
    """Distil the policy and measure its success in ``env`` on fresh seeds."""
    policy, info = distill_policy(observations, labels, distill, progress=progress)
    seeds = [70_000 + seed * 1000 + i for i in range(eval_episodes)]
    stats = run_episodes(
        env, make_policy_module(policy), seeds=seeds, progress=progress, desc="policy eval"
    )
    return policy, {
        **info,
        "policy_success_rate": stats.success_rate,
        "policy_median_steps": stats.steps.float().median().item(),
    }


def label_states(
    planner: Callable[[TensorDictBase], TensorDictBase], states: torch.Tensor, chunk: int = 256
) -> torch.Tensor:
    """The planner's action ``[M, A]`` for each state ``[M, S]``, planned in batches."""
    from tensordict import TensorDict

    actions = []
    for part in states.split(chunk):
        if hasattr(type(planner), "reset"):
            planner.reset()
        td = TensorDict({"observation": part}, batch_size=[part.shape[0]])
        with torch.no_grad():
            actions.append(planner(td)["action"])
    return torch.cat(actions)


def dagger(
    ensemble: RCVAEEnsemble,
    env: EnvBase,
    planner_config: PlannerConfig,
    observations: torch.Tensor,
    labels: torch.Tensor,
    distill: DistillConfig,
    *,
    rounds: int,
    episodes: int,
    seed: int,
    progress: bool = True,
    base: nn.Module | None = None,
) -> tuple[nn.Module, torch.Tensor, torch.Tensor, list[dict[str, float]]]:
    """Distil, then ``rounds`` times: run the policy, label its states with MPC, retrain.

    With a ``base`` policy (the planner's own prior), the MLP learns the correction
    ``label - base(s)`` and the agent is a :class:`ResidualPolicy`. Returns the last policy, all
    observations and labels, and per-round statistics.
    """
    planner = make_mpc_policy(ensemble, env, planner_config, seed=seed)

    def fit(obs: torch.Tensor, target: torch.Tensor) -> tuple[nn.Module, dict]:
        if base is None:
            return distill_policy(obs, target, distill, progress=progress)
        with torch.no_grad():
            correction = target - base(obs)
        mlp, stats = distill_policy(obs, correction, distill, progress=progress)
        return ResidualPolicy(base, mlp), stats

    policy, info = fit(observations, labels)
    history = [{"round": 0, "pairs": float(len(observations)), **info}]
    for k in range(1, rounds + 1):
        seeds = [80_000 + seed * 1000 + 100 * k + i for i in range(episodes)]
        stats = run_episodes(
            env,
            make_policy_module(policy),
            seeds=seeds,
            progress=progress,
            desc=f"DAgger {k}: policy",
        )
        states = stats.data["observation"]
        observations = torch.cat([observations, states])
        labels = torch.cat([labels, label_states(planner, states)])
        policy, info = fit(observations, labels)
        history.append(
            {
                "round": k,
                "pairs": float(len(observations)),
                "policy_success_before": stats.success_rate,
                **info,
            }
        )
    return policy, observations, labels, history
