"""Competency assessment: uncertainty in bits, outcome forecasts and their calibration.

Pure tensor functions (sample / member axes first, batch axes next, state dimension last) and the
TorchRL-style metric modules built on them. Reference: Acharya, Russell & Ahmed (2022),
equations 2 and 3 and Table 1.
"""

from rcvae_torchrl.competency.accuracy import (
    band_coverage,
    constant_baseline_error,
    forecast_error,
    forecast_spread,
)
from rcvae_torchrl.competency.assessor import (
    CompetencyAssessor,
    ImaginesRollouts,
    PerSample,
)
from rcvae_torchrl.competency.boundary import (
    Predicate,
    SuccessBoundary,
    check_same_predicates,
    hold_last_state,
)
from rcvae_torchrl.competency.calibration import (
    BrierDecomposition,
    ReliabilityDiagram,
    brier_decomposition,
    brier_score,
    expected_calibration_error,
    reliability_diagram,
)
from rcvae_torchrl.competency.comparison import AgentComparison, compare_agents
from rcvae_torchrl.competency.decomposition import (
    ESTIMATORS,
    UncertaintyDecomposition,
    decompose_uncertainty,
    variance_decomposition,
)
from rcvae_torchrl.competency.entropy import gaussian_entropy, histogram_entropy, knn_entropy
from rcvae_torchrl.competency.intervals import binomial_interval, paired_difference_interval
from rcvae_torchrl.competency.metrics import (
    SuccessMetric,
    UncertaintyMetric,
    bits_per_live_step,
    rescale_aleatoric,
)
from rcvae_torchrl.competency.mixture import (
    EntropyBounds,
    fit_gaussian_mixture_entropy_bounds,
    gaussian_mixture_entropy_bounds,
)
from rcvae_torchrl.competency.outcome import (
    TimeToSuccess,
    binary_entropy,
    first_success_step,
    outcome_uncertainty,
    success_on_grid,
    success_probability,
    time_to_success,
)
from rcvae_torchrl.competency.outcome_assessment import (
    famsec_outcome_assessment,
    generalized_outcome_assessment,
    ordinal_distribution,
    partial_moments,
)
from rcvae_torchrl.competency.recalibration import (
    PlattMap,
    apply_platt,
    cross_fitted_recalibration,
    fit_platt,
)
from rcvae_torchrl.competency.report import (
    AleatoricShare,
    CompetencyReport,
    RealSpread,
    Reference,
)
from rcvae_torchrl.competency.validation import (
    StartReliability,
    auroc,
    brier_skill_score,
    chance_brier_skill,
    crps_samples,
    episode_brier,
    members_brier_skill,
    per_start_rates,
    pool_outcomes,
    rank_correlation,
    rate_reliability,
    same_chance_p_value,
    start_reliability,
    time_to_success_scores,
    validate_forecasts,
)

__all__ = [
    "AgentComparison",
    "compare_agents",
    # entropy estimators (bits)
    "EntropyBounds",
    "fit_gaussian_mixture_entropy_bounds",
    "gaussian_entropy",
    "gaussian_mixture_entropy_bounds",
    "histogram_entropy",
    "knn_entropy",
    # decompositions
    "ESTIMATORS",
    "UncertaintyDecomposition",
    "decompose_uncertainty",
    "variance_decomposition",
    # outcome forecasts
    "TimeToSuccess",
    "binary_entropy",
    "binomial_interval",
    "first_success_step",
    "paired_difference_interval",
    "outcome_uncertainty",
    "success_on_grid",
    "success_probability",
    "time_to_success",
    # outcome assessment (FaMSeC)
    "famsec_outcome_assessment",
    "generalized_outcome_assessment",
    "ordinal_distribution",
    "partial_moments",
    # calibration against real outcomes
    "BrierDecomposition",
    "ReliabilityDiagram",
    "brier_decomposition",
    "brier_score",
    "expected_calibration_error",
    "reliability_diagram",
    # recalibration on real episodes (cross-fitted over start states)
    "PlattMap",
    "apply_platt",
    "cross_fitted_recalibration",
    "fit_platt",
    # forecasts against real episodes, start by start
    "StartReliability",
    "auroc",
    "brier_skill_score",
    "chance_brier_skill",
    "crps_samples",
    "episode_brier",
    "members_brier_skill",
    "per_start_rates",
    "pool_outcomes",
    "rate_reliability",
    "same_chance_p_value",
    "rank_correlation",
    "start_reliability",
    "time_to_success_scores",
    "validate_forecasts",
    # imagined trajectories against real ones
    "band_coverage",
    "constant_baseline_error",
    "forecast_error",
    "forecast_spread",
    # metric modules
    "Predicate",
    "SuccessBoundary",
    "check_same_predicates",
    "hold_last_state",
    "SuccessMetric",
    "UncertaintyMetric",
    "bits_per_live_step",
    "rescale_aleatoric",
    # one-call assessment from start states
    "CompetencyAssessor",
    "CompetencyReport",
    "RealSpread",
    "AleatoricShare",
    "ImaginesRollouts",
    "PerSample",
    "Reference",
]
