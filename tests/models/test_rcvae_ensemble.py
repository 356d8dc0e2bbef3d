"""RCVAEEnsemble: config checks, vectorisation exactness, passthrough, member independence."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.objectives import RCVAELoss, gaussian_nll
from rcvae_torchrl.rollout import imagine


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"obs_dim": 0, "action_dim": 1}, "obs_dim"),
        ({"obs_dim": 3, "action_dim": 1, "min_log_std": 1.0, "max_log_std": 0.0}, "min_log_std"),
        ({"obs_dim": 3, "action_dim": 1, "passthrough_dims": (3,)}, "passthrough_dims"),
        ({"obs_dim": 3, "action_dim": 1, "passthrough_dims": (1, 1)}, "duplicates"),
        ({"obs_dim": 2, "action_dim": 1, "passthrough_dims": (0, 1)}, "every state dimension"),
    ],
)
def test_config_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        RCVAEConfig(**kwargs)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"hidden_dim": True}, ValueError, "hidden_dim must be a positive int, got True"),
        ({"latent_min_std": float("nan")}, ValueError, "latent_min_std must be finite"),
        ({"max_log_std": float("inf")}, ValueError, "max_log_std must be finite"),
        ({"min_log_std": "a"}, TypeError, "min_log_std must be a number, got 'a'"),
        ({"passthrough_dims": (1.7,)}, TypeError, r"passthrough_dims must hold ints, got \(1.7,\)"),
        ({"passthrough_dims": "12"}, TypeError, "passthrough_dims must be a sequence of ints"),
        ({"observation_names": "abc"}, TypeError, "observation_names: expected a sequence of"),
        ({"observation_names": ("a", "a", "b")}, ValueError, r"expected distinct names .*\['a'\]"),
        ({"observation_names": ("a", "b")}, ValueError, "observation_names: expected 3 names"),
        ({"state_constraint": 3}, TypeError, r"state_constraint must be the name of a function"),
        ({"input_features": len}, TypeError, r"input_features must be the name of a function"),
    ],
)
def test_config_values_are_taken_as_given_or_refused(kwargs, error, match):
    """Nothing is coerced: 1.7 is not dimension 1, and 'abc' is not three names."""
    with pytest.raises(error, match=match):
        RCVAEConfig(3, 1, **kwargs)
    assert RCVAEConfig(3, 1, passthrough_dims=[2]).passthrough_dims == (2,)


def test_bad_ensemble_size(config):
    with pytest.raises(ValueError, match="ensemble_size"):
        RCVAEEnsemble(config, ensemble_size=0)


def _inputs(ensemble, batch=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    e, c = ensemble.ensemble_size, ensemble.config
    return (
        torch.randn(e, batch, c.hidden_dim, generator=g),
        torch.randn(e, batch, c.obs_dim, generator=g),
        torch.rand(e, batch, c.action_dim, generator=g),
        torch.randn(e, batch, c.latent_dim, generator=g),
        torch.randn(e, batch, c.predicted_dim, generator=g),
    )


def test_step_equals_each_member_alone(ensemble):
    hidden, obs, act, nz, ns = _inputs(ensemble)
    out = ensemble.step(hidden, obs, act, noise_latent=nz, noise_obs=ns)
    for e in range(ensemble.ensemble_size):
        single = ensemble.select_members([e])
        sl = slice(e, e + 1)
        ref = single.step(hidden[sl], obs[sl], act[sl], noise_latent=nz[sl], noise_obs=ns[sl])
        for got, want in zip(out, ref):
            torch.testing.assert_close(got[sl], want, rtol=1e-6, atol=1e-6)


def test_training_pass_distributions_equal_each_member_alone(ensemble):
    g = torch.Generator().manual_seed(3)
    obs = torch.randn(4, 3, 7, 5, generator=g)
    act = torch.rand(4, 3, 7, 2, generator=g)
    seq = ensemble(obs, act)
    assert seq.prior_mean.shape == (4, 3, 6, 3)
    assert seq.decoder_mean.shape == seq.target.shape == (4, 3, 6, 3)  # 2 of 5 dims pass through
    for e in range(4):
        ref = ensemble.select_members([e])(obs[e : e + 1], act[e : e + 1])
        for name in ("prior_mean", "prior_std", "posterior_mean", "posterior_std", "target"):
            torch.testing.assert_close(
                getattr(seq, name)[e : e + 1], getattr(ref, name), rtol=1e-6, atol=1e-6
            )


def test_passthrough_dims_are_copied_exactly(ensemble):
    hidden, obs, act, nz, ns = _inputs(ensemble)
    obs[..., 3:] = torch.tensor([0.123456789, -9.87654321])
    out = ensemble.step(hidden, obs, act, noise_latent=nz, noise_obs=ns * 100)
    assert torch.equal(out.observation[..., 3:], obs[..., 3:])
    assert not torch.equal(out.observation[..., :3], obs[..., :3])


def test_state_loc_scale_units(ensemble):
    hidden, obs, act, nz, ns = _inputs(ensemble)
    out = ensemble.step(hidden, obs, act, noise_latent=nz, noise_obs=ns)
    loc, scale = ensemble.state_loc_scale(obs, out.delta_mean, out.delta_std)
    assert torch.equal(scale[..., 3:], torch.zeros_like(scale[..., 3:]))
    rebuilt = loc[..., :3] + scale[..., :3] * ns  # s_t = loc + scale · ε on predicted dims
    torch.testing.assert_close(rebuilt, out.observation[..., :3], rtol=1e-5, atol=1e-5)


def _windows(seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        observation=torch.randn(4, 3, 6, 5, generator=g),
        action=torch.rand(4, 3, 6, 2, generator=g),
        batch_size=[4, 3, 6],
    )


def test_members_do_not_see_each_others_windows(ensemble):
    td = _windows()
    perturbed = td.clone()
    perturbed["observation"][1] += 1.0
    base = RCVAELoss(ensemble, generator=torch.Generator().manual_seed(5))(td)
    other = RCVAELoss(ensemble, generator=torch.Generator().manual_seed(5))(perturbed)
    keep = torch.tensor([0, 2, 3])
    torch.testing.assert_close(base["nll_per_member"][keep], other["nll_per_member"][keep])
    assert base["nll_per_member"][1] != other["nll_per_member"][1]


def test_member_gradients_do_not_mix(ensemble):
    td = _windows()
    seq = ensemble(td["observation"], td["action"], open_loop_steps=2)
    gaussian_nll(seq.target, seq.decoder_mean, seq.decoder_std)[0].sum().backward()
    for name, param in ensemble.named_parameters():
        assert param.grad[1:].abs().max() == 0, name
    assert any(p.grad[0].abs().max() > 0 for p in ensemble.parameters())


def test_select_members_and_state_dict_round_trip(ensemble):
    pair = ensemble.select_members([2, 0])
    assert pair.ensemble_size == 2
    torch.testing.assert_close(pair.embed.weight[0], ensemble.embed.weight[2])
    assert torch.equal(pair.normalizer.state_mean, ensemble.normalizer.state_mean)
    clone = RCVAEEnsemble(ensemble.config, ensemble.ensemble_size)
    clone.load_state_dict(ensemble.state_dict())
    assert clone.normalizer.fitted
    for (name, a), (_, b) in zip(ensemble.named_parameters(), clone.named_parameters()):
        assert torch.equal(a, b), name


def test_double_precision_model(ensemble):
    model = ensemble.double()
    assert model.dtype == torch.float64 and model.device.type == "cpu"
    assert model.select_members([1]).dtype == torch.float64
    td = imagine(model, torch.zeros(5, dtype=torch.float64), torch.zeros(3, 2).double())
    assert td["observation"].dtype == torch.float64


def test_members_are_initialised_differently(ensemble):
    weight = ensemble.decoder[0].weight
    assert not torch.equal(weight[0], weight[1])


def test_a_seed_draws_the_same_initial_weights_and_leaves_torchs_generator(config):
    """A trial trained twice with ``TrainConfig(seed=0)`` and got two models: that seed draws
    training's sampling and noise, not the weights the ensemble was built with."""
    before = torch.random.get_rng_state()
    a, b = (RCVAEEnsemble(config, 2, seed=3).state_dict() for _ in range(2))
    assert torch.equal(torch.random.get_rng_state(), before)  # left as it was
    other = RCVAEEnsemble(config, 2, seed=4).state_dict()
    for name, value in a.items():
        assert torch.equal(value, b[name]), name
    assert any(not torch.equal(value, other[name]) for name, value in a.items())
    torch.manual_seed(3)  # the same as seeding torch before building
    plain = RCVAEEnsemble(config, 2).state_dict()
    assert all(torch.equal(value, plain[name]) for name, value in a.items())
    before = torch.random.get_rng_state()  # nor does picking members draw from it
    RCVAEEnsemble(config, 3, seed=1).select_members([0, 2])
    assert torch.equal(torch.random.get_rng_state(), before)
    assert torch.equal(  # any integer type, up to torch's largest seed
        RCVAEEnsemble(config, 1, seed=np.int64(3)).embed.weight,
        RCVAEEnsemble(config, 1, seed=3).embed.weight,
    )
    RCVAEEnsemble(config, 1, seed=2**64 - 1)
    for bad in (-1, 1.5, True, 2**64):
        with pytest.raises(
            ValueError, match=r"^seed: expected an integer in \[0, 2\*\*64\) or None, got"
        ):
            RCVAEEnsemble(config, 2, seed=bad)
