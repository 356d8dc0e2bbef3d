"""Trajectory sampling (PETS TS-∞, TS-1) and the ensemble mean; determinism under a seed."""

from __future__ import annotations

import torch
from model_env_utils import E, Replay
from tensordict import TensorDict

from rcvae_torchrl.rollout import init_model_state, make_transition_module, propagate


def _rollout(env, starts, n=12, steps=6, seed=0):
    env.set_seed(seed)
    td = env.reset(TensorDict({"observation": starts[:n]}, batch_size=[n]))
    actions = torch.rand(n, steps, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
    return env.rollout(
        steps, Replay(actions), tensordict=td, auto_reset=False, break_when_any_done=False
    )


def test_ts_inf_keeps_each_particle_on_its_member(make_env, starts):
    td = _rollout(make_env(terminate_on_success=False), starts)
    member = torch.cat([td["member"], td["next", "member"][:, -1:]], dim=1)
    assert torch.equal(member, (torch.arange(12) % E)[:, None].expand(12, 7))


def test_ts1_redraws_members_every_step(make_env, starts):
    td = _rollout(make_env(trajectory_sampling="ts1", terminate_on_success=False), starts, 30)
    drawn = td["next", "member"]
    assert set(drawn.unique().tolist()) == set(range(E))
    assert (drawn[:, 1:] != drawn[:, :-1]).any(1).all()  # every particle switched at least once


def test_ts1_particle_samples_from_the_drawn_member(make_env, starts, ensemble):
    """propagate("ts1") (the fast paths' step) = the TensorDict module's TS-1 step, same
    generator state."""
    obs, action = starts[:8], torch.rand(8, 2) * 2 - 1
    hidden = torch.randn(8, E, 16)
    td = init_model_state(ensemble, obs, trajectory_sampling="ts1")
    td.update({"action": action, ("rcvae", "hidden"): hidden})
    module = make_transition_module(
        ensemble, trajectory_sampling="ts1", generator=torch.Generator().manual_seed(4)
    )
    ref = module(td)
    out = propagate(
        ensemble,
        "ts1",
        hidden.transpose(0, 1),
        obs,
        action,
        generator=torch.Generator().manual_seed(4),
    )
    assert torch.equal(out.member, ref["next", "member"])
    torch.testing.assert_close(out.observation, ref["next", "observation"])
    torch.testing.assert_close(out.hidden.transpose(0, 1), ref["next", "rcvae", "hidden"])


def test_mean_is_the_average_of_the_noise_free_member_predictions(ensemble, starts):
    obs, action = starts[:5], torch.rand(5, 2) * 2 - 1
    hidden = torch.randn(E, 5, 16)
    out = propagate(ensemble, "mean", hidden, obs, action)
    preds = []
    for m in range(E):
        single = ensemble.select_members([m])
        step = single.step(
            hidden[m : m + 1],
            obs[None],
            action[None],
            noise_latent=torch.zeros(1, 5, 4),
            noise_obs=torch.zeros(1, 5, 12),
        )
        preds.append(step.observation[0])
        torch.testing.assert_close(out.hidden[m], step.hidden[0])
    torch.testing.assert_close(out.observation, torch.stack(preds).mean(0))
    assert out.member is None


def test_mean_env_is_deterministic_and_particles_of_a_start_coincide(make_env, starts):
    env = make_env(trajectory_sampling="mean", terminate_on_success=False)
    obs = starts[:2].repeat(3, 1)
    actions = (torch.rand(2, 5, 2) * 2 - 1).repeat(3, 1, 1)
    a, b = (
        env.rollout(5, Replay(actions), tensordict=env.reset(TensorDict({"observation": obs}, [6])))
        for _ in range(2)
    )
    assert torch.equal(a["next", "observation"], b["next", "observation"])
    torch.testing.assert_close(a["next", "observation"][:2], a["next", "observation"][2:4])


def test_same_seed_same_rollout_other_seed_other_rollout(make_env, starts):
    for mode in ("ts_inf", "ts1"):
        env = make_env(trajectory_sampling=mode, member_assignment="random")
        a, b = _rollout(env, starts, seed=7), _rollout(env, starts, seed=7)
        c = _rollout(env, starts, seed=8)
        assert torch.equal(a["next", "observation"], b["next", "observation"])
        assert torch.equal(a["member"], b["member"])
        assert not torch.equal(a["next", "observation"], c["next", "observation"])
