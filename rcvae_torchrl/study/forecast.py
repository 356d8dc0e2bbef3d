"""Forecasting one condition: imagined rollouts of the agent from start states, and their metrics.

Closed loop (default): the agent's policy acts inside the imagined rollouts, so the forecast is
about the same agent that later runs in the real env. Open loop (the paper's
p(s_1:T | s_0, a_0:T-1)): the action sequence is the policy's plan in the model's mean rollout.
Rollouts run the whole horizon; success is reaching the boundary at any step within the time
limit. With ``episode_end`` (the study's default) the uncertainty is that of the episode, which
the real env ends at success: from the step after a sample's success on, the sample counts in a
shared terminal bin (:meth:`SuccessBoundary.ended_over_time`) instead of the states the model
would imagine for a finished episode.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict

from rcvae_torchrl.competency import SuccessBoundary, SuccessMetric, UncertaintyMetric
from rcvae_torchrl.envs import OBSERVATION_NAMES, ball_to_target, obs_indices, resolution_tensor
from rcvae_torchrl.model_env import RCVAEEnsembleEnv

__all__ = ["forecast_condition", "pusher_boundary"]


def pusher_boundary(radius: float, horizon_s: float, dt: float) -> SuccessBoundary:
    """Success: the ball within ``radius`` of the target within ``horizon_s`` seconds."""
    return SuccessBoundary.ball(
        obs_indices("ball"), radius, target=obs_indices("target"), time_limit_s=horizon_s, dt=dt
    )


def _open_loop_actions(
    model_env: RCVAEEnsembleEnv,
    starts: torch.Tensor,
    policy: Callable[[torch.Tensor], torch.Tensor],
    steps: int,
    generator: torch.Generator,
) -> torch.Tensor:
    """The policy's actions along one imagined rollout per start (member 0), ``[B, T, A]``."""
    plan = model_env.imagine(
        starts, policy=policy, horizon=steps, samples_per_member=1, generator=generator
    )
    return plan["action"][0, 0]


def forecast_condition(
    model_env: RCVAEEnsembleEnv,
    policy: Callable[[torch.Tensor], torch.Tensor],
    starts: torch.Tensor,
    *,
    samples_per_member: int,
    horizon_s: float,
    dt: float,
    radius: float,
    open_loop: bool = False,
    episode_end: bool = True,
    bias_correction: str = "none",
    seed: int = 0,
) -> dict[str, torch.Tensor]:
    """Imagine ``[E, N, B, T]`` rollouts from ``starts [B, S]`` and measure them.

    Returns CPU tensors: ``aleatoric``/``epistemic``/``total`` bits ``[B, T, D]`` (histogram
    estimator at the Pusher's declared resolution; ``bias_correction`` as in
    :func:`~rcvae_torchrl.competency.decompose_uncertainty`), ``p_success`` ``[B]`` with its
    interval and per-member values ``[E, B]``, the outcome's entropy decomposition ``[B]``, the
    forecast success ``[E, N, B]`` and the ball-to-target distance of every sample ``[E·N, B, T]``.
    """
    steps = round(horizon_s / dt)
    generator = torch.Generator(device=starts.device).manual_seed(seed)
    if open_loop:
        actions = _open_loop_actions(model_env, starts, policy, steps, generator)
        td = model_env.imagine(
            starts, actions, samples_per_member=samples_per_member, generator=generator
        )
    else:
        td = model_env.imagine(
            starts,
            policy=policy,
            horizon=steps,
            samples_per_member=samples_per_member,
            generator=generator,
        )
    td = TensorDict({"observation": td["observation"]}, batch_size=td.batch_size).cpu()
    boundary = pusher_boundary(radius, horizon_s, dt)
    if episode_end:
        td["ended"] = boundary.ended_over_time(td["observation"])
    uncertainty = UncertaintyMetric(
        bin_width=resolution_tensor(),
        dim_names=OBSERVATION_NAMES,
        episode_end=episode_end,
        bias_correction=bias_correction,
        generator=torch.Generator().manual_seed(seed),
    )
    u = uncertainty(td)["uncertainty"]
    c = SuccessMetric(boundary)(td)["competency"]
    obs = td["observation"]
    return {
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
        "ball_to_target": ball_to_target(obs).flatten(0, 1),
    }
