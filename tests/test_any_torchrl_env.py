"""The whole API on an env the project did not write and that is unlike its own: TorchRL's
pure-torch ``PendulumEnv`` (scalar observations, a torque in [-2, 2], a stateless env that reads
its state back from the TensorDict and carries its constants), its episodes cut by a
``StepCounter``."""

from __future__ import annotations

import warnings

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.envs import PendulumEnv, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs

from rcvae_torchrl import CompetencyAssessor, SuccessBoundary, make_rcvae_env
from rcvae_torchrl.agent import real_outcomes, score_forecast
from rcvae_torchrl.data import (
    UniformRandomPolicy,
    action_bounds,
    collect_episodes,
    make_policy_module,
    prepare_env,
    split_episodes,
)
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.training import TrainConfig, train_ensemble

STEPS = 20  # the env's own time limit, and the task's


def _env():
    return prepare_env(TransformedEnv(PendulumEnv(), StepCounter(STEPS)), ["th", "thdot"])[0]


class _Upright(torch.nn.Module):
    """A PD torque towards the top, within the env's [-2, 2]."""

    def forward(self, observation):
        return (-5 * observation[..., :1] - observation[..., 1:]).clamp(-2, 2)


def _reset_to(env, start):
    """The pendulum takes a given state: ``reset(td, set_state=True)``."""
    td = TensorDict({"th": start[0], "thdot": start[1], **PendulumEnv.gen_params().to_dict()})
    return env.reset(td, set_state=True)


def _reward(observation, action):
    return -observation[..., :1].abs()


def _upright(observation):
    return observation[..., 0].abs() < 0.3


def test_the_pendulum_from_data_to_a_checked_forecast():
    torch.manual_seed(0)
    env = _env()
    check_env_specs(env)
    low, high = action_bounds(env)
    assert low.tolist() == [-2.0] and high.tolist() == [2.0]
    explore = make_policy_module(UniformRandomPolicy(1, hold=3, low=low, high=high))
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # the env's whole action range: no warning
        data = collect_episodes(_env, explore, 12, seed=0, frames_per_batch=STEPS, progress=False)
    assert data["observation"].shape == (12 * STEPS, 2) and data["action"].abs().max() > 1.5
    train, val = split_episodes(data, val_fraction=0.25, seed=0)
    config = RCVAEConfig(
        2, 1, hidden_dim=8, latent_dim=2, mlp_dim=8, observation_names=("th", "thdot")
    )
    model = RCVAEEnsemble(config, 2)
    budget = TrainConfig(max_steps=10, batch_windows=4, window=8, val_every=5, val_windows=4)
    train_ensemble(model, train, val, budget, progress=False, checks=False)

    model_env = make_rcvae_env(model, env, _reward, _upright, seed=0)
    check_env_specs(model_env)
    agent = TensorDictModule(_Upright(), in_keys=["observation"], out_keys=["action"])
    boundary = SuccessBoundary.within_distance(
        lambda observation: observation[..., 0].abs(), 0.3, time_limit=STEPS, dt=0.05
    )
    assessor = CompetencyAssessor(
        model_env, boundary, bin_width=torch.tensor([0.05, 0.2]), samples_per_member=4
    )
    starts = torch.tensor([[0.2, 0.0], [-1.0, 0.5], [2.5, 0.0], [0.1, -0.2]])
    report = assessor.assess(starts, policy=agent, seed=0)
    p = report.competency["p_success"]
    assert p.shape == (4,) and bool(((p >= 0) & (p <= 1)).all())
    # training fitted the novelty check: a start spinning 5x faster than the env lets it (its
    # max speed is 8 rad/s) is unlike every training state, and its paragraph says where
    far = assessor.assess(torch.tensor([[0.2, 40.0]]), policy=agent, seed=0)
    assert far.novel.tolist() == [True] and not bool(report.novel[0])
    assert "thdot = 40 (training " in far.summary(index=0)

    assert torch.allclose(_reset_to(env, starts[1])["observation"], starts[1])
    args = dict(runs_per_start=2, reset_to_state=_reset_to, success=boundary.success_over_time)
    real = real_outcomes(env, agent, starts, max_steps=STEPS, progress=False, **args)
    assert real.success.shape == (4, 2)
    assert real.success[0].all() and real.success[3].all()  # near the top: caught at once
    assert set(score_forecast(p, real)) >= {"auroc", "brier"}
    # the env's own StepCounter cuts a longer episode at the boundary's time limit, which has
    # decided it by then: known, and taken; judged by a bare predicate, which decides nothing
    # by a time, it is refused, not counted a failure
    longer = real_outcomes(env, agent, starts[2:3], max_steps=STEPS + 10, progress=False, **args)
    assert longer.success.shape == (1, 2)
    bare = {**args, "success": lambda observation: boundary.success_over_time(observation)}
    with pytest.raises(ValueError, match="cut short by the env itself"):
        real_outcomes(env, agent, starts[2:3], max_steps=STEPS + 10, progress=False, **bare)
