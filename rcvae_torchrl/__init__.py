"""rcvae_torchrl: competency assessment for model-based RL agents in TorchRL.

The main public API is re-exported here, grouped as the data flows: world model, loss, data,
training, the model as a TorchRL env, planning, competency. Everything else lives in the
subpackages (:mod:`rcvae_torchrl.models`, ``.objectives``, ``.data``, ``.training``,
``.model_env``, ``.planners``, ``.competency``), and four more are imported on their own because
they pull in heavier dependencies:

- :mod:`rcvae_torchrl.envs`: the MuJoCo Pusher (dm_control);
- :mod:`rcvae_torchrl.agent`: the MPC agent and the model-based RL loop on the Pusher;
- :mod:`rcvae_torchrl.reporting`: tables and figures (matplotlib);
- :mod:`rcvae_torchrl.study`: the Pusher competency study behind
  ``recipes/pusher_competency.py``.

Example:
    >>> import rcvae_torchrl as rt
    >>> model = rt.RCVAEEnsemble(rt.RCVAEConfig(14, 2, hidden_dim=16), ensemble_size=3)
    >>> model.ensemble_size
    3
"""

from rcvae_torchrl.competency import (
    CompetencyAssessor,
    CompetencyReport,
    SuccessBoundary,
    SuccessMetric,
    UncertaintyDecomposition,
    UncertaintyMetric,
    brier_score,
    decompose_uncertainty,
    expected_calibration_error,
    famsec_outcome_assessment,
    histogram_entropy,
    outcome_uncertainty,
    reliability_diagram,
    success_probability,
    time_to_success,
)
from rcvae_torchrl.data import (
    TRAJ_KEY,
    collect_episodes,
    load_episodes,
    make_window_buffer,
    sample_windows,
    save_episodes,
    split_episodes,
)
from rcvae_torchrl.model_env import RCVAEEnsembleEnv, imagine_rollouts, make_rcvae_env
from rcvae_torchrl.models import (
    RCVAEConfig,
    RCVAEEnsemble,
    RCVAETransition,
    generate,
    make_transition_module,
)
from rcvae_torchrl.objectives import RCVAELoss
from rcvae_torchrl.planners import CEMPlanner, make_cem_planner
from rcvae_torchrl.training import (
    CheckpointError,
    TrainConfig,
    TrainResult,
    load_ensemble,
    save_ensemble,
    train_ensemble,
)

__version__ = "0.1.0"

__all__ = [
    "__version__",
    # world model
    "RCVAEConfig",
    "RCVAEEnsemble",
    "RCVAETransition",
    "generate",
    "make_transition_module",
    # loss
    "RCVAELoss",
    # data
    "TRAJ_KEY",
    "collect_episodes",
    "load_episodes",
    "make_window_buffer",
    "sample_windows",
    "save_episodes",
    "split_episodes",
    # training and checkpoints
    "CheckpointError",
    "TrainConfig",
    "TrainResult",
    "load_ensemble",
    "save_ensemble",
    "train_ensemble",
    # the ensemble as a TorchRL env
    "RCVAEEnsembleEnv",
    "imagine_rollouts",
    "make_rcvae_env",
    # planning
    "CEMPlanner",
    "make_cem_planner",
    # competency: uncertainty in bits
    "UncertaintyDecomposition",
    "UncertaintyMetric",
    "decompose_uncertainty",
    "histogram_entropy",
    # competency: outcome forecasts and their calibration
    "SuccessBoundary",
    "SuccessMetric",
    "brier_score",
    "expected_calibration_error",
    "famsec_outcome_assessment",
    "outcome_uncertainty",
    "reliability_diagram",
    "success_probability",
    "time_to_success",
    # competency: one call from start states to a report
    "CompetencyAssessor",
    "CompetencyReport",
]
