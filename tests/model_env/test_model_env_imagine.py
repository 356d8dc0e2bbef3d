"""imagine(): layout [E, N, *B, T], task entries, and equality with env.rollout under a seed."""

from __future__ import annotations

import pytest
import torch
from model_env_utils import E, Replay, at_target
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn

from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.model_env import make_rcvae_env

N, B, T = 2, 4, 5


def _member_major_start(starts):
    """The tensordict [E, N, B] that env.rollout steps like imagine's layout."""
    member = torch.arange(E)[:, None, None].expand(E, N, B)
    obs = starts[:B].expand(E, N, B, 14)
    return TensorDict({"observation": obs, "member": member}, batch_size=[E, N, B])


def test_layout_and_task_entries(make_env, starts):
    env = make_env()
    td = env.imagine(starts[:B], torch.rand(B, T, 2) * 2 - 1, samples_per_member=N)
    assert td.batch_size == (E, N, B, T)
    assert td["observation"].shape == (E, N, B, T, 14)
    assert td["reward"].shape == (E, N, B, T, 1)
    for key in ("success", "terminated", "truncated", "done"):
        assert td[key].shape == (E, N, B, T, 1) and td[key].dtype == torch.bool
    assert td["mask"].shape == (E, N, B, T)
    assert torch.equal(td["member"], torch.arange(E)[:, None, None, None].expand(E, N, B, T))
    torch.testing.assert_close(td["reward"], pusher_reward(td["observation"], td["action"]))
    assert torch.equal(td["success"].squeeze(-1), pusher_success(td["observation"]))
    assert {("rcvae", "loc"), ("rcvae", "scale"), ("rcvae", "latent")} <= set(td.keys(True, True))


def test_start_can_be_a_tensordict(make_env, starts):
    env = make_env()
    actions = torch.zeros(3, 2, 2)
    a = env.imagine(TensorDict({"observation": starts[:3]}, [3]), actions, generator=_g(1))
    b = env.imagine(starts[:3], actions, generator=_g(1))
    assert torch.equal(a["observation"], b["observation"])


def test_mask_and_done_after_success(make_env, starts):
    env = make_env()
    obs = torch.stack([at_target(starts[0]), starts[1]])
    td = env.imagine(obs, torch.zeros(2, T, 2), samples_per_member=3)
    done = td["done"].squeeze(-1)
    first = done.int().argmax(-1)
    steps = torch.arange(T)
    expected = torch.where(done.any(-1, keepdim=True), steps <= first.unsqueeze(-1), True)
    assert torch.equal(td["mask"], expected)
    horizon = torch.zeros_like(td["done"])
    horizon[..., -1, :] = True
    assert torch.equal(td["terminated"], td["success"])
    assert torch.equal(td["truncated"], horizon & ~td["success"])
    assert torch.equal(td["done"], td["success"] | horizon)
    free = make_env(terminate_on_success=False).imagine(obs, torch.zeros(2, T, 2))
    assert not free["terminated"].any() and free["mask"].all()
    assert torch.equal(free["done"], free["truncated"]) and free["truncated"][..., -1, :].all()


@pytest.mark.parametrize("terminate", [False, True])
def test_open_loop_imagine_equals_env_rollout_under_the_same_seed(
    ensemble, real_env, starts, terminate
):
    """Layout map: imagine[m, n, b, t] = env.rollout of the [E, N, B] tensordict whose member
    is m along dim 0 (member-major, as generate's rows), "next" entries at step t."""
    # a success that some particles reach within T steps; without start_states an auto-reset
    # draws no random numbers, so the particles still running keep their noise
    env = make_rcvae_env(
        ensemble,
        real_env,
        pusher_reward,
        lambda observation: observation[..., 8] > 0.3,
        terminate_on_success=terminate,
        seed=0,
    )
    actions = torch.rand(B, T, 2, generator=_g(2)) * 2 - 1
    env.set_seed(11)
    imagined = env.imagine(starts[:B], actions, samples_per_member=N, chunk_size=None)
    assert bool(imagined["terminated"].any()) == terminate
    assert bool(imagined["mask"].all()) != terminate
    env.set_seed(11)
    td = env.reset(_member_major_start(starts))
    rollout = env.rollout(
        T,
        Replay(actions.expand(E, N, B, T, 2)),
        tensordict=td,
        auto_reset=False,
        break_when_any_done=False,
    )
    mask = imagined["mask"]  # an auto-reset restarts a done particle: compare its episode only
    nxt = rollout["next"]
    assert torch.equal(imagined["observation"][mask], nxt["observation"][mask])
    assert torch.equal(imagined["reward"][mask], nxt["reward"][mask])
    assert torch.equal(imagined["success"][mask], nxt["success"][mask])
    assert torch.equal(imagined["terminated"][mask], nxt["terminated"][mask])
    # the model env has no clock: only imagine marks the horizon's last step as truncated
    assert torch.equal(
        imagined["done"][..., :-1, :][mask[..., :-1]], nxt["done"][..., :-1, :][mask[..., :-1]]
    )
    assert torch.equal(imagined["rcvae", "latent"][mask], nxt["rcvae", "latent"][mask])
    assert torch.equal(imagined["action"], rollout["action"])
    assert torch.equal(imagined["member"], rollout["member"])


def test_closed_loop_imagine_equals_env_rollout_with_a_module_policy(make_env, starts):
    torch.manual_seed(3)
    policy = TensorDictModule(
        nn.Sequential(nn.Linear(14, 2), nn.Tanh()), in_keys=["observation"], out_keys=["action"]
    )
    env = make_env(terminate_on_success=False)
    env.set_seed(5)
    with torch.no_grad():
        imagined = env.imagine(starts[:B], policy=policy, horizon=T, samples_per_member=N)
        env.set_seed(5)
        td = env.reset(_member_major_start(starts))
        rollout = env.rollout(T, policy, tensordict=td, auto_reset=False)
    torch.testing.assert_close(imagined["observation"], rollout["next", "observation"])
    torch.testing.assert_close(imagined["action"], rollout["action"])
    tensor_policy = env.imagine(
        starts[:B],
        policy=lambda s: policy.module(s),
        horizon=T,
        samples_per_member=N,
        generator=_g(0),
    )
    assert tensor_policy.batch_size == (E, N, B, T)


def test_imagine_is_deterministic_under_the_env_seed(make_env, starts):
    env = make_env()
    actions = torch.zeros(2, 3, 2)
    env.set_seed(1)
    a = env.imagine(starts[:2], actions, samples_per_member=3)
    env.set_seed(1)
    b = env.imagine(starts[:2], actions, samples_per_member=3)
    c = env.imagine(starts[:2], actions, samples_per_member=3)
    assert torch.equal(a["observation"], b["observation"])
    assert not torch.equal(b["observation"], c["observation"])


def test_chunked_imagine_keeps_the_layout(make_env, starts):
    env = make_env(terminate_on_success=False)
    actions = torch.zeros(B, T, 2)
    whole = env.imagine(starts[:B], actions, samples_per_member=N, chunk_size=None)
    chunked = env.imagine(starts[:B], actions, samples_per_member=N, chunk_size=3)
    assert chunked.batch_size == whole.batch_size == (E, N, B, T)
    # passthrough target dims are exact in both, whatever noise each chunk drew
    assert torch.equal(chunked["observation"][..., 12:], whole["observation"][..., 12:])


def test_imagine_errors(make_env, starts):
    env = make_env()
    with pytest.raises(ValueError, match="actions, policy: expected exactly one"):
        env.imagine(starts[:2])
    with pytest.raises(ValueError, match="actions"):
        env.imagine(starts[:2], torch.zeros(2, 3, 5))
    with pytest.raises(ValueError, match="horizon"):
        env.imagine(starts[:2], policy=lambda s: torch.zeros(*s.shape[:-1], 2), horizon=0)
    bad = starts[:2].clone()
    bad[0, 3] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        env.imagine(bad, torch.zeros(2, 3, 2))


def _g(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)
