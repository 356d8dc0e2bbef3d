"""The rollout engine: every imagined step of the library is taken here.

- :mod:`~rcvae_torchrl.rollout.sampling`: trajectory sampling (TS-∞, TS-1, ensemble mean), one
  step of a batch of particles;
- :mod:`~rcvae_torchrl.rollout.loop`: the rollout loop, with a hook per step;
- :mod:`~rcvae_torchrl.rollout.task`: reward, success and episode ends of imagined transitions;
- thin callers: :func:`imagine` (rollouts ``[E, N, *B, T]`` for the competency metrics),
  :func:`plan_actions` (a policy's plan along one imagined rollout),
  :func:`evaluate_action_sequences` (returns of candidate plans: the planner's fast path) and
  :class:`ParticleTransition` (one step of a tensordict: the model env's ``step``);
- compiled scoring: :func:`compiled_scoring` (``torch.compile``, per process) and
  :mod:`~rcvae_torchrl.rollout.aot` (:func:`aot_scoring`: compiled ahead of time, cached
  across processes).
"""

from rcvae_torchrl.rollout.aot import (
    SCORING_CACHE_ENV,
    AOTCacheWarning,
    AOTLoadError,
    AOTScoring,
    aot_scoring,
    default_cache_dir,
    scoring_key,
)
from rcvae_torchrl.rollout.imagine import (
    ImaginePolicy,
    as_tensor_policy,
    chunk_size_for,
    imagine,
    plan_actions,
    policy_reset,
)
from rcvae_torchrl.rollout.layout import MemberLayout
from rcvae_torchrl.rollout.loop import (
    ActionBounds,
    Policy,
    RolloutHook,
    StepRecord,
    check_action_bounds,
    rollout,
)
from rcvae_torchrl.rollout.sampling import (
    TRAJECTORY_SAMPLINGS,
    Propagated,
    TrajectorySampling,
    draw_noise,
    initial_hidden,
    propagate,
)
from rcvae_torchrl.rollout.scoring import (
    COMPILE_MODES,
    Compile,
    SequenceReturns,
    check_compile,
    compiled_scoring,
    evaluate_action_sequences,
    particle_groups,
)
from rcvae_torchrl.rollout.task import RewardFn, SuccessFn, Task, alive_mask
from rcvae_torchrl.rollout.transition import (
    ParticleTransition,
    init_model_state,
    make_transition_module,
)

__all__ = [
    # trajectory sampling
    "TRAJECTORY_SAMPLINGS",
    "MemberLayout",
    "Propagated",
    "TrajectorySampling",
    "draw_noise",
    "initial_hidden",
    "propagate",
    # the loop
    "ActionBounds",
    "Policy",
    "RolloutHook",
    "StepRecord",
    "check_action_bounds",
    "rollout",
    # the task
    "RewardFn",
    "SuccessFn",
    "Task",
    "alive_mask",
    # callers
    "ImaginePolicy",
    "ParticleTransition",
    "SequenceReturns",
    "as_tensor_policy",
    "chunk_size_for",
    "evaluate_action_sequences",
    "imagine",
    "init_model_state",
    "make_transition_module",
    "particle_groups",
    "plan_actions",
    "policy_reset",
    # compiled scoring
    "AOTCacheWarning",
    "AOTLoadError",
    "AOTScoring",
    "COMPILE_MODES",
    "Compile",
    "SCORING_CACHE_ENV",
    "aot_scoring",
    "check_compile",
    "compiled_scoring",
    "default_cache_dir",
    "scoring_key",
]
