"""Reset semantics: start states from the input or from start_states, partial resets, members."""

from __future__ import annotations

import warnings

import pytest
import torch
from model_env_utils import at_target
from tensordict import TensorDict
from torchrl.envs import StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs

from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.model_env import RCVAEEnsembleEnv, make_rcvae_env


def test_reset_takes_the_input_observations_and_returns_a_new_tensordict(make_env, starts):
    env = make_env()
    td_in = TensorDict({"observation": starts[:5]}, batch_size=[5])
    td = env._reset(td_in)
    assert td is not td_in
    assert torch.equal(td["observation"], starts[:5])
    assert td["observation"].data_ptr() != starts.data_ptr()
    assert (td["rcvae", "hidden"] == 0).all() and (td["rcvae", "latent"] == 0).all()
    assert td["member"].tolist() == [0, 1, 2, 0, 1]
    assert not td["done"].any() and not td["terminated"].any() and not td["truncated"].any()


def test_reset_reports_success_of_the_start_state_without_done(make_env, starts):
    env = make_env()
    obs = torch.stack([starts[0], at_target(starts[1])])
    td = env.reset(TensorDict({"observation": obs}, batch_size=[2]))
    assert td["success"].squeeze(-1).tolist() == [False, True]
    assert not td["done"].any()


def test_reset_honours_given_members_and_random_assignment(make_env, starts):
    env = make_env()
    given = torch.tensor([2, 2, 0, 1])
    td = env.reset(TensorDict({"observation": starts[:4], "member": given}, batch_size=[4]))
    assert torch.equal(td["member"], given)
    rand = make_env(member_assignment="random").reset(TensorDict(batch_size=[200]))
    assert set(rand["member"].unique().tolist()) == {0, 1, 2}
    assert not torch.equal(rand["member"], torch.arange(200) % 3)


def test_reset_without_observation_samples_start_states_under_the_seed(make_env, starts):
    a = make_env(seed=3).reset(TensorDict(batch_size=[2, 4]))
    b = make_env(seed=3).reset(TensorDict(batch_size=[2, 4]))
    assert a["observation"].shape == (2, 4, 14)
    assert torch.equal(a["observation"], b["observation"])
    rows = (a["observation"].reshape(-1, 1, 14) == starts[None]).all(-1).any(-1)
    assert rows.all()
    assert make_env().reset()["observation"].shape == (14,)


def test_partial_reset_with_only_reset_key(make_env, starts):
    env = make_env()
    td = env.rollout(
        3,
        tensordict=env.reset(TensorDict({"observation": starts[:4]}, [4])),
        auto_reset=False,
        break_when_any_done=False,
    )[..., -1]["next"].clone()
    mask = torch.tensor([True, False, True, False])
    only_reset = TensorDict({"_reset": mask.unsqueeze(-1)}, batch_size=[4])
    env.set_seed(5)
    fresh = env._reset(only_reset)
    assert fresh is not only_reset and fresh.batch_size == (4,)
    assert "_reset" not in fresh.keys()
    # the same partial reset as TorchRL runs it inside rollouts (input stripped to "_reset")
    td.set("done", mask.unsqueeze(-1))
    env.set_seed(5)
    out = env.maybe_reset(td.clone())
    assert torch.equal(out["observation"][mask], fresh["observation"][mask])
    assert (out["observation"][mask].unsqueeze(1) == starts).all(-1).any(-1).all()
    assert (out["rcvae", "hidden"][mask] == 0).all()
    kept = ~mask
    assert torch.equal(out["observation"][kept], td["observation"][kept])
    assert torch.equal(out["rcvae", "hidden"][kept], td["rcvae", "hidden"][kept])
    assert not out["done"].any()


def test_reset_without_any_start_state_is_a_clear_error(ensemble):
    env = RCVAEEnsembleEnv(ensemble, pusher_reward, pusher_success)
    with pytest.raises(ValueError, match="no start observations"):
        env.reset()
    with pytest.raises(ValueError, match="no start observations"):
        env._reset(TensorDict({"_reset": torch.ones(3, 1, dtype=torch.bool)}, batch_size=[3]))


def test_reset_without_start_states_draws_them_from_the_real_env(ensemble, real_env):
    """With a real env and no start states, reset() starts from real_env.reset(), so the model
    env passes TorchRL's spec check out of the box."""
    env = make_rcvae_env(ensemble, real_env, pusher_reward, pusher_success, seed=0)
    check_env_specs(env)
    real_env.set_seed(3)
    expected = torch.stack([real_env.reset()["observation"] for _ in range(2)])
    real_env.set_seed(3)
    td = env.reset(TensorDict(batch_size=[2]))
    assert torch.equal(td["observation"], expected)


def test_auto_reset_without_start_states_restarts_from_the_last_observation(make_env, starts):
    """After an imagined success inside a rollout, the done particle restarts where it was."""
    env = make_env(start_states=None)
    td = env.reset(TensorDict({"observation": starts[:2]}, batch_size=[2]))
    td["rcvae", "hidden"] = torch.ones(2, 16)
    td["done"] = torch.tensor([[False], [True]])
    out = env.maybe_reset(td.clone())
    assert torch.equal(out["observation"], td["observation"])
    assert (out["rcvae", "hidden"][0] == 1).all() and (out["rcvae", "hidden"][1] == 0).all()
    assert not out["done"].any()


def test_rollout_with_auto_resets_from_start_states(make_env, starts):
    env = make_env()
    obs = at_target(starts[:6])
    td = env.rollout(
        4,
        tensordict=env.reset(TensorDict({"observation": obs}, [6])),
        auto_reset=False,
        break_when_any_done=False,
    )
    assert td.batch_size == (6, 4) and torch.isfinite(td["next", "observation"]).all()


def test_reset_through_a_transformed_env_takes_the_observation(make_env, starts):
    env = TransformedEnv(make_env(), StepCounter(10))
    td = env.reset(TensorDict({"observation": starts[:3]}, batch_size=[3]))
    assert torch.equal(td["observation"], starts[:3])
    assert (td["step_count"] == 0).all()


def test_an_auto_reset_through_a_transform_that_resets_the_real_env_says_so_once(
    ensemble, real_env, starts
):
    """TorchRL's reset through a transform hands the model env only '_reset', not the done
    particles' last observations: with neither start states nor their observations, new ones
    come from resetting the real env, which ends the episode an agent may be acting in."""
    from torchrl.envs import RewardScaling

    env = TransformedEnv(
        make_rcvae_env(
            ensemble, real_env, pusher_reward, pusher_success, seed=0, terminate_on_success=True
        ),
        RewardScaling(0.0, 1.0),
    )
    td = env.reset(TensorDict({"observation": starts[:3]}, batch_size=[3]))
    td["done"] = torch.tensor([[False], [True], [False]])
    with pytest.warns(UserWarning, match=r"resets real_env to draw new start states; if an agent"):
        env.maybe_reset(td.clone())
    with warnings.catch_warnings():  # said once per model env
        warnings.simplefilter("error")
        env.maybe_reset(td.clone())
    # with start states the real env is not touched, and nothing is said
    quiet = TransformedEnv(
        make_rcvae_env(ensemble, real_env, pusher_reward, pusher_success, start_states=starts),
        RewardScaling(0.0, 1.0),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet.maybe_reset(td.clone())
