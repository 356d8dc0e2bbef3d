"""Objectives: the RCVAE sequence ELBO as a TorchRL LossModule, and its pure math."""

from rcvae_torchrl.objectives.functional import free_bits, gaussian_kl, gaussian_nll, masked_mean
from rcvae_torchrl.objectives.rcvae_loss import RCVAELoss

__all__ = [
    # loss modules
    "RCVAELoss",
    # pure functions
    "free_bits",
    "gaussian_kl",
    "gaussian_nll",
    "masked_mean",
]
