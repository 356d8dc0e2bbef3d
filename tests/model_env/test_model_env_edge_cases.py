"""Out-of-spec actions are clipped as the real env clips them, in every rollout path; missing
entries and empty inputs give named errors or defined results."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict


def _g() -> torch.Generator:
    return torch.Generator().manual_seed(0)


def _constant(value: float):
    return lambda obs: torch.full((*obs.shape[:-1], 2), value)


def test_the_real_env_clips_to_the_bounds_the_model_env_uses(make_env, real_env):
    env = make_env()
    spec = real_env.action_spec.space
    assert torch.equal(env.action_bounds.low, spec.low)
    assert torch.equal(env.action_bounds.high, spec.high)
    steps = []
    for action in (torch.full((2,), 7.0), spec.high.clone()):
        real_env.set_seed(1)
        steps.append(real_env.step(real_env.reset().set("action", action)))
    assert torch.equal(steps[0]["next", "observation"], steps[1]["next", "observation"])


@pytest.mark.parametrize("mode", ["ts_inf", "ts1", "mean"])
def test_step_clips_actions(make_env, starts, mode):
    env = make_env(trajectory_sampling=mode)
    outs = []
    for value in (5.0, 1.0):
        env.set_seed(0)
        td = env.reset(TensorDict({"observation": starts[:4]}, [4]))
        outs.append(env.step(td.set("action", torch.full((4, 2), value))))
    assert torch.equal(outs[0]["next", "observation"], outs[1]["next", "observation"])
    assert torch.equal(outs[0]["next", "reward"], outs[1]["next", "reward"])


def test_imagine_clips_open_and_closed_loop_actions(make_env, starts):
    env = make_env()
    s = starts[:3]
    over = env.imagine(s, torch.full((3, 4, 2), -5.0), generator=_g())
    edge = env.imagine(s, torch.full((3, 4, 2), -1.0), generator=_g())
    assert torch.equal(over["observation"], edge["observation"])
    assert over["action"].min() == -1.0
    closed = env.imagine(s, policy=_constant(9.0), horizon=4, generator=_g())
    closed_edge = env.imagine(s, policy=_constant(1.0), horizon=4, generator=_g())
    assert torch.equal(closed["observation"], closed_edge["observation"])
    assert torch.equal(closed["reward"], closed_edge["reward"])


def test_plans_and_scoring_clip_actions(make_env, starts):
    env = make_env()
    s = starts[:3]
    assert env.plan_actions(s, _constant(3.0), 4).max() == 1.0
    returns = []
    for value in (-7.0, -1.0):
        env.set_seed(0)
        td = TensorDict({"observation": s}, [3])
        returns.append(env.evaluate_action_sequences(td, torch.full((3, 2, 4, 2), value), 2))
    assert torch.equal(returns[0], returns[1])


def _td_policy(value: float):
    def policy(td):
        return td.set("action", torch.full((*td.batch_size, 2), value))

    return policy


def test_env_rollout_with_an_out_of_spec_policy_matches_the_clipped_one(make_env):
    env = make_env()
    runs = []
    for value in (4.0, 1.0):
        env.set_seed(0)
        runs.append(env.rollout(3, _td_policy(value)))
    assert torch.equal(runs[0]["next", "observation"], runs[1]["next", "observation"])


def test_step_without_an_action_names_it(make_env, starts):
    env = make_env()
    td = env.reset(TensorDict({"observation": starts[:3]}, [3]))
    with pytest.raises(KeyError, match=r"the input has no 'action' entry \(got keys"):
        env.step(td)


def test_empty_inputs(make_env, starts):
    env = make_env()
    with pytest.raises(ValueError, match=r"^observation: expected at least one start state"):
        env.imagine(starts[:0], horizon=3, policy=_constant(0.0))
    with pytest.raises(ValueError, match=r"^actions: expected shape .*T >= 1, got \(3, 0, 2\)"):
        env.imagine(starts[:3], torch.zeros(3, 0, 2))
    with pytest.raises(ValueError, match=r"^horizon: expected a positive integer, got 0"):
        env.imagine(starts[:3], horizon=0, policy=_constant(0.0))
    with pytest.raises(ValueError, match=r"^samples_per_member: expected a positive integer"):
        env.imagine(starts[:3], torch.zeros(3, 4, 2), samples_per_member=0)
    empty = env.reset(TensorDict({"observation": starts[:0]}, [0]))  # B = 0: a defined reset
    assert empty["observation"].shape == (0, 14)
    stepped = env.step(empty.set("action", torch.zeros(0, 2)))
    assert stepped["next", "observation"].shape == (0, 14)
