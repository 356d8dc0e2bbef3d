"""The RCVAE world model: config, vectorised ensemble, normalisation and TensorDict entry points."""

from rcvae_torchrl.models.config import RCVAEConfig
from rcvae_torchrl.models.constraints import (
    StateConstraint,
    get_state_constraint,
    register_state_constraint,
)
from rcvae_torchrl.models.ensemble_gru import EnsembleGRUCell, gru_update
from rcvae_torchrl.models.ensemble_layers import EnsembleLinear, EnsembleMLP
from rcvae_torchrl.models.features import (
    InputFeatures,
    get_input_features,
    register_input_features,
)
from rcvae_torchrl.models.functional import (
    gaussian_head,
    reparameterize,
    soft_clamp,
    standard_normal,
)
from rcvae_torchrl.models.generate import Policy, generate
from rcvae_torchrl.models.layout import MemberLayout
from rcvae_torchrl.models.normalizer import StateNormalizer, masked_mean_std
from rcvae_torchrl.models.rcvae import RCVAEEnsemble, SequenceOutput, StepOutput
from rcvae_torchrl.models.transition import (
    RCVAETransition,
    TrajectorySampling,
    init_model_state,
    make_transition_module,
)

__all__ = [
    # model
    "RCVAEConfig",
    "RCVAEEnsemble",
    "SequenceOutput",
    "StepOutput",
    # TensorDict entry points
    "Policy",
    "RCVAETransition",
    "TrajectorySampling",
    "generate",
    "init_model_state",
    "make_transition_module",
    # known state constraints
    "StateConstraint",
    "get_state_constraint",
    "register_state_constraint",
    # known input features
    "InputFeatures",
    "get_input_features",
    "register_input_features",
    # building blocks
    "EnsembleGRUCell",
    "EnsembleLinear",
    "EnsembleMLP",
    "MemberLayout",
    "StateNormalizer",
    # pure functions
    "gaussian_head",
    "gru_update",
    "masked_mean_std",
    "reparameterize",
    "soft_clamp",
    "standard_normal",
]
