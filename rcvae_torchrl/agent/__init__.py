"""The agent: an amortised policy and its distillation from the planner."""

from .distill import DistillConfig, distill_policy
from .loop import AgentConfig, AgentResult, run_model_based_agent
from .mpc import EpisodeStats, PlannerConfig, make_mpc_policy, run_episodes
from .policy import MLPPolicy, ResidualPolicy, make_policy_module

__all__ = [
    # amortised policy
    "MLPPolicy",
    "ResidualPolicy",
    "make_policy_module",
    # MPC agent
    "EpisodeStats",
    "PlannerConfig",
    "make_mpc_policy",
    "run_episodes",
    # model-based RL loop
    "AgentConfig",
    "AgentResult",
    "run_model_based_agent",
    # distillation
    "DistillConfig",
    "distill_policy",
]
