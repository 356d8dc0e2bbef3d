"""The task on top of the model: functions called by keyword and checked, episode ends."""

from __future__ import annotations

import functools

import pytest
import torch

from rcvae_torchrl.model_env import RCVAEEnsembleEnv
from rcvae_torchrl.rollout import Task


def _success(observation):
    return observation[..., 0] > 0


def test_task_functions_are_called_by_keyword_whatever_their_order():
    def reward(action, observation):  # swapped order: the keywords decide
        return observation[..., :1] - action[..., :1]

    task = Task(reward, _success)
    obs, act = torch.ones(3, 2), torch.full((3, 1), 0.25)
    torch.testing.assert_close(task.reward(obs, act), torch.full((3, 1), 0.75))


@pytest.mark.parametrize(
    ("reward", "success", "match"),
    [
        (lambda s, a: s[..., :1], _success, r"reward_fn: expected a function called as reward_fn"),
        (lambda observation: observation, _success, r"reward_fn: .*missing \['action'\]"),
        (lambda observation, action, extra: 0, _success, r"no default for \['extra'\]"),
        (lambda observation, action: 0, lambda state: state, r"success_fn: expected a function"),
        (3, _success, "reward_fn: expected a callable"),
    ],
)
def test_misnamed_or_missing_arguments_are_refused_when_the_task_is_made(reward, success, match):
    with pytest.raises(TypeError, match=match):
        Task(reward, success)


def test_partials_defaults_and_keyword_arguments_are_accepted():
    def success(observation, radius=0.1):
        return observation[..., 0] < radius

    Task(lambda observation, action, **kwargs: observation, functools.partial(success, radius=1))
    Task(lambda *, observation, action: observation, success)


def test_float_success_is_not_cast_silently():
    task = Task(
        lambda observation, action: observation[..., :1], lambda observation: observation[..., 0]
    )
    with pytest.raises(
        TypeError, match=r"success_fn: expected a bool tensor, got dtype torch\.float32"
    ):
        task.success(torch.ones(2, 3))


def test_episode_ends_mirror_the_real_env(ensemble):
    assert (
        RCVAEEnsembleEnv(
            ensemble, lambda observation, action: observation[..., :1], _success
        ).terminate_on_success
        is False
    )
    task = Task(lambda observation, action: observation[..., :1], _success)
    out = task.transitions(
        torch.tensor([[[-1.0], [1.0], [-1.0]]]), torch.zeros(1, 3, 1), horizon_ends=True
    )
    assert out["success"].squeeze(-1).tolist() == [[False, True, False]]
    assert not out["terminated"].any()  # off unless asked for
    assert out["truncated"].squeeze(-1).tolist() == [[False, False, True]]  # the horizon
    ends = Task(task.reward_fn, _success, terminate_on_success=True).transitions(
        torch.tensor([[[-1.0], [1.0], [1.0]]]), torch.zeros(1, 3, 1), horizon_ends=True
    )
    assert ends["terminated"].squeeze(-1).tolist() == [[False, True, True]]
    assert ends["truncated"].squeeze(-1).tolist() == [[False, False, False]]
