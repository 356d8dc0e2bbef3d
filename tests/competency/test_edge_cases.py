"""Edge cases of the competency metrics: missing keys, empty inputs, NaN, degenerate samples,
boundaries with bad radii, predicates or indices. Each gives a named error or a defined result."""

from __future__ import annotations

import math
import re

import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.competency import (
    SuccessBoundary,
    SuccessMetric,
    UncertaintyMetric,
    decompose_uncertainty,
    gaussian_entropy,
)

E, N, B, T, D = 3, 5, 2, 4, 3


def _td(obs: torch.Tensor, key: str = "observation") -> TensorDict:
    return TensorDict({key: obs}, [])


def _boundary(**kwargs) -> SuccessBoundary:
    return SuccessBoundary(lambda obs: obs[..., 0] > 0, time_limit=3, **kwargs)


METRICS = {
    "uncertainty": lambda: UncertaintyMetric(bin_width=0.1),
    "success": lambda: SuccessMetric(_boundary()),
}


# --------------------------------------------------------------------------- missing / NaN
@pytest.mark.parametrize("metric", METRICS)
def test_a_missing_observation_is_a_named_key_error(metric):
    with pytest.raises(KeyError, match=r"expected an 'observation' entry.*got keys \['obs'\]"):
        METRICS[metric]()(_td(torch.randn(E, N, B, T, D), key="obs"))


@pytest.mark.parametrize("metric", METRICS)
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_observations_are_refused_by_every_metric(metric, bad):
    obs = torch.randn(E, N, B, T, D)
    obs[1, 2, 0, 3, 1] = bad
    with pytest.raises(ValueError, match=r"tensordict\['observation'\]: expected finite values"):
        METRICS[metric]()(_td(obs))


@pytest.mark.parametrize("method", ["success_over_time", "outcome", "ended_over_time"])
def test_the_boundary_refuses_nan_observations(method):
    obs = torch.zeros(2, T, D)
    obs[0, 1, 2] = math.nan  # not even in the dimension the predicate reads
    with pytest.raises(ValueError, match=r"^observation: expected finite values, got 1 NaN"):
        getattr(_boundary(), method)(obs)


@pytest.mark.parametrize("metric", METRICS)
def test_integer_observations_are_a_type_error(metric):
    with pytest.raises(TypeError, match=r"expected a floating-point tensor, got dtype torch.int64"):
        METRICS[metric]()(_td(torch.zeros(E, N, B, T, D, dtype=torch.int64)))


# --------------------------------------------------------------------------- empty inputs
@pytest.mark.parametrize("metric", METRICS)
@pytest.mark.parametrize(
    ("shape", "axis"), [((E, 0, B, T, D), "N"), ((E, N, B, 0, D), "T"), ((E, N, B, T, 0), "D")]
)
def test_empty_sample_time_or_dimension_axes_are_refused(metric, shape, axis):
    with pytest.raises(ValueError, match=re.escape(f"with {axis} >= 1, got {tuple(shape)}")):
        METRICS[metric]()(_td(torch.randn(shape)))


def test_an_empty_batch_gives_empty_results_of_the_right_shapes():
    obs = torch.randn(E, N, 0, T, D)
    u = UncertaintyMetric(bin_width=0.1)(_td(obs))["uncertainty"]
    assert u["total"].shape == (0, T, D) and u["time_mean", "epistemic"].shape == (0, D)
    assert u["summary", "total"].shape == (0,)
    c = SuccessMetric(_boundary())(_td(obs))["competency"]
    assert c["p_success"].shape == (0,) and c["success"].shape == (E, N, 0)
    for estimator, shape in [("gaussian", (0, 7, D)), ("knn", (0, 7)), ("mixture", (0, 7))]:
        parts = decompose_uncertainty(torch.randn(E, 6, 0, 7, D), estimator)
        assert parts.total.shape == parts.epistemic.shape == shape


# --------------------------------------------------------------------------- degenerate samples
@pytest.mark.parametrize("estimator", ["gaussian", "mixture"])
def test_variance_estimators_need_two_samples_per_member(estimator):
    with pytest.raises(ValueError, match=r"needs at least 2 samples per member.*got N = 1"):
        decompose_uncertainty(torch.randn(E, 1, 4, D), estimator)
    with pytest.raises(ValueError, match=r"at least 2 samples on axis 0.*got N = 1"):
        gaussian_entropy(torch.randn(1, 4, D))
    assert torch.isfinite(decompose_uncertainty(torch.randn(E, 2, 4, D), estimator).total).all()


@pytest.mark.parametrize(("n", "k"), [(2, 3), (3, 3), (1, 1)])
def test_knn_names_the_per_member_sample_count(n, k):
    samples = torch.randn(E, n, 4, D)  # E·n pooled samples may be enough; n per member is not
    with pytest.raises(ValueError, match=rf"more than k = {k}\).*got N = {n} "):
        decompose_uncertainty(samples, "knn", k=k)


def test_a_single_sample_histogram_is_defined():
    """One sample per member: each member's entropy is 0, all of the total is epistemic."""
    samples = torch.arange(E, dtype=torch.float32).reshape(E, 1, 1, 1).expand(E, 1, 1, D)
    parts = decompose_uncertainty(samples.contiguous(), bin_width=0.5)
    assert torch.equal(parts.aleatoric, torch.zeros(1, D))
    assert torch.allclose(parts.epistemic, torch.full((1, D), math.log2(E)))


# --------------------------------------------------------------------------- boundaries
@pytest.mark.parametrize("radius", [math.inf, -math.inf, math.nan, 0.0, -1.0, "0.1", True])
def test_a_ball_needs_a_finite_positive_radius(radius):
    with pytest.raises(ValueError, match=r"^radius: expected a positive number"):
        SuccessBoundary.ball([0, 1], radius, target=[2, 3])
    with pytest.raises(ValueError, match=r"^radius: expected a positive number"):
        SuccessBoundary.within_distance(lambda obs: obs[..., 0], radius)


@pytest.mark.parametrize("dtype", [torch.float32, torch.int64, torch.uint8])
def test_predicates_must_return_bool(dtype):
    boundary = SuccessBoundary(lambda obs: (obs[..., 0] > 0).to(dtype), time_limit=3)
    match = rf"success: expected the predicate to return a bool.*{dtype}"
    with pytest.raises(TypeError, match=match):
        boundary.success_over_time(torch.randn(2, T, D))
    failing = SuccessBoundary(lambda obs: obs[..., 0] > 0, failure=lambda obs: obs[..., 1] * 1.0)
    with pytest.raises(TypeError, match=r"^failure: expected the predicate to return a bool"):
        failing.outcome(torch.randn(2, T, D))


@pytest.mark.parametrize(
    ("position", "target", "match"),
    [
        ([0, 1], [2, 14], r"^target: expected observation indices in \[0, 14\).*\[2, 14\]"),
        ([0, 20], [2, 3], r"^position: expected observation indices in \[0, 14\).*\[0, 20\]"),
        ([0, -1], [2, 3], r"^position: expected distinct indices >= 0, got \[0, -1\]"),
        ([0, 0], [2, 3], r"^position: expected distinct indices >= 0, got \[0, 0\]"),
        ([], [], r"^position: expected a non-empty sequence"),
        ([0.5, 1], [2, 3], r"^position: expected a non-empty sequence of int indices"),
        ([0, 1], [2], r"^target: expected 2 observation indices, got \[2\]"),
    ],
)
def test_bad_indices_are_refused_at_construction(position, target, match):
    with pytest.raises((ValueError, TypeError), match=match):
        SuccessBoundary.ball(position, 0.1, target=target, obs_dim=14)


def test_out_of_range_indices_without_obs_dim_are_a_value_error_at_evaluation():
    boundary = SuccessBoundary.ball([0, 1], 0.1, target=[2, 30])  # D unknown yet
    with pytest.raises(ValueError, match=r"^target: expected observation indices in \[0, 4\)"):
        boundary.success_over_time(torch.randn(2, T, 4))
    ok = SuccessBoundary.ball([0, 1], 0.1, target=[2, 3], obs_dim=4)
    inside = torch.tensor([[[0.0, 0.0, 0.05, 0.0]]])  # distance 0.05 <= 0.1
    assert ok.success_over_time(inside).tolist() == [[True]]


def test_a_fixed_target_must_be_finite():
    with pytest.raises(ValueError, match=r"^target: expected finite values"):
        SuccessBoundary.ball([0, 1], 0.1, target=torch.tensor([0.0, math.inf]))
