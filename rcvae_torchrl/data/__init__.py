"""Data: exploration policies, episode collection, trajectory replay and windows."""

from .collection import (
    TRAJ_KEY,
    check_actions,
    check_episode_ids,
    check_frames_type,
    collect_episodes,
    episode_ids,
    merge_episodes,
    warn_narrow_bounds,
)
from .exploration import (
    GaussianExploration,
    UniformRandomPolicy,
    acting,
    acting_record,
    action_bounds,
    check_same_acting,
    check_same_agent,
    exploration_mode,
    held_generators,
    make_policy_module,
    planner_generators,
)
from .prepare import (
    ActionNoise,
    AngleAsCosSin,
    ObservationLayout,
    control_step,
    observation_layout,
    prepare_env,
    seed_env,
)
from .replay import (
    episode_spans,
    make_window_buffer,
    resample_episodes,
    sample_windows,
    split_episodes,
)
from .storage import load_episodes, save_episodes

__all__ = [
    # collection
    "TRAJ_KEY",
    "check_actions",
    "check_episode_ids",
    "check_frames_type",
    "collect_episodes",
    "episode_ids",
    "merge_episodes",
    "warn_narrow_bounds",
    # exploration
    "GaussianExploration",
    "UniformRandomPolicy",
    "acting",
    "acting_record",
    "action_bounds",
    "check_same_acting",
    "check_same_agent",
    "exploration_mode",
    "held_generators",
    "planner_generators",
    "make_policy_module",
    # any env as the library expects it
    "ActionNoise",
    "AngleAsCosSin",
    "ObservationLayout",
    "control_step",
    "observation_layout",
    "prepare_env",
    "seed_env",
    # replay
    "episode_spans",
    "make_window_buffer",
    "resample_episodes",
    "sample_windows",
    "split_episodes",
    # storage
    "load_episodes",
    "save_episodes",
]
