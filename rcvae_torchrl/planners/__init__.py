"""CEM model-predictive control for TorchRL envs, learned world models included.

The planner (:class:`CEMPlanner`, a TorchRL ``MPCPlannerBase``) wraps pure functions: the CEM
update (:mod:`~rcvae_torchrl.planners.functional`), the particle reductions behind its risk-aware
objectives (:mod:`~rcvae_torchrl.planners.reductions`) and the seam through which it scores action
sequences in an env (:mod:`~rcvae_torchrl.planners.evaluation`).
"""

from rcvae_torchrl.planners.cem import CEMPlanner, make_cem_planner
from rcvae_torchrl.planners.evaluation import (
    ActionSequenceEvaluator,
    ParticleReturns,
    SuccessAwareEvaluator,
    env_returns,
    has_fast_path,
    rollout_returns,
    supports_success,
)
from rcvae_torchrl.planners.functional import (
    action_prior,
    cem_update,
    elite_mask,
    sample_candidates,
    shift_plan,
)
from rcvae_torchrl.planners.reductions import (
    OBJECTIVES,
    cvar_return,
    expected_return,
    lexicographic_score,
    quantile_return,
    reduce_particles,
    success_fraction,
)

__all__ = [
    # planner
    "CEMPlanner",
    "make_cem_planner",
    # scoring action sequences in an env (the model seam)
    "ActionSequenceEvaluator",
    "ParticleReturns",
    "SuccessAwareEvaluator",
    "env_returns",
    "has_fast_path",
    "rollout_returns",
    "supports_success",
    # CEM math
    "action_prior",
    "cem_update",
    "elite_mask",
    "sample_candidates",
    "shift_plan",
    # objectives over particles
    "OBJECTIVES",
    "cvar_return",
    "expected_return",
    "lexicographic_score",
    "quantile_return",
    "reduce_particles",
    "success_fraction",
]
