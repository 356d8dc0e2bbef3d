"""The MPC agent: our CEM planner over the RCVAE ensemble env, and running it in the real env."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from tqdm.auto import tqdm

from rcvae_torchrl.data import TRAJ_KEY
from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.envs.scripted import ScriptedPusher
from rcvae_torchrl.envs.state import reset_to_state
from rcvae_torchrl.model_env import RCVAEEnsembleEnv, make_rcvae_env
from rcvae_torchrl.model_env.imagine import as_tensor_policy
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.planners import OBJECTIVES, CEMPlanner

__all__ = ["EpisodeStats", "PlannerConfig", "make_mpc_policy", "policy_proposal", "run_episodes"]


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
        policy_prior: guide CEM with the scripted pusher's plan, imagined in the model: each
            call searches around it (std ``prior_std`` × the prior std) and keeps it among the
            candidates, so the planner refines it where the model finds better. Off: plain CEM
            from the Gaussian prior, warm-started from the shifted previous plan.
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
    policy_prior: bool = True
    prior_std: float = 0.1

    def __post_init__(self) -> None:
        for name in ("horizon", "num_candidates", "top_k", "iterations", "particles"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise ValueError(f"{name}: expected an int >= 1, got {getattr(self, name)!r}")
        if self.top_k > self.num_candidates:
            raise ValueError(
                f"top_k: expected at most num_candidates ({self.num_candidates}), got {self.top_k}"
            )
        if not 0.0 <= self.momentum < 1.0:
            raise ValueError(f"momentum: expected a value in [0, 1), got {self.momentum!r}")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective: expected one of {OBJECTIVES}, got {self.objective!r}")
        if self.trajectory_sampling not in ("ts_inf", "ts1", "mean"):
            raise ValueError(
                "trajectory_sampling: expected 'ts_inf', 'ts1' or 'mean', "
                f"got {self.trajectory_sampling!r}"
            )


def make_mpc_policy(
    ensemble: RCVAEEnsemble,
    real_env: EnvBase,
    config: PlannerConfig = PlannerConfig(),
    *,
    reward_fn: Callable = pusher_reward,
    success_fn: Callable = pusher_success,
    seed: int = 0,
    compile: bool = False,
) -> CEMPlanner:
    """A CEM planner over an :class:`~rcvae_torchrl.model_env.RCVAEEnsembleEnv` of ``ensemble``
    with the specs of ``real_env``; use it as a TorchRL policy in ``real_env``.

    ``compile``: score candidates with the ``torch.compile``-d rollout (``"ts_inf"`` only;
    the env's ``compile_scoring``). The first plan compiles (tens of seconds to minutes on a
    CPU), later ones are faster; the plans agree with the eager ones up to float rounding. An
    execution setting, so not part of :class:`PlannerConfig` (recorded with the results).
    """
    model_env = make_rcvae_env(
        ensemble,
        real_env,
        reward_fn,
        success_fn,
        trajectory_sampling=config.trajectory_sampling,
        seed=seed,
        compile_scoring=compile,
    )
    skip = ("trajectory_sampling", "policy_prior", "prior_std")
    kwargs = {k: v for k, v in asdict(config).items() if k not in skip}
    proposal = None
    if config.policy_prior:
        proposal = policy_proposal(model_env, ScriptedPusher(), config.horizon)
    proposal_std = config.prior_std if config.policy_prior else None
    return CEMPlanner(model_env, seed=seed, proposal=proposal, proposal_std=proposal_std, **kwargs)


def policy_proposal(
    model_env: RCVAEEnsembleEnv, policy: Callable[[torch.Tensor], torch.Tensor], horizon: int
) -> Callable[[TensorDictBase], torch.Tensor]:
    """A planner proposal: ``policy``'s actions along one imagined rollout (member 0),
    ``[*B, H, A]`` from the input's observations ``[*B, S]``.

    The same actions as ``model_env.imagine(obs, policy=policy, horizon=horizon)["action"][0,
    0]`` from the same generator state (the same model steps and noise, all members stepped),
    without what the planner does not use: the decoder's state distribution, the task's reward
    and success, the TensorDict of the whole rollout.
    """
    tensor_policy = as_tensor_policy(policy)
    ensemble = model_env.ensemble

    def propose(td: TensorDictBase) -> torch.Tensor:
        obs = td["observation"]
        starts = obs.reshape(-1, obs.shape[-1])
        if starts.shape[0] > _IMAGINE_CHUNK:  # imagine rolls out in chunks: its own noise
            rollout = model_env.imagine(obs, policy=policy, horizon=horizon, samples_per_member=1)
            return rollout["action"][0, 0]
        with torch.no_grad():
            state = starts.expand(ensemble.ensemble_size, *starts.shape)
            hidden = ensemble.initial_hidden(starts.shape[:1], state)
            actions = []
            for _ in range(horizon):
                action = tensor_policy(state)
                actions.append(action[0])
                out = ensemble.step(hidden, state, action, generator=model_env.generator)
                state, hidden = out.observation, out.hidden
            plan = torch.stack(actions, dim=-2).reshape(*obs.shape[:-1], horizon, -1)
        if not bool(torch.isfinite(plan).all()):
            raise ValueError("policy_proposal: non-finite actions along the imagined rollout.")
        return plan

    return propose


_IMAGINE_CHUNK = 1024  # RCVAEEnsembleEnv.imagine's default chunk_size


@dataclass
class EpisodeStats:
    """Outcomes of episodes run by :func:`run_episodes`."""

    success: torch.Tensor  # [n] bool
    steps: torch.Tensor  # [n] int64: steps to success, or the episode length
    data: TensorDict  # flat transitions [frames] with episode ids under TRAJ_KEY

    @property
    def success_rate(self) -> float:
        return self.success.float().mean().item()


def run_episodes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase],
    *,
    seeds: Sequence[int],
    starts: torch.Tensor | None = None,
    max_steps: int = 600,
    first_id: int = 0,
    progress: bool = True,
    desc: str = "episodes",
) -> EpisodeStats:
    """One episode per seed (``env.set_seed(seed)`` draws the start state and the noise), or
    from the given start observations ``starts [n, S]`` (the seed then only draws the noise).

    Calls ``policy.reset()`` before each episode when the policy has one (the planner's warm
    start must not leak across episodes).
    """
    if starts is not None and len(starts) != len(seeds):
        raise ValueError(
            f"starts: expected one start state per seed ({len(seeds)}), got {len(starts)}"
        )
    success, steps, parts = [], [], []
    for i, seed in enumerate(tqdm(seeds, desc=desc, disable=not progress, leave=False)):
        env.set_seed(int(seed))
        td = env.reset() if starts is None else reset_to_state(env, starts[i])
        if hasattr(type(policy), "reset"):  # a planner's warm start (not an env's reset)
            policy.reset()
        with torch.no_grad():
            episode = env.rollout(
                max_steps, policy, auto_reset=False, tensordict=td, break_when_any_done=True
            )
        won = episode["next", "success"].reshape(-1)
        success.append(bool(won.any()))
        steps.append(int(won.float().argmax()) + 1 if won.any() else episode.shape[0])
        episode[TRAJ_KEY] = torch.full(episode.shape, first_id + i, dtype=torch.int64)
        parts.append(episode.exclude("is_init"))
    return EpisodeStats(torch.tensor(success), torch.tensor(steps), torch.cat(parts))
