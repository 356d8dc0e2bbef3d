"""Distilling a planner into an amortised policy: demonstrations, then DAgger rounds.

Planning at every step of thousands of imagined particles over a whole episode is far beyond a
CPU budget, so the agent that acts and is forecast can be an :class:`~rcvae_torchrl.agent.MLPPolicy`
distilled from the planner's actions (behaviour cloning). The executed action is perturbed
during the demonstrations (:class:`PerturbedPolicy`; the recorded label is the planner's), so
the policy also sees states off the planner's own path and learns to recover from them. DAgger
rounds (Ross, Gordon & Bagnell 2011) then run the policy itself, label the states it visits
with the planner (all of a round's states planned at once, as one batch) and retrain on
everything. With a ``base`` policy (e.g. the planner's own prior) the MLP learns the correction
``label - base(s)`` and the agent is a :class:`~rcvae_torchrl.agent.ResidualPolicy`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.envs import EnvBase

from rcvae_torchrl._checks import (
    check_bounds,
    check_non_negative,
    check_non_negative_int,
    check_positive_int,
    check_rank,
    check_tensor,
    make_generator,
)
from rcvae_torchrl.data import make_policy_module

from .distill import DistillConfig, distill_policy
from .episodes import check_policy, run_episodes
from .policy import ResidualPolicy

__all__ = ["PerturbedPolicy", "dagger", "label_states"]

TensorDictPolicy = Callable[[TensorDictBase], TensorDictBase]


class PerturbedPolicy:
    """Records ``policy``'s action under ``"label"`` and executes it plus Gaussian noise
    (clipped to ``[low, high]``, the action bounds)."""

    def __init__(
        self,
        policy: TensorDictPolicy,
        noise_std: float,
        seed: int = 0,
        low: float = -1.0,
        high: float = 1.0,
    ) -> None:
        check_policy(policy)
        check_non_negative("noise_std", noise_std)
        check_bounds("low, high", low, high)
        self.policy, self.noise_std, self.low, self.high = policy, noise_std, low, high
        self.generator = make_generator(None, seed)

    def reset(self) -> None:
        if hasattr(type(self.policy), "reset"):
            self.policy.reset()

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td = self.policy(td)
        label = td.get("action", None)
        if not isinstance(label, torch.Tensor):
            raise KeyError("policy: expected it to write an 'action' to perturb, got none")
        noise = torch.randn(label.shape, generator=self.generator) * self.noise_std
        td["label"] = label
        td["action"] = (label + noise).clamp(self.low, self.high)
        return td


def label_states(planner: TensorDictPolicy, states: torch.Tensor, chunk: int = 256) -> torch.Tensor:
    """The planner's action ``[M, A]`` for each state ``[M, S]``, planned in batches (each from
    a fresh plan: the planner's warm start is reset per batch)."""
    actions = []
    check_positive_int("chunk", chunk)
    check_tensor("states", states)
    check_rank("states", states, 2, "[M, S]")
    for part in states.split(chunk):
        if hasattr(type(planner), "reset"):
            planner.reset()
        td = TensorDict({"observation": part}, batch_size=[part.shape[0]])
        with torch.no_grad():
            actions.append(planner(td)["action"])
    return torch.cat(actions)


def dagger(
    planner: TensorDictPolicy,
    env: EnvBase,
    observations: torch.Tensor,
    labels: torch.Tensor,
    distill: DistillConfig,
    *,
    rounds: int,
    episode_seeds: Callable[[int], Sequence[int]],
    max_steps: int,
    base: nn.Module | None = None,
    progress: bool = True,
) -> tuple[nn.Module, torch.Tensor, torch.Tensor, list[dict[str, float]]]:
    """Distil, then ``rounds`` times: run the policy, label its states with ``planner``, retrain.

    Args:
        planner: the expert (e.g. :func:`~rcvae_torchrl.agent.make_mpc_policy`).
        env: the real env the policy runs in.
        observations, labels: the demonstrations ``[M, S]`` and the planner's actions ``[M, A]``.
        distill: the behaviour-cloning budget.
        rounds: DAgger rounds (0: distil only).
        episode_seeds: round k (1-based) -> the seeds of its policy episodes.
        max_steps: episode length cap.
        base: learn a residual on this policy.
        progress: show progress bars.

    Returns:
        the last policy, all observations and labels, and per-round statistics.
    """

    check_non_negative_int("rounds", rounds)
    if rounds and not callable(episode_seeds):
        raise TypeError(
            "episode_seeds: expected a function of the round k (1-based) giving its episodes' "
            f"seeds, e.g. lambda k: range(100 * k, 100 * k + 10), got {episode_seeds!r}"
        )

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
        stats = run_episodes(
            env,
            make_policy_module(policy),
            seeds=list(episode_seeds(k)),
            max_steps=max_steps,
            progress=progress,
            desc=f"DAgger {k}: policy",
        )
        states = stats.data["observation"]
        new = label_states(planner, states)
        if new.shape[-1] != labels.shape[-1]:
            raise ValueError(
                f"planner: expected actions of A={labels.shape[-1]} (the demonstrations' labels), "
                f"got A={new.shape[-1]}"
            )
        observations = torch.cat([observations, states])
        labels = torch.cat([labels, new])
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
