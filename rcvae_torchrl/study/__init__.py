"""The Pusher competency study: the library side of ``recipes/pusher_competency.py``."""

from .config import (
    AgentStudyConfig,
    AssessConfig,
    DataConfig,
    ModelConfig,
    StudyConfig,
    from_mapping,
)
from .pipeline import CONDITIONS, run_study
from .stages import StageRunner

__all__ = [
    # configuration
    "AgentStudyConfig",
    "AssessConfig",
    "DataConfig",
    "ModelConfig",
    "StudyConfig",
    "from_mapping",
    # running
    "CONDITIONS",
    "StageRunner",
    "run_study",
]
