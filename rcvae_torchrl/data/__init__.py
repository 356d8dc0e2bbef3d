"""Data: exploration policies, episode collection, trajectory replay and windows."""

from .collection import TRAJ_KEY, collect_episodes
from .exploration import GaussianExploration, UniformRandomPolicy, make_exploration_policy
from .replay import make_window_buffer, sample_windows, split_episodes
from .storage import load_episodes, save_episodes

__all__ = [
    # collection
    "TRAJ_KEY",
    "collect_episodes",
    # exploration
    "GaussianExploration",
    "UniformRandomPolicy",
    "make_exploration_policy",
    # replay
    "make_window_buffer",
    "sample_windows",
    "split_episodes",
    # storage
    "load_episodes",
    "save_episodes",
]
