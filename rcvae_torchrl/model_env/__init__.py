"""The RCVAE ensemble as a TorchRL environment, with fast imagination and plan scoring.

:class:`RCVAEEnsembleEnv` is a ``ModelBasedEnvBase`` (``batch_size=()``, particles are batch
elements) that TorchRL's planners, transforms and rollouts use like any env; its fast paths
:meth:`~RCVAEEnsembleEnv.imagine` (rollouts ``[E, N, *B, T]`` for the competency metrics) and
:meth:`~RCVAEEnsembleEnv.evaluate_action_sequences` (the planner seam) step member-major tensors
directly. The math is in pure functions: particle propagation (TS-∞, TS-1, mean), task reward /
success / episode masks, and the scoring loop.
"""

from rcvae_torchrl.model_env.env import MemberAssignment, RCVAEEnsembleEnv
from rcvae_torchrl.model_env.factory import make_rcvae_env
from rcvae_torchrl.model_env.imagine import ImaginePolicy, as_tensor_policy, imagine_rollouts
from rcvae_torchrl.model_env.propagation import (
    PROPAGATIONS,
    MeanTransition,
    ParticleStep,
    Propagation,
    make_step_module,
    mean_step,
    ts1_step,
)
from rcvae_torchrl.model_env.scoring import (
    SequenceScores,
    particle_groups,
    score_action_sequences,
)
from rcvae_torchrl.model_env.specs import ModelEnvSpecs, model_env_specs
from rcvae_torchrl.model_env.task import (
    RewardFn,
    SuccessFn,
    alive_mask,
    task_reward,
    task_success,
)

__all__ = [
    # environment
    "MemberAssignment",
    "RCVAEEnsembleEnv",
    "make_rcvae_env",
    # fast paths
    "ImaginePolicy",
    "SequenceScores",
    "as_tensor_policy",
    "imagine_rollouts",
    "particle_groups",
    "score_action_sequences",
    # propagation (PETS trajectory sampling)
    "PROPAGATIONS",
    "MeanTransition",
    "ParticleStep",
    "Propagation",
    "make_step_module",
    "mean_step",
    "ts1_step",
    # task functions and specs
    "ModelEnvSpecs",
    "RewardFn",
    "SuccessFn",
    "alive_mask",
    "model_env_specs",
    "task_reward",
    "task_success",
]
