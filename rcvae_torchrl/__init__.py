"""rcvae_torchrl: competency assessment for model-based RL agents in TorchRL.

The main public API is re-exported here, grouped as the data flows: world model, loss, data,
training, the rollout engine, the model as a TorchRL env, planning, competency. Everything else
lives in the subpackages (:mod:`rcvae_torchrl.models`, ``.objectives``, ``.data``,
``.training``, ``.rollout``, ``.model_env``, ``.planners``, ``.competency``, ``.io``), and three
more are imported on their own because they pull in heavier dependencies:

- :mod:`rcvae_torchrl.agent`: the MPC agent, its distillation into a policy, real episodes;
- :mod:`rcvae_torchrl.reporting`: tables and figures (matplotlib);
- :mod:`rcvae_torchrl.envs`: an example MuJoCo domain, which the library itself
  never imports.

Example:
    >>> import rcvae_torchrl as rt
    >>> model = rt.RCVAEEnsemble(rt.RCVAEConfig(5, 1, hidden_dim=16), ensemble_size=3)
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
from rcvae_torchrl.model_env import RCVAEEnsembleEnv, make_rcvae_env
from rcvae_torchrl.models import InputFeatures, ModelFunctions, RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.objectives import RCVAELoss
from rcvae_torchrl.planners import CEMPlanner, make_cem_planner
from rcvae_torchrl.rollout import (
    ParticleTransition,
    Task,
    evaluate_action_sequences,
    imagine,
    make_transition_module,
    plan_actions,
)
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
    "InputFeatures",
    "ModelFunctions",
    "RCVAEConfig",
    "RCVAEEnsemble",
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
    # the rollout engine
    "ParticleTransition",
    "Task",
    "evaluate_action_sequences",
    "imagine",
    "make_transition_module",
    "plan_actions",
    # the ensemble as a TorchRL env
    "RCVAEEnsembleEnv",
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
