"""Known input features: registered by name, normalised, read by the recurrence."""

import pytest
import torch

from rcvae_torchrl.models import (
    RCVAEConfig,
    RCVAEEnsemble,
    get_input_features,
    register_input_features,
)
from rcvae_torchrl.training import load_ensemble, save_ensemble


def _norm_and_square(state):
    return torch.stack([state.norm(dim=-1), state[..., 0].square()], dim=-1)


register_input_features("test_norm_square", _norm_and_square, 2)


def _config(**kwargs):
    return RCVAEConfig(3, 1, hidden_dim=8, mlp_dim=8, **kwargs)


def test_features_widen_the_input_and_are_normalised_from_data():
    model = RCVAEEnsemble(_config(input_features="test_norm_square"), 2)
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
    model = RCVAEEnsemble(_config(input_features="test_norm_square"), 2)
    model.fit_normalizer(torch.randn(4, 50, 3), torch.randn(4, 50, 1))
    obs, act = torch.randn(2, 5, 3), torch.zeros(2, 5, 1)
    before = model.embed_inputs(obs, act)
    with torch.no_grad():
        model.embed.weight[:, -2:].add_(1.0)  # the feature columns
    assert not torch.allclose(model.embed_inputs(obs, act), before)


def test_checkpoint_round_trip_keeps_features(tmp_path):
    model = RCVAEEnsemble(_config(input_features="test_norm_square"), 2)
    model.fit_normalizer(torch.randn(4, 50, 3), torch.randn(4, 50, 1))
    save_ensemble(model, tmp_path / "m.pt")
    loaded = load_ensemble(tmp_path / "m.pt")
    assert loaded.config.input_features == "test_norm_square"
    torch.testing.assert_close(loaded.normalizer.feature_std, model.normalizer.feature_std)
    g1, g2 = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    a = model.generate(torch.ones(3), torch.zeros(4, 1), generator=g1)["observation"]
    b = loaded.generate(torch.ones(3), torch.zeros(4, 1), generator=g2)["observation"]
    torch.testing.assert_close(a, b)


def test_models_without_features_keep_their_state_dict_layout():
    keys = RCVAEEnsemble(_config(), 2).state_dict().keys()
    assert not any("feature" in k for k in keys)


def test_bad_feature_registrations_and_names_are_clear_errors():
    with pytest.raises(KeyError, match="no feature function registered as 'nope'"):
        get_input_features("nope")
    with pytest.raises(KeyError, match="input_features"):
        RCVAEEnsemble(_config(input_features="nope"), 2)
    with pytest.raises(TypeError, match="fn: expected a callable"):
        register_input_features("bad", 3, 2)
    with pytest.raises(ValueError, match="dim: expected a positive int"):
        register_input_features("bad", _norm_and_square, 0)
    model = RCVAEEnsemble(_config(input_features="test_norm_square"), 2)
    with pytest.raises(ValueError, match=r"features: expected \[\.\.\., F=2\]"):
        model.normalizer.fit(torch.randn(4, 50, 3))
