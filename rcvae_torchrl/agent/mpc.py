"""The MPC agent: our CEM planner over the RCVAE ensemble env, optionally guided by a prior."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase

from rcvae_torchrl.model_env import RCVAEEnsembleEnv, make_rcvae_env
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.planners import OBJECTIVES, CEMPlanner
from rcvae_torchrl.rollout import (
    TRAJECTORY_SAMPLINGS,
    Compile,
    ImaginePolicy,
    RewardFn,
    SuccessFn,
)

__all__ = ["PlannerConfig", "make_mpc_policy", "policy_proposal"]


@dataclass(frozen=True)
class PlannerConfig:
    """The planning budget: ``num_candidates × iterations × horizon × particles`` model steps.

    Args:
        horizon: planning horizon H (control steps).
        num_candidates: action sequences sampled per CEM iteration.
        top_k: elites per iteration.
        iterations: CEM iterations per control step.
        particles: imagined trajectories per candidate (spread over the members).
        momentum: weight of the previous mean/std in the CEM update.
        objective: ``"mean"``, ``"quantile"``, ``"cvar"`` or ``"success"``.
        trajectory_sampling: ``"ts_inf"``, ``"ts1"`` or ``"mean"``.
        policy_prior: guide CEM with a prior policy's plan, imagined in the model (the prior
            is passed to :func:`make_mpc_policy`): each call searches around it (std
            ``prior_std`` × the prior std) and keeps it among the candidates, so the planner
            refines it where the model finds better. Off: plain CEM from the Gaussian prior,
            warm-started from the shifted previous plan.
        prior_std: the search width around the policy's plan, relative to the prior std.
    """

    horizon: int = 12
    num_candidates: int = 64
    top_k: int = 8
    iterations: int = 2
    particles: int = 5
    momentum: float = 0.1
    objective: str = "mean"
    trajectory_sampling: str = "ts_inf"
    policy_prior: bool = False
    prior_std: float = 0.1

    def __post_init__(self) -> None:
        for name in ("horizon", "num_candidates", "top_k", "iterations", "particles"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {value!r}")
        if self.top_k > self.num_candidates:
            raise ValueError(
                f"top_k: expected at most num_candidates ({self.num_candidates}), got {self.top_k}"
            )
        for name in ("momentum", "prior_std"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ValueError(f"{name}: expected a number, got {value!r}")
        if not 0.0 <= self.momentum < 1.0:
            raise ValueError(f"momentum: expected a value in [0, 1), got {self.momentum!r}")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective: expected one of {OBJECTIVES}, got {self.objective!r}")
        if self.trajectory_sampling not in TRAJECTORY_SAMPLINGS:
            raise ValueError(
                f"trajectory_sampling: expected one of {list(TRAJECTORY_SAMPLINGS)}, "
                f"got {self.trajectory_sampling!r}"
            )
        if not (self.prior_std > 0 and math.isfinite(self.prior_std)):
            raise ValueError(
                f"prior_std: expected a positive finite number, got {self.prior_std!r}"
            )


def make_mpc_policy(
    ensemble: RCVAEEnsemble,
    real_env: EnvBase,
    config: PlannerConfig,
    *,
    reward_fn: RewardFn,
    success_fn: SuccessFn,
    terminate_on_success: bool = False,
    prior: ImaginePolicy | None = None,
    seed: int = 0,
    compile: Compile = False,
) -> CEMPlanner:
    """A CEM planner over an :class:`~rcvae_torchrl.model_env.RCVAEEnsembleEnv` of ``ensemble``
    with the specs of ``real_env``; use it as a TorchRL policy in ``real_env``.

    Args:
        ensemble: the world model.
        real_env: the env the agent acts in (its specs are copied).
        config: the planning budget.
        reward_fn, success_fn: the task (:class:`~rcvae_torchrl.rollout.Task`).
        terminate_on_success: whether success ends the real env's episodes.
        prior: the prior policy of ``config.policy_prior`` (a tensor callable or TensorDict
            module on observations); required then, ignored otherwise.
        seed: seeds the model env and the planner.
        compile: score candidates with the compiled rollout (``"ts_inf"`` only; the env's
            ``compile_scoring``): ``True`` with ``torch.compile`` (the first plan of every
            process compiles, tens of seconds to minutes on a CPU), ``"aot"`` with a package
            compiled ahead of time and cached across processes (built once per architecture,
            task and horizon, then loaded in a fraction of a second). Later plans are faster
            than eager ones and agree with them up to float rounding. An execution setting,
            so not part of :class:`PlannerConfig`.
    """
    if config.policy_prior and prior is None:
        raise ValueError("prior: config.policy_prior is True, so a prior policy is needed")
    model_env = make_rcvae_env(
        ensemble,
        real_env,
        reward_fn,
        success_fn,
        trajectory_sampling=config.trajectory_sampling,
        terminate_on_success=terminate_on_success,
        seed=seed,
        compile_scoring=compile,
    )
    skip = ("trajectory_sampling", "policy_prior", "prior_std")
    kwargs = {k: v for k, v in asdict(config).items() if k not in skip}
    proposal, proposal_std = None, None
    if config.policy_prior:
        proposal = policy_proposal(model_env, prior, config.horizon)
        proposal_std = config.prior_std
    return CEMPlanner(model_env, seed=seed, proposal=proposal, proposal_std=proposal_std, **kwargs)


def policy_proposal(
    model_env: RCVAEEnsembleEnv, policy: ImaginePolicy, horizon: int
) -> Callable[[TensorDictBase], torch.Tensor]:
    """A planner proposal: ``policy``'s actions along one imagined rollout (member 0),
    ``[*B, H, A]`` from the input's observations ``[*B, S]``
    (:meth:`~rcvae_torchrl.model_env.RCVAEEnsembleEnv.plan_actions`)."""

    def propose(td: TensorDictBase) -> torch.Tensor:
        plan = model_env.plan_actions(td["observation"], policy, horizon)
        if not bool(torch.isfinite(plan).all()):
            raise ValueError("policy_proposal: non-finite actions along the imagined rollout")
        return plan

    return propose
