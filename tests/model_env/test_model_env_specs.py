"""RCVAEEnsembleEnv contract: TorchRL spec checks, keys, batch shapes and spec copying."""

from __future__ import annotations

import copy

import pytest
import torch
from model_env_utils import CONFIG, E
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.model_env import RCVAEEnsembleEnv

MODES = ["ts_inf", "ts1", "mean"]


@pytest.mark.parametrize("mode", MODES)
def test_check_env_specs_with_real_env_specs(make_env, mode):
    check_env_specs(make_env(trajectory_sampling=mode), seed=0)


def test_check_env_specs_with_default_specs(ensemble, starts):
    env = RCVAEEnsembleEnv(ensemble, pusher_reward, pusher_success, start_states=starts, seed=0)
    check_env_specs(env, seed=0)
    assert (env.action_spec.space.low == -1).all() and (env.action_spec.space.high == 1).all()


def test_specs_copied_from_the_real_env(make_env, real_env):
    env = make_env()
    assert env.batch_size == () and not env.batch_locked
    assert env.action_spec == real_env.action_spec
    assert env.reward_spec == real_env.reward_spec
    assert env.done_keys == real_env.done_keys
    for key in real_env.done_keys:
        assert env.full_done_spec[key] == real_env.full_done_spec[key]
    assert env.observation_spec["observation"] == real_env.observation_spec["observation"]
    assert env.observation_spec["success"] == real_env.observation_spec["success"]
    assert set(env.observation_spec.keys(True, True)) == {
        "observation",
        "success",
        ("rcvae", "hidden"),
        ("rcvae", "latent"),
        "member",
    }
    assert set(env.state_spec.keys(True, True)) == {
        "observation",
        ("rcvae", "hidden"),
        ("rcvae", "latent"),
        "member",
    }
    assert env.state_spec["member"].dtype == torch.int64


@pytest.mark.parametrize(
    ("mode", "hidden", "has_member"),
    [("ts_inf", (16,), True), ("ts1", (E, 16), True), ("mean", (E, 16), False)],
)
def test_model_state_layout_per_mode(make_env, mode, hidden, has_member):
    env = make_env(trajectory_sampling=mode, terminate_on_success=False)
    assert env.state_spec["rcvae", "hidden"].shape == hidden
    assert ("member" in env.state_spec.keys()) == has_member
    td = env.rollout(3, tensordict=env.reset(TensorDict(batch_size=[5])), auto_reset=False)
    assert td["next", "rcvae", "hidden"].shape == (5, 3, *hidden)
    assert ("member" in td.keys()) == has_member


@pytest.mark.parametrize("batch", [(), (4,), (2, 3)])
@pytest.mark.parametrize("mode", MODES)
def test_any_leading_batch(make_env, starts, batch, mode):
    env = make_env(trajectory_sampling=mode, terminate_on_success=False)
    n = torch.Size(batch).numel()
    start = TensorDict({"observation": starts[:n].reshape(*batch, 14)}, batch_size=batch)
    td = env.rollout(4, tensordict=env.reset(start), auto_reset=False)
    assert td.batch_size == (*batch, 4)
    assert td["next", "observation"].shape == (*batch, 4, 14)
    assert td["next", "reward"].shape == (*batch, 4, 1)
    for key in ("success", "done", "terminated", "truncated"):
        assert td["next", key].shape == (*batch, 4, 1) and td["next", key].dtype == torch.bool
    assert torch.equal(td["observation"][..., 0, :], start["observation"])
    # passthrough dims (the target) are copied exactly
    assert torch.equal(td["next", "observation"][..., 12:], td["observation"][..., 12:])
    assert not td["next", "truncated"].any()


def test_reward_and_success_are_the_task_functions(make_env, starts):
    env = make_env(terminate_on_success=False)
    td = env.rollout(5, tensordict=env.reset(TensorDict({"observation": starts[:6]}, [6])))
    nxt = td["next"]
    torch.testing.assert_close(nxt["reward"], pusher_reward(nxt["observation"], td["action"]))
    assert torch.equal(nxt["success"].squeeze(-1), pusher_success(nxt["observation"]))


def test_real_env_with_other_dims_is_refused(pusher_data, real_env):
    from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble

    small = RCVAEEnsemble(RCVAEConfig(10, 2, hidden_dim=8, mlp_dim=8), ensemble_size=2)
    with pytest.raises(ValueError, match="'observation' spec: expected shape \\(10,\\)"):
        RCVAEEnsembleEnv(small, pusher_reward, pusher_success, real_env=real_env)
    assert CONFIG.obs_dim == 14


@pytest.mark.parametrize("discrete", ["OneHot", "Categorical"])
def test_a_discrete_action_space_is_refused(discrete):
    import torchrl.data
    from torchrl.envs import EnvBase

    from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble

    class Discrete(EnvBase):  # the specs are all that is read
        def __init__(self):
            super().__init__()
            self.observation_spec = torchrl.data.Composite(observation=torchrl.data.Unbounded((3,)))
            self.action_spec = getattr(torchrl.data, discrete)(4)
            self.reward_spec = torchrl.data.Unbounded((1,))

        def _reset(self, tensordict):
            raise NotImplementedError

        def _step(self, tensordict):
            raise NotImplementedError

        def _set_seed(self, seed):
            pass

    model = RCVAEEnsemble(RCVAEConfig(3, 4, hidden_dim=8, mlp_dim=8), ensemble_size=2)
    with pytest.raises(TypeError, match=rf"'action' spec is {discrete} of dtype .* continuous"):
        RCVAEEnsembleEnv(model, pusher_reward, pusher_success, real_env=Discrete())


@pytest.mark.parametrize("mode", MODES)
def test_episode_latent_rides_in_the_hidden_state(pusher_data, real_env, starts, mode):
    """With an episode latent the model state carries it after h: the specs say so, a reset
    draws one per episode (its prior mean for ``"mean"``) and steps keep it."""
    from dataclasses import replace

    from rcvae_torchrl.model_env import make_rcvae_env
    from rcvae_torchrl.models import RCVAEEnsemble

    torch.manual_seed(0)
    model = RCVAEEnsemble(replace(CONFIG, episode_latent_dim=2), ensemble_size=E)
    model.fit_normalizer(pusher_data["observation"], pusher_data["action"])
    env = make_rcvae_env(
        model,
        real_env,
        pusher_reward,
        pusher_success,
        start_states=starts,
        seed=0,
        trajectory_sampling=mode,
        terminate_on_success=False,
    )
    check_env_specs(env, seed=0)
    width = CONFIG.hidden_dim + 2
    assert env.state_spec["rcvae", "hidden"].shape[-1] == width
    td = env.rollout(4, tensordict=env.reset(TensorDict(batch_size=[6])), auto_reset=False)
    episode = td["rcvae", "hidden"][..., CONFIG.hidden_dim :]  # [6, T, (E,) 2]
    assert torch.equal(episode, episode[:, :1].expand_as(episode))
    if mode == "mean":
        assert torch.allclose(episode[:, 0], episode[:1, 0].expand_as(episode[:, 0]))
    else:
        assert not torch.allclose(episode[0, 0], episode[1, 0])


def test_a_float64_model_without_a_real_env_gets_float64_specs(ensemble, starts):
    """The default specs take the model's dtype: a float64 ensemble's env passes TorchRL's
    spec check (its random actions were float32, refused by its own step)."""
    from rcvae_torchrl.model_env import make_rcvae_env

    model = copy.deepcopy(ensemble).double()
    env = make_rcvae_env(
        model, None, pusher_reward, pusher_success, start_states=starts.double(), seed=0
    )
    specs = (env.observation_spec["observation"], env.action_spec, env.reward_spec)
    assert [s.dtype for s in specs] == [torch.float64] * 3
    assert env.observation_spec["rcvae", "hidden"].dtype == torch.float64
    check_env_specs(env)


def test_check_env_specs_with_a_real_env_that_never_truncates():
    # TorchRL's PendulumEnv declares done and terminated alone; the model env marks an imagined
    # horizon's last step truncated all the same, so its spec must declare it
    from torchrl.envs import PendulumEnv

    from rcvae_torchrl.data import prepare_env
    from rcvae_torchrl.model_env import make_rcvae_env
    from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble

    real, _ = prepare_env(PendulumEnv(), ["th", "thdot"])
    assert "truncated" not in real.full_done_spec.keys()
    ensemble = RCVAEEnsemble(RCVAEConfig(2, 1, hidden_dim=8, mlp_dim=8), ensemble_size=2)
    env = make_rcvae_env(
        ensemble,
        real,
        lambda observation, action: observation[..., :1],
        lambda observation: observation[..., 0] > 3.0,
    )
    check_env_specs(env, seed=0)
    assert env.full_done_spec["truncated"] == env.full_done_spec["done"]
    assert env.full_done_spec["done"] == real.full_done_spec["done"]
