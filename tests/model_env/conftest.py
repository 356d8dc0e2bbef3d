"""Fixtures for the model-env tests: a tiny untrained ensemble with a normaliser fitted on the
real Pusher, the real env, and a factory of model envs."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from model_env_utils import CONFIG, E

from rcvae_torchrl.envs import make_pusher_env, pusher_reward, pusher_success
from rcvae_torchrl.model_env import RCVAEEnsembleEnv, make_rcvae_env
from rcvae_torchrl.models import RCVAEEnsemble


@pytest.fixture(scope="session")
def pusher_data():
    """60 real Pusher transitions under a fixed random policy (normaliser and start states)."""
    env = make_pusher_env(seed=0)
    torch.manual_seed(0)
    return env.rollout(60, break_when_any_done=False)


@pytest.fixture(scope="session")
def real_env():
    return make_pusher_env(seed=1)


@pytest.fixture
def ensemble(pusher_data) -> RCVAEEnsemble:
    torch.manual_seed(0)
    model = RCVAEEnsemble(CONFIG, ensemble_size=E)
    model.fit_normalizer(
        pusher_data["observation"],
        pusher_data["action"],
        next_observations=pusher_data["next", "observation"],
    )
    return model


@pytest.fixture
def starts(pusher_data) -> torch.Tensor:
    """Real start observations ``[60, 14]``."""
    return pusher_data["observation"].clone()


@pytest.fixture
def make_env(ensemble, real_env, starts):
    """``make_env(**kwargs)``: a model env with the real env's specs, start states, seed 0."""

    def make(**kwargs) -> RCVAEEnsembleEnv:
        kwargs.setdefault("start_states", starts)
        kwargs.setdefault("seed", 0)
        kwargs.setdefault("terminate_on_success", True)  # as the real Pusher
        return make_rcvae_env(ensemble, real_env, pusher_reward, pusher_success, **kwargs)

    return make


@pytest.fixture
def still_ball_env(pusher_data, real_env):
    """``still_ball_env(**kwargs)``: a model whose ball and target never move (passthrough
    dims), so Pusher success is decided by the start state."""
    torch.manual_seed(0)
    model = RCVAEEnsemble(replace(CONFIG, passthrough_dims=(8, 9, 12, 13)), ensemble_size=E)
    model.fit_normalizer(
        pusher_data["observation"],
        pusher_data["action"],
        next_observations=pusher_data["next", "observation"],
    )

    def make(**kwargs):
        kwargs.setdefault("terminate_on_success", True)  # as the real Pusher
        return make_rcvae_env(model, real_env, pusher_reward, pusher_success, seed=0, **kwargs)

    return make
