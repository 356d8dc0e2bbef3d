"""The Pusher domain (installed as ``rcvae_torchrl.envs``): a dm_control task, its TorchRL
factory, and pure functions of its observations. It depends on the library's dependencies only,
never on the library itself, which never imports it."""

from . import _gl  # noqa: F401  (sets MUJOCO_GL before dm_control loads)
from .batched import BatchedPusherEnv, make_batched_pusher_env
from .constraints import pusher_state_constraint
from .factory import DEFAULT_ACTION_NOISE_STD, VARIANTS, check_strength, make_pusher_env
from .features import PUSHER_FEATURE_NAMES, pusher_input_features
from .functions import DEFAULT_SUCCESS_RADIUS, ball_to_target, pusher_reward, pusher_success
from .layout import (
    OBSERVATION_DIM,
    OBSERVATION_GROUPS,
    OBSERVATION_LAYOUT,
    OBSERVATION_NAMES,
    OBSERVATION_PARTS,
    OBSERVATION_RESOLUTION,
    obs_indices,
    obs_slice,
    resolution_tensor,
)
from .pusher import (
    CONTROL_TIMESTEP,
    DEFAULT_TIME_LIMIT,
    IN_DISTRIBUTION,
    OUT_OF_DISTRIBUTION,
    InitialStateRegion,
)
from .state import reset_to_state

__all__ = [
    # factory
    "DEFAULT_ACTION_NOISE_STD",
    "VARIANTS",
    "check_strength",
    "make_pusher_env",
    "reset_to_state",
    # batched env
    "BatchedPusherEnv",
    "make_batched_pusher_env",
    # task constants and regions
    "CONTROL_TIMESTEP",
    "DEFAULT_SUCCESS_RADIUS",
    "DEFAULT_TIME_LIMIT",
    "IN_DISTRIBUTION",
    "OUT_OF_DISTRIBUTION",
    "InitialStateRegion",
    # observation layout
    "OBSERVATION_DIM",
    "OBSERVATION_GROUPS",
    "OBSERVATION_LAYOUT",
    "OBSERVATION_NAMES",
    "OBSERVATION_PARTS",
    "OBSERVATION_RESOLUTION",
    "obs_indices",
    "obs_slice",
    "resolution_tensor",
    # pure functions of observations
    "pusher_state_constraint",
    "PUSHER_FEATURE_NAMES",
    "pusher_input_features",
    "ball_to_target",
    "pusher_reward",
    "pusher_success",
]
