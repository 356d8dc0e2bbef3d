"""The RCVAE ensemble as a TorchRL environment.

:class:`RCVAEEnsembleEnv` is a ``ModelBasedEnvBase`` (``batch_size=()``, particles are batch
elements) that TorchRL's planners, transforms and rollouts use like any env; its fast paths
(:meth:`~RCVAEEnsembleEnv.imagine`, :meth:`~RCVAEEnsembleEnv.plan_actions`,
:meth:`~RCVAEEnsembleEnv.evaluate_action_sequences`) call the rollout engine
(:mod:`rcvae_torchrl.rollout`) directly.
"""

from rcvae_torchrl.model_env.env import MemberAssignment, RCVAEEnsembleEnv
from rcvae_torchrl.model_env.factory import make_rcvae_env
from rcvae_torchrl.model_env.specs import ModelEnvSpecs, model_env_specs

__all__ = [
    "MemberAssignment",
    "ModelEnvSpecs",
    "RCVAEEnsembleEnv",
    "make_rcvae_env",
    "model_env_specs",
]
