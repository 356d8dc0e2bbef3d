"""The RCVAE world model: config, vectorised ensemble, normalisation, building blocks."""

from rcvae_torchrl.models.config import RCVAEConfig
from rcvae_torchrl.models.ensemble_gru import (
    EnsembleGRUCell,
    gru_scan,
    gru_scan_stepwise,
    gru_step,
    gru_update,
)
from rcvae_torchrl.models.ensemble_layers import (
    EnsembleLinear,
    EnsembleMLP,
    ensemble_linear,
    ensemble_mlp,
)
from rcvae_torchrl.models.functional import (
    gaussian_head,
    reparameterize,
    soft_clamp,
    standard_normal,
)
from rcvae_torchrl.models.functions import InputFeatures, ModelFunctions, StateConstraint
from rcvae_torchrl.models.normalizer import StateNormalizer, masked_mean_std
from rcvae_torchrl.models.rcvae import RCVAEEnsemble, SequenceOutput, StepOutput

__all__ = [
    # model
    "RCVAEConfig",
    "RCVAEEnsemble",
    "SequenceOutput",
    "StepOutput",
    # known functions of the state, passed explicitly
    "InputFeatures",
    "ModelFunctions",
    "StateConstraint",
    # building blocks
    "EnsembleGRUCell",
    "EnsembleLinear",
    "EnsembleMLP",
    "StateNormalizer",
    # pure functions
    "ensemble_linear",
    "ensemble_mlp",
    "gaussian_head",
    "gru_scan",
    "gru_scan_stepwise",
    "gru_step",
    "gru_update",
    "masked_mean_std",
    "reparameterize",
    "soft_clamp",
    "standard_normal",
]
