"""Argument checks of the planner modules: the library's shared checks plus the CEM's own.

Every check raises ``ValueError`` (or ``TypeError``) whose message names the argument, what was
expected and what was given.
"""

from __future__ import annotations

from rcvae_torchrl._checks import (  # noqa: F401  (re-exported for the planner modules)
    check_bool,
    check_bounds,
    check_choice,
    check_finite,
    check_positive_int,
    check_shape,
    check_unit_interval,
)


def check_top_k(top_k: object, num_candidates: int) -> None:
    """Require ``1 <= top_k <= num_candidates``."""
    check_positive_int("top_k", top_k)
    if top_k > num_candidates:
        raise ValueError(
            f"top_k: expected at most num_candidates = {num_candidates} elites, got {top_k}"
        )


def check_momentum(momentum: object) -> None:
    """Require a number in [0, 1)."""
    if isinstance(momentum, bool) or not isinstance(momentum, (int, float)):
        raise TypeError(f"momentum: expected a float in [0, 1), got {momentum!r}")
    if not 0.0 <= momentum < 1.0:
        raise ValueError(f"momentum: expected a float in [0, 1), got {momentum!r}")
