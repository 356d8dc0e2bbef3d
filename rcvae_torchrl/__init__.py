"""rcvae_torchrl: competency assessment for model-based RL agents in TorchRL."""

__version__ = "0.1.0"

__all__ = ["__version__"]
