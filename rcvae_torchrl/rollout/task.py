"""The task on top of the world model: reward, success and episode ends of imagined steps.

The model predicts states only; reward and success are pure functions of the predicted state,
the same functions the real env's numbers can be checked against. They are called by keyword,
``reward_fn(observation=s_{t+1}, action=a_t)`` and ``success_fn(observation=s_{t+1})``, and
their signatures are checked when a :class:`Task` is made, so swapped or misnamed arguments are
an error instead of a silently wrong reward.

An imagined episode ends as the real one does: at success when ``terminate_on_success`` (most
envs never end at success, so it is off by default), and at the horizon (``truncated``). The
reward of the step that ends an episode counts, later ones do not.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass

import torch

__all__ = ["RewardFn", "SuccessFn", "Task", "alive_mask"]

RewardFn = Callable[..., torch.Tensor]
"""``reward_fn(observation=[..., S], action=[..., A]) -> [..., 1]`` (``[...]`` accepted)."""

SuccessFn = Callable[..., torch.Tensor]
"""``success_fn(observation=[..., S]) -> [...]`` bool (``[..., 1]`` accepted)."""


def _check_keywords(name: str, fn: object, keywords: tuple[str, ...]) -> None:
    """``fn`` must be callable with exactly these keywords (others must have defaults)."""
    if not callable(fn):
        raise TypeError(f"{name}: expected a callable, got {type(fn).__name__}")
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):  # builtins without a signature: trust the caller
        return
    params = signature.parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return
    missing = [k for k in keywords if k not in params or params[k].kind.name == "POSITIONAL_ONLY"]
    extra = [
        p.name
        for p in params.values()
        if p.name not in keywords
        and p.default is inspect.Parameter.empty
        and p.kind not in (inspect.Parameter.VAR_POSITIONAL,)
    ]
    if missing or extra:
        raise TypeError(
            f"{name}: expected a function called as "
            f"{name}({', '.join(f'{k}=...' for k in keywords)}), got the signature {signature}"
            + (f" (missing {missing})" if missing else "")
            + (f" (no default for {extra})" if extra else "")
            + "; name the parameters so, e.g. def "
            + f"{name}({', '.join(keywords)}): ..., or wrap the function"
        )


def _column(name: str, value: object, observation: torch.Tensor, expected: str) -> torch.Tensor:
    """A task function's output as ``[*B, 1]`` for observations ``[*B, S]``, or a clear error."""
    batch = observation.shape[:-1]
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name}: expected a tensor, got {type(value).__name__}")
    if value.shape == batch:
        value = value.unsqueeze(-1)
    if value.shape != (*batch, 1):
        raise ValueError(
            f"{name}: expected {expected} for observations {tuple(observation.shape)}, "
            f"got {tuple(value.shape)}"
        )
    return value


def alive_mask(done: torch.Tensor, time_dim: int = -1) -> torch.Tensor:
    """Steps that belong to the episode: no ``done`` strictly before them.

    Args:
        done: bool flags of each step, time on ``time_dim``.
        time_dim: the time dimension.

    Returns:
        bool, the shape of ``done``: True up to and including the first ``done``.

    Example:
        >>> alive_mask(torch.tensor([False, True, False, True]))
        tensor([ True,  True, False, False])
    """
    if done.dtype != torch.bool:  # a fraction would read as not done
        raise TypeError(f"done: expected bool flags, got dtype {done.dtype}")
    done = done.to(torch.int64)
    return (done.cumsum(time_dim) - done) == 0


@dataclass(frozen=True)
class Task:
    """Reward, success and episode ends of imagined transitions (see the module docstring).

    Args:
        reward_fn: ``reward_fn(observation=s_{t+1}, action=a_t) -> [..., 1]``.
        success_fn: ``success_fn(observation=s_{t+1}) -> [...]`` bool.
        terminate_on_success: success ends an episode (mirror the real env's setting).

    Example:
        >>> task = Task(lambda observation, action: -observation[..., :1],
        ...             lambda observation: observation[..., 0] > 1.0)
        >>> task.reward(torch.ones(4, 3), torch.zeros(4, 1)).shape
        torch.Size([4, 1])
    """

    reward_fn: RewardFn
    success_fn: SuccessFn
    terminate_on_success: bool = False

    def __post_init__(self) -> None:
        _check_keywords("reward_fn", self.reward_fn, ("observation", "action"))
        _check_keywords("success_fn", self.success_fn, ("observation",))
        if not isinstance(self.terminate_on_success, bool):
            raise TypeError(
                f"terminate_on_success: expected True or False, got {self.terminate_on_success!r}"
            )

    def check_batched(self, observation: torch.Tensor, action: torch.Tensor) -> None:
        """Call both functions once on a batch (``observation [B, S]``, ``action [B, A]``,
        B >= 2) and refuse outputs of another shape than the batch's: a function that reduces
        over the batch (``.any()``, ``.sum()``) gives one value, which an unbatched check
        cannot tell from a right one. Where a function raises on these states, nothing is
        judged here (its first step, on real states, will)."""
        try:
            reward = self.reward_fn(observation=observation, action=action)
            success = self.success_fn(observation=observation)
        except Exception:  # e.g. states it was not written for: judged at its first step
            return
        self.checked_reward(reward, observation)
        self.checked_success(success, observation)

    # ------------------------------------------------------------------ one step, any batch
    def reward(self, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """``reward_fn`` checked and shaped ``[*B, 1]`` (the observation's dtype)."""
        return self.checked_reward(
            self.reward_fn(observation=observation, action=action), observation
        )

    def success(self, observation: torch.Tensor) -> torch.Tensor:
        """``success_fn`` checked and shaped bool ``[*B, 1]``."""
        return self.checked_success(self.success_fn(observation=observation), observation)

    @staticmethod
    def checked_reward(reward: object, observation: torch.Tensor) -> torch.Tensor:
        """A reward function's output for ``observation [*B, S]`` as ``[*B, 1]``, checked."""
        expected = f"a reward of shape [*B, 1] = {(*observation.shape[:-1], 1)}"
        return _column("reward_fn", reward, observation, expected).to(observation.dtype)

    @staticmethod
    def checked_success(success: object, observation: torch.Tensor) -> torch.Tensor:
        """A success function's output for ``observation [*B, S]`` as bool ``[*B, 1]``."""
        if isinstance(success, torch.Tensor) and success.dtype != torch.bool:
            raise TypeError(
                f"success_fn: expected a bool tensor, got dtype {success.dtype} (compare with a "
                "threshold, e.g. distance <= radius)"
            )
        batch = tuple(observation.shape[:-1])
        expected = f"a flag of shape [*B] = {batch} or [*B, 1] = {(*batch, 1)}"
        return _column("success_fn", success, observation, expected)

    def terminated(self, success: torch.Tensor) -> torch.Tensor:
        """Success ends the episode when ``terminate_on_success``; else nothing does."""
        return success if self.terminate_on_success else torch.zeros_like(success)

    # ------------------------------------------------------------------ whole rollouts
    def transitions(
        self, observation: torch.Tensor, action: torch.Tensor, horizon_ends: bool = False
    ) -> dict[str, torch.Tensor]:
        """What ``env.step`` writes for transitions ``(a_t, s_{t+1})`` of any batch ``[*B]``.

        Returns ``"reward"`` ``[*B, 1]`` and bool ``[*B, 1]`` ``"success"``, ``"terminated"``,
        ``"truncated"``, ``"done"``. With ``horizon_ends`` the last axis of ``[*B]`` is time and
        its last step is ``truncated`` (the episode reached the horizon) unless it terminated.
        """
        success = self.success(observation)
        terminated = self.terminated(success)
        truncated = torch.zeros_like(terminated)
        if horizon_ends:
            truncated[..., -1, :] = ~terminated[..., -1, :]
        return {
            "reward": self.reward(observation, action),
            "success": success,
            "terminated": terminated,
            "truncated": truncated,
            "done": terminated | truncated,
        }

    def returns(self, reward: torch.Tensor, success: torch.Tensor) -> torch.Tensor:
        """Σ_t r_t of each particle up to and including its episode's end.

        Args:
            reward: ``[H, n]`` rewards in time order.
            success: bool ``[H, n]``.

        Returns:
            ``[n]``, summed in time order (as the rewards come, not pairwise).
        """
        if reward.ndim != 2 or success.shape != reward.shape or success.dtype != torch.bool:
            raise ValueError(
                f"reward, success: expected [H, n] rewards and bool [H, n] success flags, got "
                f"{tuple(reward.shape)} and {success.dtype} {tuple(success.shape)}"
            )
        if self.terminate_on_success:
            reward = reward.masked_fill(~alive_mask(success, time_dim=0), 0.0)
        total = reward.new_zeros(reward.shape[1:])
        for r in reward.unbind(0):
            total = total + r
        return total
