"""The agent: an amortised policy and its distillation from the planner."""

from .distill import DistillConfig, distill_policy
from .policy import MLPPolicy, make_policy_module

__all__ = [
    # amortised policy
    "MLPPolicy",
    "make_policy_module",
    # distillation
    "DistillConfig",
    "distill_policy",
]
