"""What the study knows about the Pusher: its conditions, its known functions, its task.

Everything Pusher-specific the pipeline uses is named here, on top of the Pusher domain
(:mod:`rcvae_torchrl.envs`) and the library's generic pieces.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import torch
from torchrl.envs import EnvBase

from rcvae_torchrl.agent import PlannerConfig, make_mpc_policy
from rcvae_torchrl.competency import SuccessBoundary
from rcvae_torchrl.envs import (
    CONTROL_TIMESTEP,
    DEFAULT_SUCCESS_RADIUS,
    OBSERVATION_DIM,
    OBSERVATION_NAMES,
    PUSHER_FEATURE_NAMES,
    make_pusher_env,
    obs_indices,
    pusher_input_features,
    pusher_reward,
    pusher_state_constraint,
    pusher_success,
)
from rcvae_torchrl.envs.scripted import ScriptedPusher
from rcvae_torchrl.models import InputFeatures, ModelFunctions, RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.planners import CEMPlanner
from rcvae_torchrl.rollout import Compile

from .config import DataConfig, ModelConfig

__all__ = [
    "CONDITIONS",
    "FIGURE_PANELS",
    "MODEL_FUNCTIONS",
    "WORLD_MODELS",
    "make_env",
    "make_planner",
    "rcvae_config",
    "success_boundary",
    "success_fn",
    "variant_randomness",
]

#: The known functions a Pusher model config may name (``"pusher"``).
MODEL_FUNCTIONS = ModelFunctions(
    state_constraints={"pusher": pusher_state_constraint},
    input_features={"pusher": InputFeatures(pusher_input_features, len(PUSHER_FEATURE_NAMES))},
)

#: The two world models, each trained on data of its Pusher variant.
WORLD_MODELS = ("deterministic", "stochastic")

#: condition -> (world model, real env variant), as in the paper's Table 1.
CONDITIONS: dict[str, tuple[str, str]] = {
    "deterministic": ("deterministic", "deterministic"),
    "stochastic": ("stochastic", "stochastic"),
    "out-of-distribution": ("deterministic", "ood"),
}

#: The paper's Figure 1 panels: arm position, elbow angle, ball velocity.
FIGURE_PANELS = {
    "arm position (fingertip x, y)": obs_indices("finger"),
    "elbow angle (wrist cos, sin)": obs_indices("wrist"),
    "ball velocity (x, y)": obs_indices("ball_vel"),
}


def rcvae_config(model: ModelConfig) -> RCVAEConfig:
    """One member's config: the Pusher's sizes, dimension names and control step, the target
    passed through."""
    return RCVAEConfig(
        OBSERVATION_DIM,
        2,
        hidden_dim=model.hidden_dim,
        mlp_dim=model.hidden_dim,
        latent_dim=model.latent_dim,
        passthrough_dims=tuple(obs_indices("target")),
        state_constraint=model.state_constraint,
        input_features=model.input_features,
        episode_latent_dim=model.episode_latent_dim,
        observation_names=OBSERVATION_NAMES,
        control_step=CONTROL_TIMESTEP,
    )


def variant_randomness(variant: str, data: DataConfig) -> dict[str, Any]:
    """The study's randomness of a Pusher variant, as env arguments: the stochastic variant's
    actuator strength range and action noise; nothing for the others."""
    if variant != "stochastic":
        return {}
    strength = data.stochastic_strength
    return {
        "action_noise_std": data.stochastic_noise_std,
        "actuator_strength": None if strength is None else tuple(strength),
    }


def make_env(variant: str, data: DataConfig, radius: float, **kwargs) -> EnvBase:
    """The real Pusher of a variant with the study's randomness and success radius."""
    return make_pusher_env(
        variant, success_radius=radius, **variant_randomness(variant, data), **kwargs
    )


def success_fn(radius: float) -> Callable[..., torch.Tensor]:
    """The task's success: the ball within ``radius`` of the target."""
    return functools.partial(pusher_success, radius=radius)


def success_boundary(radius: float, horizon_s: float) -> SuccessBoundary:
    """Success: the ball within ``radius`` of the target within ``horizon_s`` seconds."""
    return SuccessBoundary.ball(
        obs_indices("ball"),
        radius,
        target=obs_indices("target"),
        obs_dim=OBSERVATION_DIM,
        time_limit_s=horizon_s,
        dt=CONTROL_TIMESTEP,
    )


def make_planner(
    model: RCVAEEnsemble,
    env: EnvBase,
    config: PlannerConfig,
    *,
    radius: float = DEFAULT_SUCCESS_RADIUS,
    seed: int = 0,
    compile: Compile = False,
) -> CEMPlanner:
    """The study's MPC planner over ``model`` acting in ``env``: the Pusher's reward and
    success, success ends an episode, guided by the scripted pusher when
    ``config.policy_prior``; ``compile`` as :func:`~rcvae_torchrl.agent.make_mpc_policy`'s."""
    return make_mpc_policy(
        model,
        env,
        config,
        reward_fn=pusher_reward,
        success_fn=success_fn(radius),
        terminate_on_success=True,
        prior=ScriptedPusher() if config.policy_prior else None,
        seed=seed,
        compile=compile,
    )
