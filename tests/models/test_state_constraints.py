"""Known state constraints: registered by name, applied to every generated state."""

import dataclasses

import pytest
import torch

from rcvae_torchrl.models import (
    RCVAEConfig,
    RCVAEEnsemble,
    get_state_constraint,
    register_state_constraint,
)


def _zero_first_dim(previous, state):
    return torch.cat([torch.zeros_like(state[..., :1]), state[..., 1:]], dim=-1)


def test_generated_states_obey_the_constraint():
    register_state_constraint("test_zero_first", _zero_first_dim)
    config = RCVAEConfig(3, 1, hidden_dim=8, mlp_dim=8, state_constraint="test_zero_first")
    model = RCVAEEnsemble(config, 2)
    out = model.generate(torch.ones(4, 3), torch.zeros(4, 5, 1), samples_per_member=3)
    assert torch.equal(out["observation"][..., 0], torch.zeros(2, 3, 4, 5))
    free = RCVAEEnsemble(dataclasses.replace(config, state_constraint=None), 2)
    free.load_state_dict(model.state_dict())
    assert (
        free.generate(torch.ones(4, 3), torch.zeros(4, 5, 1))["observation"][..., 0].abs().sum() > 0
    )


def test_unknown_constraint_is_a_clear_error():
    with pytest.raises(KeyError, match="no constraint registered as 'nope'"):
        get_state_constraint("nope")
    with pytest.raises(TypeError, match="constraint: expected a callable"):
        register_state_constraint("bad", 3)
    model = RCVAEEnsemble(RCVAEConfig(3, 1, hidden_dim=8, mlp_dim=8, state_constraint="nope"), 2)
    with pytest.raises(KeyError, match="state_constraint"):
        model.generate(torch.ones(3), torch.zeros(2, 1))
