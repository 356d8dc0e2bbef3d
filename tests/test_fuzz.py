"""Property-based fuzzing of the public entry points (Hypothesis).

Random shapes (empty axes included), dtypes, NaN / ±inf, extreme magnitudes and wrong keys go
into the model env (reset, step, imagine), the metrics, the success boundary, the competency
assessor and the recipe's config loading. Every call must either return finite, well-shaped
output or raise ``ValueError`` / ``TypeError`` / ``KeyError`` whose message names one of the
arguments involved; anything else (``AttributeError``, ``IndexError``, ``RuntimeError``,
``OverflowError``, a silent NaN) fails the test.

The default suite runs a few examples per entry point (derandomised, a few seconds in all);
``test_fuzz_long`` (slow) runs many more with fresh randomness.
"""

from __future__ import annotations

import functools
import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from rcvae_torchrl.competency import (
    CompetencyAssessor,
    SuccessBoundary,
    SuccessMetric,
    UncertaintyMetric,
)
from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.model_env import RCVAEEnsembleEnv
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble

S, A, E = 14, 2, 2
SPECIAL = (math.nan, math.inf, -math.inf, 1e30, -1e30, 1e-30, 0.0)
DTYPES = (torch.float32,) * 4 + (torch.float64, torch.float16, torch.int64, torch.bool)
FAST = settings(
    max_examples=12,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
LONG = settings(
    max_examples=300,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


# --------------------------------------------------------------------------- shared pieces
@functools.cache
def _env() -> RCVAEEnsembleEnv:
    torch.manual_seed(0)
    model = RCVAEEnsemble(
        RCVAEConfig(S, A, hidden_dim=8, latent_dim=2, mlp_dim=8, passthrough_dims=(12, 13)), E
    )
    g = torch.Generator().manual_seed(0)
    obs = 0.1 * torch.randn(64, S, generator=g)
    model.fit_normalizer(obs, torch.rand(64, A, generator=g) * 2 - 1)
    return RCVAEEnsembleEnv(model, pusher_reward, pusher_success, seed=0)


def _boundary(**kwargs) -> SuccessBoundary:
    kwargs.setdefault("time_limit", 5)
    return SuccessBoundary.ball([8, 9], 0.03, target=[12, 13], obs_dim=S, **kwargs)


def _shape(data, valid: tuple[int, ...]) -> list[int]:
    """``valid`` most of the time; else a perturbed shape (a dim dropped, added, zeroed or
    resized)."""
    shape = list(valid)
    kind = data.draw(st.sampled_from(["valid"] * 3 + ["drop", "add", "zero", "resize"]))
    if kind == "drop" and shape:
        shape.pop(data.draw(st.integers(0, len(shape) - 1)))
    elif kind == "add":
        shape.insert(data.draw(st.integers(0, len(shape))), data.draw(st.integers(0, 3)))
    elif kind in ("zero", "resize") and shape:
        i = data.draw(st.integers(0, len(shape) - 1))
        shape[i] = 0 if kind == "zero" else data.draw(st.integers(0, 16))
    return shape


def _tensor(data, shape, dtype=None) -> torch.Tensor:
    """A tensor of ``shape``: random scale, sometimes special values, a random dtype."""
    dtype = data.draw(st.sampled_from(DTYPES)) if dtype is None else dtype
    g = torch.Generator().manual_seed(data.draw(st.integers(0, 2**16)))
    x = torch.randn(shape, generator=g) * data.draw(st.sampled_from([1e-6, 0.1, 1.0, 1e6]))
    if x.numel() and data.draw(st.integers(0, 3)) == 0:
        flat = x.view(-1)
        for _ in range(data.draw(st.integers(1, 3))):
            flat[data.draw(st.integers(0, flat.numel() - 1))] = data.draw(st.sampled_from(SPECIAL))
    return x.to(dtype)


def _batch(data, max_dims: int = 2) -> list[int]:
    return data.draw(st.lists(st.integers(0, 3), max_size=max_dims))


def _call(fn, names: tuple[str, ...]):
    """``fn()``, or None when it raised a ValueError / TypeError / KeyError naming one of
    ``names``; any other exception propagates (and fails the test)."""
    try:
        return fn()
    except (ValueError, TypeError, KeyError) as err:
        message = str(err)
        assert any(name in message for name in names), (
            f"{type(err).__name__} names none of {names}: {message}"
        )
        return None


def _finite(x: torch.Tensor, shape) -> None:
    assert tuple(x.shape) == tuple(shape), (tuple(x.shape), tuple(shape))
    if x.is_floating_point():
        assert bool(torch.isfinite(x).all()), "non-finite output"


# --------------------------------------------------------------------------- entry points
def fuzz_reset(data) -> None:
    batch = _batch(data)
    obs = _tensor(data, _shape(data, (*batch, S)))
    env = _env()
    td = TensorDict({"observation": obs}, batch_size=obs.shape[:-1] if obs.ndim else [])
    out = _call(lambda: env.reset(td), ("observation",))
    if out is not None:
        _finite(out["observation"], obs.shape)


def fuzz_step(data) -> None:
    batch = _batch(data)
    env = _env()
    starts = 0.1 * torch.randn(*batch, S)
    td = env.reset(TensorDict({"observation": starts}, batch_size=batch))
    if data.draw(st.integers(0, 5)):
        td.set("action", _tensor(data, [*batch, *_shape(data, (A,))]))
    out = _call(lambda: env.step(td), ("action",))
    if out is not None:
        _finite(out["next", "observation"], (*batch, S))
        _finite(out["next", "reward"], (*batch, 1))


def fuzz_imagine(data) -> None:
    batch = _batch(data)
    start = _tensor(data, _shape(data, (*batch, S)))
    n = data.draw(st.sampled_from([1, 2, 0, -1]))
    t = data.draw(st.integers(0, 4))
    env = _env()
    if data.draw(st.booleans()):
        actions = _tensor(data, _shape(data, (*batch, t, A)))
        t = actions.shape[-2] if actions.ndim >= 2 else t  # the steps imagined: T of the plan
        out = _call(
            lambda: env.imagine(start, actions, samples_per_member=n),
            ("observation", "actions", "samples_per_member", "imagine", "reward_fn"),
        )
    else:
        scale = data.draw(st.sampled_from([0.0, 1.0, 1e30, math.nan]))
        policy = lambda o: torch.full((*o.shape[:-1], A), scale)  # noqa: E731
        out = _call(
            lambda: env.imagine(start, policy=policy, horizon=t, samples_per_member=n),
            ("observation", "horizon", "samples_per_member", "policy", "imagine", "reward_fn"),
        )
    if out is not None:
        _finite(out["observation"], (E, n, *start.shape[:-1], t, S))
        _finite(out["reward"], (E, n, *start.shape[:-1], t, 1))


def _rollout_td(data) -> tuple[TensorDict, list[int]]:
    batch = _batch(data, 1)
    valid = (data.draw(st.integers(1, 3)), data.draw(st.integers(1, 4)), *batch, 3, S)
    obs = _tensor(data, _shape(data, valid))
    key = "observation" if data.draw(st.integers(0, 5)) else "obs"
    return TensorDict({key: obs}, batch_size=[]), list(obs.shape)


def fuzz_uncertainty(data) -> None:
    td, shape = _rollout_td(data)
    estimator = data.draw(st.sampled_from(["histogram", "gaussian", "knn", "mixture"]))
    kwargs = {"bin_width": data.draw(st.sampled_from([0.1, 1e-9, 0.0, -1.0, math.inf]))}
    if estimator != "histogram":
        kwargs = {} if estimator != "knn" else {"k": data.draw(st.integers(1, 3))}
    names = ("observation", "samples", "bin_width", "k", "estimator")
    metric = _call(lambda: UncertaintyMetric(estimator=estimator, **kwargs), names)
    out = None if metric is None else _call(lambda: metric(td), names)
    if out is not None:
        total = out["uncertainty", "total"]
        per_dim = (*shape[2:-2], shape[-2], shape[-1])
        _finite(total, per_dim if total.ndim == len(per_dim) else per_dim[:-1])
        _finite(out["uncertainty", "summary", "epistemic"], shape[2:-2])


def fuzz_success_metric(data) -> None:
    td, shape = _rollout_td(data)
    out = _call(lambda: SuccessMetric(_boundary())(td), ("observation", "target", "position"))
    if out is not None:
        p = out["competency", "p_success"]
        _finite(p, shape[2:-2])
        assert bool(((p >= 0) & (p <= 1)).all())


def fuzz_boundary(data) -> None:
    index = st.integers(-2, 16)
    position = data.draw(st.lists(index, min_size=0, max_size=3))
    target = data.draw(st.one_of(st.lists(index, max_size=3), st.just(torch.zeros(2))))
    radius = data.draw(st.sampled_from([0.03, 0.0, -1.0, math.inf, math.nan, 1e30]))
    limit = data.draw(st.sampled_from([None, 1, 5, 0, -3]))
    obs_dim = data.draw(st.sampled_from([None, S, 3]))
    names = ("position", "target", "radius", "time_limit", "obs_dim", "observation")
    boundary = _call(
        lambda: SuccessBoundary.ball(
            position, radius, target=target, time_limit=limit, obs_dim=obs_dim
        ),
        names,
    )
    obs = _tensor(data, _shape(data, (*_batch(data), 4, S)))
    out = None if boundary is None else _call(lambda: boundary.outcome(obs), names)
    if out is not None:
        over_time, success, failure = out
        assert over_time.dtype == torch.bool and tuple(over_time.shape) == tuple(obs.shape[:-1])
        assert tuple(success.shape) == tuple(failure.shape) == tuple(obs.shape[:-2])


def fuzz_assessor(data) -> None:
    n = data.draw(st.sampled_from([2, 1, 0]))
    names = ("samples_per_member", "start", "actions", "horizon", "samples", "imagine", "reward_fn")
    assessor = _call(
        lambda: CompetencyAssessor(_env(), _boundary(), bin_width=0.05, samples_per_member=n),
        names,
    )
    if assessor is None:
        return
    batch = _batch(data, 1)
    start = _tensor(data, _shape(data, (*batch, S)))
    actions = _tensor(data, _shape(data, (data.draw(st.integers(0, 4)), A)))
    report = _call(lambda: assessor.assess(start, actions=actions), names)
    if report is not None:
        p = report.data["competency", "p_success"]
        _finite(p, start.shape[:-1])
        _finite(report.data["uncertainty", "summary", "total"], start.shape[:-1])


VALUES = st.sampled_from(
    [0, 1, -1, 2, 2**40, 1.5, -0.5, math.inf, math.nan, "", "abc", True, None, "cuda:7", "cpu"]
)
KEYS = st.sampled_from(
    [
        "seed",
        "threads",
        "progress",
        "device",
        "train.window",
        "train.beta",
        "train.free_nats",
        "train.open_loop_steps",
        "train.lr",
        "assess.horizon_s",
        "assess.start_states",
        "model.ensemble_size",
        "model.state_constraint",
        "data.time_limit",
        "planner.top_k",
        "bogus",
        "train.bogus",
    ]
)


def fuzz_config(data) -> None:
    from recipes.pusher_competency.config import RecipeConfig, study_config

    overrides = data.draw(st.dictionaries(KEYS, VALUES, max_size=3))
    nested: dict = {"run_dir": _RUN_DIR}
    for key, value in overrides.items():
        *parents, leaf = key.split(".")
        node = nested
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    leaves = tuple(key.split(".")[-1] for key in overrides) or ("run_dir",)
    config = _call(lambda: study_config(nested), leaves)
    if config is not None:
        assert isinstance(config, RecipeConfig)


_RUN_DIR = "/tmp/rcvae_fuzz_run_dir_not_created"
ENTRY_POINTS = {
    "reset": fuzz_reset,
    "step": fuzz_step,
    "imagine": fuzz_imagine,
    "uncertainty_metric": fuzz_uncertainty,
    "success_metric": fuzz_success_metric,
    "success_boundary": fuzz_boundary,
    "assessor": fuzz_assessor,
    "config": fuzz_config,
}


@pytest.mark.parametrize("entry_point", ENTRY_POINTS)
@FAST
@given(data=st.data())
def test_fuzz(entry_point, data):
    ENTRY_POINTS[entry_point](data)


@pytest.mark.slow
@pytest.mark.parametrize("entry_point", ENTRY_POINTS)
@LONG
@given(data=st.data())
def test_fuzz_long(entry_point, data):
    ENTRY_POINTS[entry_point](data)
