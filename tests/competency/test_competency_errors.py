"""Bad input gives clear errors naming the argument, the expectation and what was given."""

import math
import warnings

import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.competency import (
    SuccessBoundary,
    SuccessMetric,
    UncertaintyMetric,
    binomial_interval,
    brier_decomposition,
    decompose_uncertainty,
    expected_calibration_error,
    famsec_outcome_assessment,
    first_success_step,
    gaussian_entropy,
    gaussian_mixture_entropy_bounds,
    generalized_outcome_assessment,
    histogram_entropy,
    knn_entropy,
    outcome_uncertainty,
    success_probability,
    variance_decomposition,
)


def test_wrong_rank():
    with pytest.raises(
        ValueError, match=r"samples: expected shape \[N, \*batch, D\].*got shape \(5,\)"
    ):
        histogram_entropy(torch.randn(5), 0.1)
    with pytest.raises(ValueError, match=r"samples: expected shape \[E, N, \*batch, D\]"):
        decompose_uncertainty(torch.randn(4, 10), bin_width=0.1)
    with pytest.raises(ValueError, match=r"success: expected shape \[E, N, \*batch\]"):
        success_probability(torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"observation.*\[E, N, \*B, T, D\]"):
        UncertaintyMetric(bin_width=0.1)(TensorDict({"observation": torch.randn(2, 3, 4)}, []))


def test_too_few_members():
    with pytest.raises(ValueError, match=r"samples: .*E >= 2 ensemble members.*got E = 1"):
        decompose_uncertainty(torch.randn(1, 10, 2), bin_width=0.1)
    with pytest.raises(ValueError, match="E >= 2"):
        variance_decomposition(torch.randn(1, 10, 2))
    with pytest.raises(ValueError, match=r"success: .*E >= 2"):
        outcome_uncertainty(torch.ones(1, 10, dtype=torch.bool))


@pytest.mark.parametrize("width", [0.0, -0.1, float("nan"), [0.1, -1.0]])
def test_non_positive_bin_width(width):
    with pytest.raises(ValueError, match="bin_width: expected positive finite widths"):
        histogram_entropy(torch.randn(10, 2), width)


def test_bin_width_of_wrong_length():
    with pytest.raises(
        ValueError, match=r"bin_width: expected a scalar or a tensor of shape \[D\] = \[2\]"
    ):
        decompose_uncertainty(torch.randn(2, 10, 2), bin_width=[0.1, 0.1, 0.1])
    with pytest.raises(ValueError, match="bin_width: expected a positive width for the histogram"):
        UncertaintyMetric()
    with pytest.raises(ValueError, match="bin_width: expected a positive width for the histogram"):
        decompose_uncertainty(torch.randn(2, 10, 2))
    with pytest.raises(ValueError, match="bin_width: expected None for the mixture estimator"):
        UncertaintyMetric(bin_width=0.1, estimator="mixture")


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_samples(bad):
    x = torch.randn(3, 10, 2)
    x[1, 2, 0] = bad
    for call in (
        lambda: decompose_uncertainty(x, bin_width=0.1),
        lambda: gaussian_entropy(x),
        lambda: knn_entropy(x),
        lambda: famsec_outcome_assessment(x),
    ):
        with pytest.raises(ValueError, match="expected finite values, got"):
            call()


def test_probabilities_outside_unit_interval():
    with pytest.raises(ValueError, match=r"forecast: expected probabilities in \[0, 1\]"):
        brier_decomposition(torch.tensor([0.5, 1.2]), torch.tensor([0, 1]))
    with pytest.raises(ValueError, match=r"success: expected probabilities in \[0, 1\]"):
        success_probability(torch.tensor([[0.5, -0.1], [0.2, 0.3]]))
    with pytest.raises(ValueError, match=r"probabilities: expected probabilities in \[0, 1\]"):
        generalized_outcome_assessment(torch.tensor([0.5, 2.0]), 1)
    with pytest.raises(ValueError, match=r"weights: expected probabilities in \[0, 1\]"):
        gaussian_mixture_entropy_bounds(
            torch.tensor([1.5, -0.5]), torch.zeros(2, 1), torch.ones(2, 1)
        )
    with pytest.raises(ValueError, match="outcome: expected binary outcomes"):
        expected_calibration_error(torch.tensor([0.5, 0.5]), torch.tensor([0.0, 0.3]))


def test_mismatched_shapes():
    with pytest.raises(
        ValueError, match=r"forecast and outcome: expected the same shape, got \(3,\) and \(4,\)"
    ):
        expected_calibration_error(torch.rand(3), torch.ones(4))
    with pytest.raises(ValueError, match=r"weights: expected shape \[\*batch, K\] = \(2,\)"):
        gaussian_mixture_entropy_bounds(torch.ones(3) / 3, torch.zeros(2, 1), torch.ones(2, 1))
    with pytest.raises(ValueError, match="covariances: expected shape"):
        gaussian_mixture_entropy_bounds(torch.ones(2) / 2, torch.zeros(2, 2), torch.ones(2, 3))
    metric = UncertaintyMetric(bin_width=0.1, dim_names=["x"])
    obs = torch.randn(2, 3, 4, 2)
    with pytest.raises(ValueError, match="dim_names: expected 2 names"):
        metric(TensorDict({"observation": obs}, obs.shape[:-1]))


def test_bad_choices_and_scalars():
    with pytest.raises(ValueError, match=r"estimator: expected one of .*got 'kde'"):
        decompose_uncertainty(torch.randn(2, 10, 1), "kde")
    with pytest.raises(ValueError, match=r"bound: expected one of"):
        decompose_uncertainty(torch.randn(2, 10, 1), "mixture", bound="middle")
    with pytest.raises(ValueError, match="k: expected a positive integer"):
        knn_entropy(torch.randn(10, 1), k=0)
    with pytest.raises(ValueError, match="expected more than k = 3 samples on axis 0, got N = 3"):
        knn_entropy(torch.randn(3, 1), k=3)
    with pytest.raises(ValueError, match="threshold_bin: expected an integer in"):
        generalized_outcome_assessment(torch.tensor([0.5, 0.5]), 2)
    with pytest.raises(ValueError, match="confidence: expected a number in"):
        binomial_interval(torch.tensor(1), 2, confidence=1.5)
    with pytest.raises(ValueError, match="successes, trials"):
        binomial_interval(torch.tensor(3), 2)
    with pytest.raises(TypeError, match="success_over_time: expected a bool tensor"):
        first_success_step(torch.zeros(2, 3))


def test_boundary_errors():
    with pytest.raises(ValueError, match="radius: expected a positive number"):
        SuccessBoundary.ball(position=[0], target=[1], radius=0.0)
    with pytest.raises(ValueError, match="dt: expected the step duration"):
        SuccessBoundary(lambda o: o[..., 0] > 0, time_limit_s=3.0)
    with pytest.raises(ValueError, match="time_limit, time_limit_s: expected at most one"):
        SuccessBoundary(lambda o: o[..., 0] > 0, time_limit=3, time_limit_s=3.0, dt=0.1)
    said = r"^time_limit_s: 2.05 s is not a whole number of steps of dt = 0.02 s; the deadline "
    with pytest.warns(UserWarning, match=said + r"is the end of step 102 \(2.04 s\)"):
        assert (
            SuccessBoundary(lambda o: o[..., 0] > 0, time_limit_s=2.05, dt=0.02).time_limit == 102
        )
    with warnings.catch_warnings():  # a multiple of dt, whatever its float rounding
        warnings.simplefilter("error")
        for seconds, dt, steps in ((0.3, 0.1, 3), (2.04, 0.02, 102), (30.0, 0.05, 600)):
            limit = SuccessBoundary(lambda o: o[..., 0] > 0, time_limit_s=seconds, dt=dt)
            assert limit.time_limit == steps
    with pytest.raises(ValueError, match="target: expected 2 observation indices"):
        SuccessBoundary.ball(position=[0, 1], target=[2], radius=0.1)
    with pytest.raises(TypeError, match="boundary: expected a SuccessBoundary"):
        SuccessMetric(lambda o: o)
    for predicate, error in (
        (lambda o: o.get("dist_to_target") < 0, "AttributeError: 'Tensor' object has no "),
        (lambda o: o[..., 3] < 0, "IndexError: index 3 is out of bounds"),
    ):
        with pytest.raises(
            ValueError,
            match=r"^success: the predicate failed on observations of shape \(2, 5, 3\) "
            r"\(\[\.\.\., T, D\]: .* D = 3 dimensions .*\), with " + error,
        ):
            SuccessBoundary(predicate).success_over_time(torch.randn(2, 5, 3))
    bad = SuccessBoundary(lambda o: o.sum() > 0)
    with pytest.raises(ValueError, match="success: expected the predicate to map observations"):
        bad.success_over_time(torch.randn(2, 5, 3))


def test_a_predicate_that_combines_states_along_the_steps_is_refused():
    """A return summed along the steps (in place of a RewardSum entry in the state) judges a
    forecast's trajectories, a batch of start states and the training states the boundary is
    checked on as one sequence: refused, naming the states judged otherwise."""
    obs = torch.full((2, 5, 3), 0.5)
    summed = SuccessBoundary(lambda o: o[..., 0].cumsum(-1) > 2.0)
    with pytest.raises(
        ValueError,
        match=r"^success: expected a predicate of each state alone .* judged one at a time "
        r"\(\[5, 1, D\]\) than along its steps \(\[\.\.\., 5, D\]\): 1 of the 5 states judged "
        r"otherwise\. .*RewardSum for the return",
    ):
        summed.success_over_time(obs)
    counted = SuccessBoundary.survival(lambda o: o[..., 0].cumsum(-1) > 0.6, time_limit=5)
    with pytest.raises(ValueError, match=r"^failure: expected a predicate of each state alone"):
        counted.outcome(obs)
    # each state alone: accepted, the same results as before
    alone = SuccessBoundary(lambda o: o[..., 0] > 0.4, time_limit=3)
    assert alone.success_over_time(obs).tolist() == [[True] * 3 + [False] * 2] * 2


def test_estimator_arguments_are_checked_when_the_metric_is_made():
    """A misspelt keyword is named with the ones the estimator takes, before any rollout."""
    with pytest.raises(TypeError, match=r"the 'histogram' estimator takes .*'bin_width'.*"):
        UncertaintyMetric(bin_width=0.1, bin_widht=0.2)
    with pytest.raises(TypeError, match=r"the 'knn' estimator takes .*'k'.*unknown \['joint'\]"):
        UncertaintyMetric(estimator="knn", joint=True)
    with pytest.raises(TypeError, match=r"unknown \['shufles'\]"):
        decompose_uncertainty(torch.randn(2, 5, 3), bin_width=0.1, shufles=2)
    UncertaintyMetric(estimator="gaussian", joint=True)  # a keyword of gaussian_entropy
    with pytest.raises(TypeError, match="joint: expected True or False, got 'yes'"):
        UncertaintyMetric(estimator="gaussian", joint="yes")  # truthy, not a switch
    with pytest.raises(TypeError, match="full_covariance: expected True or False, got 1"):
        decompose_uncertainty(torch.randn(2, 5, 3), estimator="mixture", full_covariance=1)
    UncertaintyMetric(bin_width=0.1, bias_correction="shuffle", shuffles=2)
    with pytest.raises(TypeError, match="bin_width: expected a number or a tensor"):
        UncertaintyMetric(bin_width="0.1")
    with pytest.raises(TypeError, match="episode_end: expected True or False, got 'yes'"):
        UncertaintyMetric(bin_width=0.1, episode_end="yes")


def test_an_assessor_keyword_neither_it_nor_its_estimator_takes_is_named_with_the_nearest():
    from test_assessor import boundary, make_ensemble, make_env

    from rcvae_torchrl.competency import CompetencyAssessor

    env = make_env(make_ensemble())
    with pytest.raises(
        TypeError,
        match=r"^CompetencyAssessor: got unknown keyword argument\(s\) \['samples'\], neither the "
        r"assessor's \(bin_width, .*samples_per_member.*\) nor the 'histogram' estimator's "
        r"\(bias_correction, .*shuffles\); did you mean 'samples_per_member'\?$",
    ):
        CompetencyAssessor(env, boundary(), bin_width=0.1, samples=4)
    with pytest.raises(TypeError, match=r"\['shufles'\].*; did you mean 'shuffles'\?$"):
        CompetencyAssessor(env, boundary(), bin_width=0.1, shufles=2)
    CompetencyAssessor(env, boundary(), bin_width=0.1, shuffles=2)  # an estimator's keyword


@pytest.mark.parametrize(
    ("confidence", "error"), [(2, ValueError), (0.0, ValueError), ("95%", TypeError)]
)
def test_a_confidence_outside_0_1_is_refused_when_the_metric_is_made(confidence, error):
    boundary = SuccessBoundary(lambda s: s[..., 0] > 0, time_limit=5)
    with pytest.raises(error, match="confidence: expected a number in"):
        SuccessMetric(boundary, confidence=confidence)


def test_summary_of_a_start_state_outside_the_batch():
    from test_assessor import hand_report

    report = hand_report()
    batched = type(report)(
        report.data.unsqueeze(0).expand(3).clone(), report.dim_names, 600, 0.05, 0.95
    )
    assert batched.summary(index=2).startswith("P(success")
    with pytest.raises(
        IndexError, match=r"index: expected one start state of the batch \(3,\), got 5"
    ):
        batched.summary(index=5)
    # one start state alone (a start [S] assessed unbatched): tensordict's "indexing a
    # tensordict with td.batch_dims==0 is not permitted" said nothing of the report
    assert report.batch_size == () and report.summary().startswith("P(success")
    with pytest.raises(IndexError, match=r"^index: this report is of one start state \(batch"):
        report.summary(index=0)


def test_validation_scores_refuse_what_they_would_turn_into_plausible_numbers():
    from rcvae_torchrl.competency import (
        auroc,
        crps_samples,
        rank_correlation,
        time_to_success_scores,
        validate_forecasts,
    )

    nan = float("nan")
    with pytest.raises(ValueError, match="x: expected finite values"):
        rank_correlation(torch.tensor([nan, 1.0, 2.0]), torch.tensor([0.0, 1.0, 2.0]))
    with pytest.raises(ValueError, match="score: expected finite values"):
        auroc(torch.tensor([nan, 0.2, 0.3]), torch.tensor([True, False, True]))
    with pytest.raises(ValueError, match="observed: expected finite values"):
        crps_samples(torch.tensor([1.0, 2.0]), torch.tensor([nan]))
    forecast, outcome = torch.tensor([0.2, 0.8]), torch.tensor([[False, True], [True, True]])
    with pytest.raises(ValueError, match=r"base_rate: expected a float in \[0, 1\], got 1.5"):
        validate_forecasts(forecast, outcome, base_rate=1.5)
    with pytest.raises(TypeError, match="forecast: expected a floating-point tensor"):
        validate_forecasts(torch.tensor([0, 1]), outcome)
    steps = torch.tensor([[3.0, 5.0], [4.0, 6.0]])
    for mask in (torch.ones(2, 2, dtype=torch.long), torch.ones(2, 3, dtype=torch.bool)):
        with pytest.raises(ValueError, match=r"mask: expected a bool tensor of real_steps' shape"):
            time_to_success_scores(steps, steps, mask)
    with pytest.raises(ValueError, match="real_steps: expected finite values"):
        time_to_success_scores(steps, steps.clone().fill_(nan))


def test_recalibration_and_outcome_assessments_refuse_silent_truncation():
    from rcvae_torchrl.competency import (
        PlattMap,
        apply_platt,
        cross_fitted_recalibration,
        fit_platt,
        ordinal_distribution,
    )

    outcome = torch.tensor([[True], [False], [True], [False]])
    with pytest.raises(TypeError, match="forecast: expected a floating-point tensor"):
        apply_platt(torch.tensor([0, 1]), PlattMap(0.5, 0.3))
    with pytest.raises(TypeError, match="forecast: expected a floating-point tensor"):
        cross_fitted_recalibration(torch.tensor([0, 1, 0, 1]), outcome, folds=2)
    with pytest.raises(ValueError, match=r"forecast: expected probabilities in \[0, 1\]"):
        apply_platt(torch.tensor([1.5]), PlattMap(1.0, 0.0))
    with pytest.raises(ValueError, match="platt: expected a finite slope and intercept"):
        apply_platt(torch.tensor([0.5]), PlattMap(float("nan"), 0.0))
    with pytest.raises(ValueError, match="ridge: expected a positive number, got inf"):
        fit_platt(torch.tensor([0.5, 0.5]), outcome[:2], ridge=float("inf"))
    with pytest.raises(ValueError, match="forecast: expected at least one start state"):
        fit_platt(torch.zeros(0), torch.zeros(0, 1, dtype=torch.bool))
    assert float(famsec_outcome_assessment(torch.tensor([-1, 5]))) == pytest.approx(2 / 3, abs=1e-4)
    with pytest.raises(ValueError, match="threshold: expected a finite number, got nan"):
        famsec_outcome_assessment(torch.tensor([-1.0, 5.0]), threshold=float("nan"))
    p = torch.tensor([0.25, 0.25, 0.5])
    for kwargs, match in (
        ({"threshold_bin": 1.5}, r"threshold_bin: expected an integer in \[0, 3\), got 1.5"),
        ({"threshold_bin": True}, "threshold_bin: expected an integer"),
        ({"threshold_bin": 1, "scale": -1.0}, "scale: expected a positive number, got -1.0"),
    ):
        with pytest.raises(ValueError, match=match):
            generalized_outcome_assessment(p, **kwargs)
    with pytest.raises(ValueError, match="probabilities: expected every row to hold some"):
        generalized_outcome_assessment(torch.zeros(3), 1)
    with pytest.raises(ValueError, match="bin_edges: expected finite values"):
        ordinal_distribution(torch.randn(5), torch.tensor([float("nan"), 0.0]))


def test_a_ball_around_its_own_position_is_refused():
    with pytest.raises(ValueError, match=r"target: expected other indices than position's \[0\]"):
        SuccessBoundary.ball([0], 0.1, target=[0], time_limit=5)
    SuccessBoundary.ball([0], 0.1, target=[1], time_limit=5)
    SuccessBoundary.ball([0], 0.1, target=torch.tensor([0.5]), time_limit=5)


def test_rollouts_shorter_than_the_boundary_s_time_limit():
    """A survival boundary is decided at its limit: shorter rollouts would read as never
    surviving (P = 0); a reach boundary's forecast answers the shorter deadline, with a
    warning."""
    obs = torch.zeros(2, 3, 4, 5, 1)  # E, N, B, T = 5, D
    rollout = TensorDict({"observation": obs}, batch_size=obs.shape[:-1])
    survive = SuccessBoundary.survival(lambda s: s[..., 0] > 1.0, time_limit=8)
    with pytest.raises(ValueError, match=r"expected T >= 8, got T = 5"):
        SuccessMetric(survive)(rollout)
    reach = SuccessBoundary(lambda s: s[..., 0] > -1.0, time_limit=8)
    with pytest.warns(UserWarning, match="rollouts of 5 steps, shorter than the boundary's"):
        out = SuccessMetric(reach)(rollout)
    assert bool(out["competency", "p_success"].eq(1.0).all())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        SuccessMetric(SuccessBoundary(lambda s: s[..., 0] > -1.0, time_limit=5))(rollout)


@pytest.mark.parametrize(
    ("names", "error", "words"),
    [
        (["a", "a", "b"], ValueError, "dim_names: expected distinct names"),
        ("abc", TypeError, "dim_names: expected a sequence of names (str), got 'abc'"),
        ([1, 2], TypeError, "dim_names: expected a sequence of names (str)"),
    ],
)
def test_dimension_names_are_distinct_strings(names, error, words):
    with pytest.raises(error) as info:
        UncertaintyMetric(bin_width=0.1, dim_names=names)
    assert words in str(info.value)


def test_counts_rates_and_briers_outside_their_range_are_refused():
    from rcvae_torchrl.competency import brier_skill_score, per_start_rates, same_chance_p_value

    with pytest.raises(ValueError, match="expected whole counts"):
        binomial_interval(torch.tensor(float("nan")), 3)
    with pytest.raises(ValueError, match="expected whole counts"):
        binomial_interval(torch.tensor(1.5), 3)
    with pytest.raises(ValueError, match="rates: expected success rates in"):
        same_chance_p_value(torch.tensor([float("nan"), 0.5]), 5)
    with pytest.raises(ValueError, match="rates: expected success rates in"):
        same_chance_p_value(torch.tensor([1.2, 0.5]), 5)
    with pytest.raises(ValueError, match="runs: expected a positive integer, got 0"):
        same_chance_p_value(torch.tensor([0.2, 0.5]), 0)
    with pytest.raises(ValueError, match="brier: expected Brier scores >= 0"):
        brier_skill_score(-0.1, 0.2)
    assert math.isnan(float(brier_skill_score(0.1, 0.0)))  # a perfect reference: NaN, as before
    with pytest.raises(ValueError, match=r"outcome: expected bool outcomes \[B, R\]"):
        per_start_rates(torch.tensor([True, False]))
    with pytest.raises(ValueError, match=r"outcome: expected bool outcomes \[B, R\]"):
        per_start_rates(torch.rand(3, 2))


def test_a_platt_map_of_strings_is_refused():
    from rcvae_torchrl.competency import PlattMap, apply_platt

    with pytest.raises(ValueError, match="platt: expected a finite slope and intercept"):
        apply_platt(torch.tensor([0.5]), PlattMap("1", 0))
