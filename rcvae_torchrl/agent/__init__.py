"""The agent: MPC over the world model, its distillation into an amortised policy, episodes
(in this process or in worker processes)."""

from rcvae_torchrl.data import make_policy_module  # one wrapper: also the agent's

from .dagger import PerturbedPolicy, dagger, label_states
from .distill import DistillConfig, distill_policy
from .episodes import EpisodeStats, ResetToState, run_episodes, seed_episodes
from .loop import AgentConfig, AgentResult, AgentTask, run_model_based_agent
from .mpc import PlannerConfig, make_mpc_policy, policy_proposal
from .policy import (
    POLICY_FORMAT_VERSION,
    FixedRowsPolicy,
    MLPPolicy,
    ResidualPolicy,
    load_policy,
    save_policy,
)
from .starts import (
    MODEL_FIELDS,
    draw_starts,
    observe_starts,
    physics_of,
    reset_by_seed,
    reset_to_physics,
    start_episodes,
)
from .validation import RealOutcomes, real_outcomes, score_comparison, score_forecast
from .workers import EpisodeStartEnv, episode_workers, start_worker_episodes

__all__ = [
    # amortised policy
    "POLICY_FORMAT_VERSION",
    "FixedRowsPolicy",
    "MLPPolicy",
    "ResidualPolicy",
    "load_policy",
    "make_policy_module",
    "save_policy",
    # episodes in the real env
    "EpisodeStats",
    "ResetToState",
    "run_episodes",
    "seed_episodes",
    # start states in the real env
    "MODEL_FIELDS",
    "draw_starts",
    "observe_starts",
    "physics_of",
    "reset_by_seed",
    "reset_to_physics",
    "start_episodes",
    # real episodes in worker processes (TorchRL ParallelEnv)
    "EpisodeStartEnv",
    "episode_workers",
    "start_worker_episodes",
    # the real agent against a forecast
    "RealOutcomes",
    "real_outcomes",
    "score_comparison",
    "score_forecast",
    # MPC agent
    "PlannerConfig",
    "make_mpc_policy",
    "policy_proposal",
    # distillation
    "DistillConfig",
    "PerturbedPolicy",
    "dagger",
    "distill_policy",
    "label_states",
    # model-based RL loop
    "AgentConfig",
    "AgentResult",
    "AgentTask",
    "run_model_based_agent",
]
