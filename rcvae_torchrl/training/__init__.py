"""Training the world model: the loop and its checkpoints."""

from .checkpoint import FORMAT_VERSION, CheckpointError, load_ensemble, save_ensemble
from .checks import ModelChecks, ModelCheckWarning, OutcomeCheck, check_model
from .dynamics import DynamicsCheck, DynamicsNovelty, check_dynamics
from .novelty import StateNovelty, entry_groups
from .trainer import TrainConfig, TrainResult, log_history, train_ensemble

__all__ = [
    # loop
    "TrainConfig",
    "TrainResult",
    "log_history",
    "train_ensemble",
    # self-checks
    "ModelCheckWarning",
    "ModelChecks",
    "OutcomeCheck",
    "check_model",
    # novelty of states
    "StateNovelty",
    "entry_groups",
    # novelty of transitions
    "DynamicsCheck",
    "DynamicsNovelty",
    "check_dynamics",
    # checkpoints
    "FORMAT_VERSION",
    "CheckpointError",
    "load_ensemble",
    "save_ensemble",
]
