"""Known functions of the state: passed explicitly, named in the config, applied or read."""

import dataclasses

import pytest
import torch

from rcvae_torchrl.models import InputFeatures, ModelFunctions, RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.rollout import imagine
from rcvae_torchrl.training import CheckpointError, load_ensemble, save_ensemble


def _norm_and_square(state):
    return torch.stack([state.norm(dim=-1), state[..., 0].square()], dim=-1)


def _zero_first_dim(previous, state):
    return torch.cat([torch.zeros_like(state[..., :1]), state[..., 1:]], dim=-1)


FUNCTIONS = ModelFunctions(
    state_constraints={"zero_first": _zero_first_dim},
    input_features={"norm_square": InputFeatures(_norm_and_square, 2)},
)


def _config(**kwargs):
    return RCVAEConfig(3, 1, hidden_dim=8, mlp_dim=8, **kwargs)


def test_features_widen_the_input_and_are_normalised_from_data():
    model = RCVAEEnsemble(_config(input_features="norm_square"), 2, functions=FUNCTIONS)
    plain = RCVAEEnsemble(_config(), 2)
    assert model.embed.weight.shape[1] == plain.embed.weight.shape[1] + 2
    obs = 3.0 + 2.0 * torch.randn(4, 50, 3)
    model.fit_normalizer(obs, torch.randn(4, 50, 1))
    feats = _norm_and_square(obs).reshape(-1, 2)
    torch.testing.assert_close(model.normalizer.feature_mean, feats.mean(0))
    torch.testing.assert_close(model.normalizer.feature_std, feats.std(0, correction=0))
    x = model.embed_inputs(obs[:, 0].expand(2, 4, 3), torch.zeros(2, 4, 1))
    assert x.shape == (2, 4, 8) and torch.isfinite(x).all()


def test_features_change_what_the_model_computes():
    torch.manual_seed(0)
    model = RCVAEEnsemble(_config(input_features="norm_square"), 2, functions=FUNCTIONS)
    model.fit_normalizer(torch.randn(4, 50, 3), torch.randn(4, 50, 1))
    obs, act = torch.randn(2, 5, 3), torch.zeros(2, 5, 1)
    before = model.embed_inputs(obs, act)
    with torch.no_grad():
        model.embed.weight[:, -2:].add_(1.0)  # the feature columns
    assert not torch.allclose(model.embed_inputs(obs, act), before)


def test_checkpoint_round_trip_needs_and_keeps_the_functions(tmp_path):
    config = _config(input_features="norm_square", state_constraint="zero_first")
    model = RCVAEEnsemble(config, 2, functions=FUNCTIONS)
    model.fit_normalizer(torch.randn(4, 50, 3), torch.randn(4, 50, 1))
    save_ensemble(model, tmp_path / "m.pt")
    with pytest.raises(CheckpointError, match=r"names 'zero_first'.*state_constraints"):
        load_ensemble(tmp_path / "m.pt")
    loaded = load_ensemble(tmp_path / "m.pt", functions=FUNCTIONS)
    assert loaded.config.input_features == "norm_square"
    torch.testing.assert_close(loaded.normalizer.feature_std, model.normalizer.feature_std)
    g1, g2 = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    a = imagine(model, torch.ones(3), torch.zeros(4, 1), generator=g1)["observation"]
    b = imagine(loaded, torch.ones(3), torch.zeros(4, 1), generator=g2)["observation"]
    torch.testing.assert_close(a, b)


def test_models_without_features_keep_their_state_dict_layout():
    keys = RCVAEEnsemble(_config(), 2).state_dict().keys()
    assert not any("feature" in k for k in keys)


def test_generated_states_obey_the_constraint():
    config = RCVAEConfig(3, 1, hidden_dim=8, mlp_dim=8, state_constraint="zero_first")
    model = RCVAEEnsemble(config, 2, functions=FUNCTIONS)
    out = imagine(model, torch.ones(4, 3), torch.zeros(4, 5, 1), samples_per_member=3)
    assert torch.equal(out["observation"][..., 0], torch.zeros(2, 3, 4, 5))
    free = RCVAEEnsemble(dataclasses.replace(config, state_constraint=None), 2)
    free.load_state_dict(model.state_dict())
    free_obs = imagine(free, torch.ones(4, 3), torch.zeros(4, 5, 1))["observation"]
    assert free_obs[..., 0].abs().sum() > 0


@pytest.mark.parametrize("horizon", [1, 5])
def test_a_constraint_returning_another_shape_or_dtype_is_named(horizon):
    """A constraint that drops a dimension (or casts) is refused at the first step it runs,
    naming it, where a one-step imagination would have returned the wrong shape."""
    bad = ModelFunctions(
        state_constraints={
            "drops": lambda previous, state: state[..., :2],
            "casts": lambda previous, state: state.double(),
        }
    )
    for name, got in (("drops", r"shape \(2, 4, 2\)"), ("casts", "dtype torch.float64")):
        config = _config(state_constraint=name)
        model = RCVAEEnsemble(config, 2, functions=bad)
        with pytest.raises(
            ValueError,
            match=rf"^state_constraint '{name}': expected the constrained state in the "
            rf"generated state's shape \(2, 4, 3\) and dtype torch.float32 .*, got .*{got}",
        ):
            imagine(model, torch.ones(4, 3), torch.zeros(4, horizon, 1))


def test_select_members_keeps_the_functions():
    config = RCVAEConfig(3, 1, hidden_dim=8, mlp_dim=8, state_constraint="zero_first")
    one = RCVAEEnsemble(config, 3, functions=FUNCTIONS).select_members([1])
    assert one.state_constraint is _zero_first_dim


def test_unknown_or_bad_functions_are_clear_errors():
    with pytest.raises(KeyError, match=r"input_features: the config names 'nope'.*known: \[\]"):
        RCVAEEnsemble(_config(input_features="nope"), 2)
    with pytest.raises(KeyError, match=r"state_constraint: the config names 'nope'.*zero_first"):
        RCVAEEnsemble(_config(state_constraint="nope"), 2, functions=FUNCTIONS)
    with pytest.raises(TypeError, match=r"state_constraints\['bad'\]: expected a callable"):
        ModelFunctions(state_constraints={"bad": 3})
    with pytest.raises(TypeError, match=r"input_features\['bad'\].fn: expected a callable"):
        ModelFunctions(input_features={"bad": (3, 2)})
    with pytest.raises(ValueError, match=r"input_features\['bad'\].dim: expected an int >= 1"):
        ModelFunctions(input_features={"bad": (_norm_and_square, 0)})
    with pytest.raises(TypeError, match=r"^functions: expected a ModelFunctions .*, got dict"):
        RCVAEEnsemble(_config(), 2, functions={"state_constraints": {}})
    model = RCVAEEnsemble(_config(input_features="norm_square"), 2, functions=FUNCTIONS)
    with pytest.raises(ValueError, match=r"features: expected \[\.\.\., F=2\]"):
        model.normalizer.fit(torch.randn(4, 50, 3))
