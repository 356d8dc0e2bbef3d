"""ParticleTransition / init_model_state: keys, layouts (TS-∞, TS-1), exactness, errors."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import step_mdp

from rcvae_torchrl.rollout import ParticleTransition, init_model_state, make_transition_module

NEXT_KEYS = [
    ("next", "observation"),
    ("next", "rcvae", "hidden"),
    ("next", "rcvae", "latent"),
    ("next", "member"),
]


def _state(ensemble, batch, ts="ts_inf", seed=0, member="round_robin"):
    g = torch.Generator().manual_seed(seed)
    td = init_model_state(
        ensemble, torch.randn(*batch, 5, generator=g), trajectory_sampling=ts, member=member
    )
    td["action"] = torch.rand(*batch, 2, generator=g)
    return td


@pytest.mark.parametrize("batch", [(), (6,), (3, 4)])
@pytest.mark.parametrize("ts", ["ts_inf", "ts1"])
def test_keys_and_shapes(ensemble, batch, ts):
    module = make_transition_module(ensemble, trajectory_sampling=ts)
    assert module.out_keys == NEXT_KEYS
    td = module(_state(ensemble, batch, ts))
    hid = (12,) if ts == "ts_inf" else (4, 12)
    assert td["next", "observation"].shape == (*batch, 5)
    assert td["next", "rcvae", "hidden"].shape == (*batch, *hid)
    assert td["next", "rcvae", "latent"].shape == (*batch, 3)
    assert td["next", "member"].shape == batch and td["next", "member"].dtype == torch.int64


def test_out_prefix_in_place_for_model_based_env(ensemble):
    """out_prefix=() overwrites the state keys, as ModelBasedEnvBase._step expects."""
    td = _state(ensemble, (6,))
    start = td["observation"].clone()
    module = make_transition_module(ensemble, out_prefix=())
    assert module.out_keys == ["observation", ("rcvae", "hidden"), ("rcvae", "latent"), "member"]
    out = module(td)
    assert "next" not in out.keys()
    assert not torch.equal(out["observation"], start)
    assert torch.equal(out["observation"][:, 3:], start[:, 3:])


def test_init_model_state_members(ensemble):
    td = init_model_state(ensemble, torch.zeros(2, 5, 5))
    assert torch.equal(td["member"].flatten(), torch.arange(10) % 4)
    assert (td["rcvae", "hidden"] == 0).all() and td["rcvae", "latent"].shape == (2, 5, 3)
    g = torch.Generator().manual_seed(0)
    rand = init_model_state(ensemble, torch.zeros(50, 5), member="random", generator=g)
    assert rand["member"].min() >= 0 and rand["member"].max() < 4
    given = init_model_state(ensemble, torch.zeros(3, 5), member=torch.tensor([3, 3, 1]))
    assert given["member"].tolist() == [3, 3, 1]


@pytest.mark.parametrize("member", [torch.tensor([3, 0, 3, 3, 1, 0, 3]), torch.arange(7) % 4])
def test_indexed_layout_equals_each_member_alone(ensemble, member):
    """Particle i evolves exactly as member[i] alone, with the same per-particle noise."""
    td = _state(ensemble, (7,), member=member)
    module = ParticleTransition(ensemble, generator=torch.Generator().manual_seed(9))
    out = module(td.clone())
    g = torch.Generator().manual_seed(9)
    noise_z, noise_s = torch.randn(7, 3, generator=g), torch.randn(7, 3, generator=g)
    for i, m in enumerate(member.tolist()):
        ref = ensemble.select_members([m]).step(
            td["rcvae", "hidden"][i][None, None],
            td["observation"][i][None, None],
            td["action"][i][None, None],
            noise_latent=noise_z[i][None, None],
            noise_obs=noise_s[i][None, None],
        )
        torch.testing.assert_close(out["next", "observation"][i], ref.observation[0, 0])
        torch.testing.assert_close(out["next", "rcvae", "hidden"][i], ref.hidden[0, 0])
    assert torch.equal(out["next", "member"], member)


def test_ts_inf_rollout_through_step_mdp_and_passthrough(ensemble):
    module = make_transition_module(ensemble, generator=torch.Generator().manual_seed(0))
    td = _state(ensemble, (8,))
    start = td["observation"].clone()
    for _ in range(5):
        td = step_mdp(module(td), keep_other=True)
        td["action"] = torch.rand(8, 2)
    assert torch.equal(td["observation"][:, 3:], start[:, 3:])
    assert torch.equal(td["member"], torch.arange(8) % 4)
    assert torch.isfinite(td["observation"]).all()


def test_ts1_redraws_members_and_samples_from_the_drawn_member(ensemble):
    module = make_transition_module(
        ensemble, trajectory_sampling="ts1", generator=torch.Generator().manual_seed(0)
    )
    td = _state(ensemble, (64,), ts="ts1")
    out = module(td.clone())
    member = out["next", "member"]
    assert len(member.unique()) == 4
    g = torch.Generator().manual_seed(0)
    torch.randint(4, (64,), generator=g)
    noise_z, noise_s = torch.randn(64, 3, generator=g), torch.randn(64, 3, generator=g)
    for i in (0, 17, 63):
        m = int(member[i])
        ref = ensemble.select_members([m]).step(
            td["rcvae", "hidden"][i, m][None, None],
            td["observation"][i][None, None],
            td["action"][i][None, None],
            noise_latent=noise_z[i][None, None],
            noise_obs=noise_s[i][None, None],
        )
        torch.testing.assert_close(out["next", "observation"][i], ref.observation[0, 0])
        torch.testing.assert_close(out["next", "rcvae", "hidden"][i, m], ref.hidden[0, 0])


@pytest.mark.parametrize("ts", ["ts_inf", "ts1"])
def test_determinism(ensemble, ts):
    def run(seed):
        module = make_transition_module(
            ensemble, trajectory_sampling=ts, generator=torch.Generator().manual_seed(seed)
        )
        return module(_state(ensemble, (10,), ts))["next", "observation"]

    assert torch.equal(run(0), run(0))
    assert not torch.equal(run(0), run(1))


def _corrupt(key, value):
    def apply(td):
        td[key] = value(td[key]) if callable(value) else value
        return td

    return apply


@pytest.mark.parametrize(
    ("corrupt", "error", "match"),
    [
        (
            _corrupt("observation", lambda x: x.index_fill(0, torch.tensor([1]), torch.nan)),
            ValueError,
            "observation: expected finite",
        ),
        (
            _corrupt("action", lambda x: x.index_fill(0, torch.tensor([0]), torch.inf)),
            ValueError,
            "action: expected finite",
        ),
        (_corrupt("member", lambda m: m + 4), ValueError, r"member: expected values in \[0, 4\)"),
        (_corrupt("member", lambda m: m.float()), TypeError, "member: expected an int64"),
        (_corrupt("action", lambda x: x.double()), TypeError, "action: expected dtype"),
    ],
)
def test_bad_values(ensemble, corrupt, error, match):
    with pytest.raises(error, match=match):
        make_transition_module(ensemble)(corrupt(_state(ensemble, (6,))))


def test_bad_shapes(ensemble):
    module = make_transition_module(ensemble)
    td = _state(ensemble, (6,))
    bad = td.exclude("action")
    bad["action"] = torch.zeros(6, 3)
    with pytest.raises(ValueError, match=r"action: expected shape \[\*B, A=2\], got \(6, 3\)"):
        module(bad)
    bad = td.exclude(("rcvae", "hidden"))
    bad["rcvae", "hidden"] = torch.zeros(6, 4, 12)  # a TS-1 state given to a TS-∞ module
    with pytest.raises(ValueError, match=r"hidden.*expected shape \[\*B, 12\]|expected batch"):
        module(bad)
    bad = td.exclude("member")
    with pytest.raises(KeyError, match="member"):
        module(bad)


def test_bad_trajectory_sampling(ensemble):
    with pytest.raises(ValueError, match="trajectory_sampling"):
        make_transition_module(ensemble, trajectory_sampling="ts2")
    with pytest.raises(ValueError, match="member: expected 'round_robin'"):
        init_model_state(ensemble, torch.zeros(5), member="first")
