"""A lean ``DMControlWrapper`` for the Pusher: float32 throughout, no per-step spec encoding.

The task already emits float32 observations of the declared shapes, so the wrapper hands them to
TorchRL as tensors without re-encoding each one through its spec, and emits a float32 reward.
That removes the ``DoubleToFloat`` pass and about a third of the per-step overhead.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torchrl.data import Bounded, Unbounded
from torchrl.envs import DMControlWrapper

__all__ = ["PusherWrapper"]


class PusherWrapper(DMControlWrapper):
    """``DMControlWrapper`` whose observations and reward are float32 tensors built directly."""

    def _make_specs(self, env: Any) -> None:
        super()._make_specs(env)
        action = self.action_spec
        self.action_spec = Bounded(
            low=action.space.low.float(),
            high=action.space.high.float(),
            shape=action.shape,
            dtype=torch.float32,
            device=self.device,
        )
        self.reward_spec = Unbounded(shape=(1,), dtype=torch.float32, device=self.device)

    def _set_seed(self, seed: int | None) -> None:
        # numpy's RandomState (the task's) takes seeds in [0, 2**32): say so before it fails
        if seed is not None and (
            isinstance(seed, bool)
            or not isinstance(seed, (int, np.integer))
            or not 0 <= seed < 2**32
        ):
            raise ValueError(f"seed: expected an integer in [0, 2**32), got {seed!r}")
        super()._set_seed(seed)

    def read_action(self, action: torch.Tensor) -> np.ndarray:
        """The action as the NumPy array dm_control takes, checked: shape ``[2]`` and finite
        (dm_control would broadcast a ``[1]`` action to both motors, clip an inf and fail on a
        NaN deep in the physics). Two-entry checks on the array, no tensor reduction."""
        values = super().read_action(action)
        expected = tuple(self.action_spec.shape)
        shape = getattr(values, "shape", None)
        if shape != expected:
            got = list(action.shape) if isinstance(action, torch.Tensor) else action
            raise ValueError(f"action: expected shape {list(expected)}, got {got}")
        if not np.isfinite(values).all():
            raise ValueError(f"action: expected finite values, got {values.tolist()}")
        return values

    def read_obs(self, observations: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
        return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in observations.items()}

    def read_reward(self, reward: float) -> torch.Tensor:
        return torch.tensor([reward], dtype=torch.float32)
