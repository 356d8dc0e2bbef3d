"""CompetencyAssessor and CompetencyReport: keys, shapes, loops, chunks, summary rules, errors."""

import dataclasses
import json
import math
import warnings

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from rcvae_torchrl.competency import (
    CompetencyAssessor,
    CompetencyReport,
    Reference,
    SuccessBoundary,
    SuccessMetric,
    UncertaintyMetric,
)
from rcvae_torchrl.envs import (
    OBSERVATION_NAMES,
    obs_indices,
    pusher_reward,
    pusher_success,
    resolution_tensor,
)
from rcvae_torchrl.model_env import RCVAEEnsembleEnv
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble

E, N, T, S, A = 3, 8, 6, 14, 2
CONFIG = RCVAEConfig(S, A, hidden_dim=16, latent_dim=4, mlp_dim=16, passthrough_dims=(12, 13))
DT = 0.05


class Passed:
    """Self-checks a model passed: these tests are of the report, not of a trained model."""

    passed = True

    def message(self) -> str:
        return ""


def make_ensemble(seed: int = 0) -> RCVAEEnsemble:
    """A tiny untrained ensemble with a normaliser fitted on random Pusher-scale data, marked
    as having passed its self-checks."""
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    model = RCVAEEnsemble(CONFIG, ensemble_size=E)
    obs = torch.randn(200, S, generator=gen) * 0.1
    actions = torch.rand(200, A, generator=gen) * 2 - 1
    model.fit_normalizer(obs, actions, next_observations=obs + 0.01 * torch.randn_like(obs))
    model.checks = Passed()
    return model


def make_env(model: RCVAEEnsemble) -> RCVAEEnsembleEnv:
    return RCVAEEnsembleEnv(model, pusher_reward, pusher_success, seed=0)


def set_decoder(model: RCVAEEnsemble, mean: torch.Tensor, raw_log_std: float) -> None:
    """Make the decoder output a constant ``mean [E, 1]`` change and log-std for every input."""
    last = model.decoder[-1]
    d = CONFIG.predicted_dim
    with torch.no_grad():
        last.weight.zero_()
        last.bias[:, :d] = mean
        last.bias[:, d:] = raw_log_std


def boundary(**kwargs) -> SuccessBoundary:
    kwargs.setdefault("time_limit", T)
    kwargs.setdefault("dt", DT)
    return SuccessBoundary.ball(obs_indices("ball"), 0.03, target=obs_indices("target"), **kwargs)


@pytest.fixture
def env() -> RCVAEEnsembleEnv:
    return make_env(make_ensemble())


@pytest.fixture
def starts() -> torch.Tensor:
    return torch.randn(3, S, generator=torch.Generator().manual_seed(1)) * 0.1


@pytest.fixture
def plan() -> torch.Tensor:
    return torch.rand(3, T, A, generator=torch.Generator().manual_seed(2)) * 2 - 1


def make_assessor(env, **kwargs) -> CompetencyAssessor:
    kwargs.setdefault("bin_width", resolution_tensor())
    kwargs.setdefault("dim_names", OBSERVATION_NAMES)
    kwargs.setdefault("samples_per_member", N)
    return CompetencyAssessor(env, kwargs.pop("boundary", boundary()), **kwargs)


def seeded(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def assert_same(a: TensorDict, b: TensorDict) -> None:
    assert a.batch_size == b.batch_size
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        assert torch.equal(a.get(key), b.get(key)), key


# ----------------------------------------------------------------- report contents
def test_report_keys_shapes_and_values(env, starts, plan):
    report = make_assessor(env).assess(starts, actions=plan, generator=seeded())
    data = report.data
    assert data.batch_size == (3,) and report.batch_size == (3,)
    for name in ("total", "aleatoric", "epistemic"):
        assert data["uncertainty", name].shape == (3, T, S)
        assert data["uncertainty", "time_mean", name].shape == (3, S)
        assert data["uncertainty", "summary", name].shape == (3,)
        assert data["uncertainty", "by_dim", "ball_vx", name].shape == (3, T)
        assert data["competency", "outcome_uncertainty", name].shape == (3,)
    assert data["uncertainty", "peak_step"].dtype == torch.int64
    assert torch.equal(data["uncertainty", "peak_step"], data["uncertainty", "total"].argmax(1))
    peak_s = (data["uncertainty", "peak_step"] + 1) * DT
    assert torch.allclose(data["uncertainty", "peak_time_s"], peak_s.float())
    for key in ("p_success", "p_success_low", "p_success_high"):
        assert data["competency", key].shape == (3,)
    assert data["competency", "p_success_member"].shape == (3, E)
    assert data["competency", "success"].shape == (3, E, N)
    assert data["competency", "time_to_success", "first_step"].shape == (3, E, N)
    assert data["competency", "time_to_success", "success_by_step"].shape == (3, T)
    assert data["competency", "time_to_success", "median_s"].shape == (3,)
    assert torch.equal(data["observation"], starts)
    assert "rollout" not in data.keys()
    assert report.time_limit == T and report.dt == DT

    # the same numbers as the metrics on env.imagine with the same noise
    rollout = env.imagine(starts, plan, samples_per_member=N, generator=seeded())
    observed = TensorDict({"observation": rollout["observation"]}, batch_size=rollout.batch_size)
    # the assessor's histogram corrects the shuffle bias by default, from a generator seeded
    # by the noise source's state (the same generator, the same shuffles)
    from rcvae_torchrl.competency.assessor import _derived_generator

    shuffled = UncertaintyMetric(
        resolution_tensor(), bias_correction="shuffle", generator=_derived_generator(seeded())
    )
    u = shuffled(observed)["uncertainty"]
    c = SuccessMetric(boundary())(observed)["competency"]
    assert torch.equal(data["uncertainty", "epistemic"], u["epistemic"])
    plain = make_assessor(env, bias_correction="none").assess(
        starts, actions=plan, generator=seeded()
    )
    u = UncertaintyMetric(resolution_tensor())(observed)["uncertainty"]
    assert torch.equal(plain.data["uncertainty", "epistemic"], u["epistemic"])
    assert torch.equal(data["competency", "p_success"], c["p_success"])
    assert torch.equal(data["competency", "success"], c["success"].permute(2, 0, 1))
    assert torch.equal(data["competency", "p_success_member"], c["p_success_member"].T)


def test_rollouts_on_request(env, starts, plan):
    assessor = make_assessor(env)
    report = assessor.assess(starts, actions=plan, generator=seeded(), return_rollouts=True)
    rollout = report.data["rollout"]
    assert rollout.batch_size == (3, E, N, T)
    assert rollout["observation"].shape == (3, E, N, T, S)
    assert torch.equal(rollout["action"][:, 0, 0], plan)
    plain = assessor.assess(starts, actions=plan, generator=seeded())
    assert_same(report.data.exclude("rollout"), plain.data)


def test_batched_start_states_and_shared_plan(env, starts):
    grid = starts[:2].expand(2, 2, S)  # [2, 2, S]
    report = make_assessor(env).assess(grid, actions=torch.zeros(T, A), generator=seeded())
    assert report.batch_size == (2, 2)
    assert report.data["uncertainty", "total"].shape == (2, 2, T, S)
    assert report.data["competency", "success"].shape == (2, 2, E, N)
    assert report[1, 0].batch_size == ()
    single = make_assessor(env).assess(starts[0], actions=torch.zeros(T, A))
    assert single.batch_size == ()
    assert single.data["uncertainty", "total"].shape == (T, S)


def test_chunks_match_separate_calls(env, starts, plan):
    chunked = make_assessor(env, start_chunk=2).assess(starts, actions=plan, generator=seeded())
    whole = make_assessor(env)
    gen = seeded()
    first = whole.assess(starts[:2], actions=plan[:2], generator=gen)
    second = whole.assess(starts[2:], actions=plan[2:], generator=gen)
    assert_same(chunked.data, torch.cat([first.data, second.data]))


# ----------------------------------------------------------------- loops, generator, forward
def test_closed_loop_constant_policy_equals_open_loop(env, starts):
    action = torch.tensor([0.3, -0.7])

    def policy(obs):
        return action.expand(*obs.shape[:-1], A)

    assessor = make_assessor(env)
    closed = assessor.assess(starts, policy=policy, generator=seeded())
    opened = assessor.assess(starts, actions=action.expand(T, A), generator=seeded())
    assert_same(closed.data, opened.data)


def test_closed_loop_tensordict_policy_acts_on_imagined_states(env, starts):
    policy = TensorDictModule(
        lambda obs: torch.tanh(obs[..., :A] * 5), in_keys=["observation"], out_keys=["action"]
    )
    assessor = make_assessor(env, policy=policy)
    rollout = assessor.assess(starts, generator=seeded(), return_rollouts=True).data["rollout"]
    assert rollout.batch_size == (3, E, N, T)  # horizon = the boundary's time limit
    expected = torch.tanh(rollout["observation"][..., :-1, :A] * 5)
    assert torch.allclose(rollout["action"][..., 1:, :], expected)
    assert torch.allclose(rollout["action"][:, 0, 0, 0], torch.tanh(starts[:, :A] * 5))


def test_determinism_under_a_generator(env, starts, plan):
    assessor = make_assessor(env)
    one = assessor.assess(starts, actions=plan, generator=seeded(3))
    two = assessor.assess(starts, actions=plan, generator=seeded(3))
    other = assessor.assess(starts, actions=plan, generator=seeded(4))
    assert_same(one.data, two.data)
    assert one.summary() == two.summary()
    assert not torch.equal(one.data["uncertainty", "total"], other.data["uncertainty", "total"])


def test_forward_reads_the_tensordict_and_set_keys(env, starts, plan):
    assessor = make_assessor(env)
    td = TensorDict({"observation": starts, "actions": plan}, batch_size=[3])
    torch.manual_seed(0)
    env.generator.manual_seed(5)
    out = assessor(td)
    direct = assessor.assess(starts, actions=plan, generator=seeded(5))
    assert_same(out, direct.data)

    assessor.set_keys(observation=("start", "obs"), actions="plan", uncertainty="u")
    td = TensorDict({("start", "obs"): starts, "plan": plan}, batch_size=[3])
    out = assessor(td)
    assert out["u", "total"].shape == (3, T, S)
    assert out["start", "obs"].shape == (3, S)
    report = assessor.assess(td, actions=plan)
    assert "Most uncertain" in report.summary(index=0)  # the report knows the keys
    with pytest.raises(ValueError, match="reward: not a key of"):
        assessor.set_keys(reward="r")


def test_forward_without_actions_uses_the_default_policy(env, starts):
    assessor = make_assessor(env, policy=lambda obs: torch.zeros(*obs.shape[:-1], A))
    out = assessor(TensorDict({"observation": starts}, batch_size=[3]))
    assert out["competency", "p_success"].shape == (3,)


def test_joint_estimator_has_no_dimension_breakdown(env, starts, plan):
    assessor = make_assessor(env, estimator="gaussian", bin_width=None, joint=True)
    report = assessor.assess(starts, actions=plan)
    assert report.data["uncertainty", "total"].shape == (3, T)
    assert "peak_step" not in report.data["uncertainty"].keys()
    text = report.summary(index=0)
    assert "Most of the doubt is" in text and "Most uncertain" not in text


# ----------------------------------------------------------------- summary
def hand_report(dt=0.05, live=None, **summary) -> CompetencyReport:
    """A one-start report with the given time-mean bits (and, with ``live``, bits per live
    step, as an assessment with ``episode_end`` gives)."""
    summary = {"aleatoric": 0.4, "epistemic": 0.7, "total": 1.1, **summary}
    uncertainty = {
        "summary": {k: torch.tensor(v) for k, v in summary.items()},
        "time_mean": {"total": torch.tensor([0.1, 0.9, 0.0, 0.5])},
        "peak_step": torch.tensor([0, 89, 3, 19]),
    }
    if live is not None:
        uncertainty["per_live_step"] = {k: torch.tensor(v) for k, v in live.items()}
    data = TensorDict(
        {
            "competency": {
                "p_success": torch.tensor(0.84),
                "p_success_low": torch.tensor(0.78),
                "p_success_high": torch.tensor(0.89),
            },
            "uncertainty": uncertainty,
        }
    )
    return CompetencyReport(data, ("a", "b", "c", "d"), 600, dt, 0.95)


#: what a report of a world model without a novelty check says of novelty
NOT_JUDGED = (
    "Novelty not judged: the world model has no novelty check (ensemble.novelty, which "
    "train_ensemble fits; or StateNovelty.from_episodes), so nothing here says whether the "
    "start states and imagined states are like those it was trained on."
)


#: what a report without a forecast check says beside each start's P
UNCHECKED = (
    "Unchecked: no check of these forecasts against real episodes is attached "
    "(with_forecast_check), so nothing shows this one right."
)


def test_summary_text_rules_on_known_numbers():
    assert hand_report().summary() == (
        f"P(success within 30 s) = 0.84 (95% interval 0.78–0.89). {UNCHECKED} {NOT_JUDGED} "
        "Most of the doubt is epistemic (0.70 of 1.10 bits): the model has not seen states "
        "like this. Most uncertain: b (time mean 0.90 bits, peak at t = 4.5 s), "
        "d (time mean 0.50 bits, peak at t = 1 s)."
    )
    steps = str(replace_top_k(hand_report(dt=None, aleatoric=0.7, epistemic=0.4), 5))
    assert steps.startswith("P(success within 600 steps)")
    assert "Most of the doubt is aleatoric (0.70 of 1.10 bits)" in steps
    assert "b (time mean 0.90 bits, peak at step 90)" in steps
    assert "c (mean" not in steps  # zero bits: never named
    tie = hand_report(aleatoric=0.5, epistemic=0.5, total=1.0).summary()
    assert "Most of the doubt is aleatoric (0.50 of 1.00 bits)" in tie
    none = hand_report(aleatoric=0.0, epistemic=0.0, total=0.0).summary()
    assert "No doubt about the imagined states (0.00 bits)" in none
    # binned bits under 1 in all: which part is larger is chance, and no cause is named
    little = dataclasses.replace(
        hand_report(aleatoric=0.17, epistemic=0.2, total=0.37), measure={"estimator": "histogram"}
    )
    said = (
        "Little doubt about the imagined states (0.37 bits, under 1: at the declared "
        "resolution they mostly share their bins): 0.17 aleatoric and 0.20 epistemic."
    )
    assert said in little.summary() and said in little.overall()
    assert "has not seen states like this" not in little.summary() + little.overall()
    joint = hand_report(aleatoric=0.17, epistemic=0.2, total=0.37)  # no estimator known
    assert "Most of the doubt is epistemic (0.20 of 0.37 bits)" in joint.summary()


def test_summary_against_a_reference_names_what_rose():
    from rcvae_torchrl.competency import Reference

    reference = Reference(aleatoric=0.4, epistemic=0.2)
    epistemic = hand_report(aleatoric=0.44, epistemic=0.5, total=0.94).with_reference(reference)
    assert (
        "Against the in-distribution reference, epistemic uncertainty rose 2.5x (0.20 -> 0.50 "
        "bits) and aleatoric 1.1x (0.40 -> 0.44 bits): the rise is epistemic, the model has not "
        "seen states like this"
    ) in epistemic.summary()
    # aleatoric far above epistemic in absolute bits, but epistemic is what changed
    big = hand_report(aleatoric=9.0, epistemic=0.6, total=9.6).with_reference(Reference(8.5, 0.2))
    assert "the rise is epistemic" in big.summary() and "Most of the doubt" not in big.summary()
    noisy = hand_report(aleatoric=1.0, epistemic=0.22, total=1.22).with_reference(reference)
    assert "the rise is aleatoric, the members agree that the states vary more" in str(noisy)
    same = hand_report(aleatoric=0.41, epistemic=0.21, total=0.62).with_reference(reference)
    assert (
        "epistemic uncertainty stayed at 1.0x (0.20 -> 0.21 bits) and aleatoric 1.0x (0.40 -> "
        "0.41 bits): neither part rose 1.3x or more, the doubt is as in the reference (no sign "
        "of states the model has not seen, which does not rule them out: a check against real "
        "episodes can)."
    ) in same.summary()
    # a ratio printed as 1.0x neither rose nor fell, whichever side of 1 it lies
    below = hand_report(aleatoric=0.39, epistemic=0.193, total=0.583).with_reference(reference)
    assert "epistemic uncertainty stayed at 1.0x (0.20 -> 0.19 bits) and aleatoric 1.0x" in (
        below.summary()
    )
    lower = hand_report(aleatoric=0.2, epistemic=0.06, total=0.26).with_reference(reference)
    assert (
        "epistemic uncertainty fell to 0.3x (0.20 -> 0.06 bits) and aleatoric fell to 0.5x "
        "(0.40 -> 0.20 bits): neither part rose 1.3x or more, the epistemic and aleatoric doubt "
        "fell below the reference's."
    ) in lower.summary()
    # a ratio just below the rise is not printed as the rise (1.26 as 1.3x), nor one just
    # past a fall as no fall (0.76 as 0.8x)
    near = hand_report(aleatoric=0.504, epistemic=0.152, total=0.656).with_reference(reference)
    assert (
        "epistemic uncertainty fell to 0.76x (0.20 -> 0.15 bits) and aleatoric rose 1.26x (0.40 "
        "-> 0.50 bits): neither part rose 1.3x or more, the epistemic doubt fell below the "
        "reference's."
    ) in near.summary()
    mixed = hand_report(aleatoric=0.48, epistemic=0.1, total=0.58).with_reference(reference)
    assert "neither part rose 1.3x or more, the epistemic doubt fell below the reference's." in str(
        mixed
    )
    from_report = hand_report(aleatoric=0.4, epistemic=0.8).with_reference(
        hand_report(aleatoric=0.4, epistemic=0.2), name="training starts"
    )
    text = from_report.summary()  # a one-start reference is named with its count
    assert (
        "Against the training starts (of only 1 start state), epistemic uncertainty rose 4.0x"
        in text
    )
    with pytest.raises(TypeError, match="reference: expected a CompetencyReport or a Reference"):
        hand_report().with_reference(0.5)
    with pytest.raises(ValueError, match="rise: expected a factor > 1"):
        Reference(1.0, 1.0, rise=0.9)


def test_with_a_warning_the_overview_gives_no_cause_either():
    """As each start's paragraph: a model that failed its checks may take missing knowledge
    for chance, over all starts too."""
    failed = replace_warning(_starts_report([0.9, 0.8]), "the world model has not learned b")
    text = failed.with_reference(_starts_report([0.2] * 12)).overall()
    assert text.startswith("Warning: the world model has not learned b. Over 2 start states")
    assert "Uncertainty: 0.40 bits aleatoric and 0.85 epistemic of 1.25; with the warning" in text
    assert "the rise is" not in text and "has not seen states" not in text


def test_a_passed_check_whose_forecasts_miss_per_start_cautions_each_start():
    """Right on average, wrong per task: each start's paragraph says so beside its P. (80
    starts: forecasts this scattered need that many for an interval of the mean gap within the
    check's tolerance, ±0.2.)"""
    from rcvae_torchrl.training import OutcomeCheck

    g = torch.Generator().manual_seed(1)
    chance = torch.rand(80, generator=g, dtype=torch.float64)
    real = torch.rand(80, 20, generator=g, dtype=torch.float64) < chance[:, None]
    # each start off by 0.2 or so, the ranking kept: better than one number for all
    noisy = (chance + 0.2 * torch.randn(80, generator=g, dtype=torch.float64)).clamp(0.02, 0.98)
    scattered = OutcomeCheck.from_outcomes(noisy, real)
    assert scattered.passed and scattered.scattered and scattered.brier_skill > 0.1
    report = _starts_report([0.3, 0.2]).with_forecast_check(scattered)
    assert report.trustworthy
    caution = (
        "Caution: on other start states the forecasts, right on average, missed their own "
        f"start's real rate by about {scattered.excess_error:.2f} beyond chance; the interval "
        "above covers only the imagined samples' chance."
    )
    assert report.summary(index=1).startswith(
        f"P(success within 30 s) = 0.84 (95% interval 0.78–0.89). {caution} {NOT_JUDGED} "
        "Most of the doubt"
    )
    fair = OutcomeCheck.from_outcomes(chance.clamp(0.02, 0.98), real)
    assert fair.passed and not fair.scattered
    assert "Caution" not in _starts_report([0.3]).with_forecast_check(fair).summary(index=0)
    # mean right, each start wrong the other way: worse than one number for all, no pass
    mirrored = OutcomeCheck.from_outcomes(1 - chance, real)
    assert mirrored.precise and not mirrored.biased and mirrored.scattered
    assert mirrored.brier_skill < 0 and mirrored.no_better_than_constant
    assert not mirrored.passed and mirrored.verdict == "no better than a constant"
    mirrored_report = _starts_report([0.3]).with_forecast_check(mirrored)
    assert not mirrored_report.trustworthy
    assert mirrored_report.warning.endswith(
        "for every start (Brier skill "
        f"{mirrored.brier_skill:+.3f} over the real episodes): they do not tell one start "
        "state's task from another, so the check has not passed"
    )


def _starts_report(epistemic: list[float], aleatoric: float = 0.4) -> CompetencyReport:
    """A report of ``len(epistemic)`` start states with these time-mean epistemic bits."""
    data = torch.stack(
        [hand_report(aleatoric=aleatoric, epistemic=e, total=aleatoric + e).data for e in epistemic]
    )
    return CompetencyReport(data, ("a", "b", "c", "d"), 600, 0.05, 0.95)


def test_one_start_rose_only_beyond_the_spread_of_the_references_own_starts():
    """In-distribution start states spread around their mean: against the mean alone, 6 of
    20 of the reference's own starts read as states the model has not seen (as 1 to 5 of 30
    did on a reacher); against the level a new in-distribution start stays at or below with
    probability 0.95 (the conformal level: with 20 starts, their largest), none does."""
    from rcvae_torchrl.competency import Reference

    reference = _starts_report([0.1 + 0.02 * i for i in range(20)])  # mean 0.29
    inside = hand_report(aleatoric=0.4, epistemic=0.45, total=0.85).with_reference(reference)
    # the ceil(21 x 0.95) = 20th smallest of 20; an interpolated quantile (0.461) would be
    # passed by about 9 % of new in-distribution starts, not 5 %
    assert inside.reference.epistemic_high == pytest.approx(0.48)
    assert inside.reference.aleatoric_high == pytest.approx(0.4)
    assert (
        "epistemic uncertainty rose 1.6x (0.29 -> 0.45 bits) and aleatoric stayed at 1.0x (0.40 "
        "-> 0.40 bits): neither part rose beyond the reference's own start states: 95% of such "
        "starts stay at or below 0.48 epistemic bits."
    ) in inside.summary()
    beyond = hand_report(aleatoric=0.4, epistemic=0.6, total=1.0).with_reference(reference)
    assert "the rise is epistemic, the model has not seen states like this" in beyond.summary()
    own = reference.with_reference(reference)
    assert not any("the rise is" in own.summary(index=i) for i in range(20))
    # with 10 starts the largest covers 10/11 of new ones: that is what the words say
    few = hand_report(aleatoric=0.4, epistemic=0.26, total=0.66).with_reference(
        _starts_report([0.1 + 0.02 * i for i in range(10)])
    )
    assert few.reference.quantile == pytest.approx(10 / 11)
    assert few.reference.epistemic_high == pytest.approx(0.28)
    assert "91% of such starts stay at or below 0.28 epistemic bits" in few.summary()
    by_mean = reference.with_reference(Reference(0.4, 0.29))  # no spread known: the mean alone
    assert sum("the rise is" in by_mean.summary(index=i) for i in range(20)) == 6
    # a mean over start states is compared with the reference's mean
    shifted = _starts_report([0.45] * 12).with_reference(reference)
    assert shifted.cause() == "epistemic"
    # ...but where no start rose beyond the reference's spread, the mean's rise is not called
    # the model's ignorance (a point-mass trial: 1.3x of 0.07 bits, 0 of 10 starts rising, read
    # "the model has not seen states like this: more data here would reduce it")
    assert (
        "epistemic uncertainty rose 1.6x (0.29 -> 0.45 bits) and aleatoric stayed at 1.0x (0.40 "
        "-> 0.40 bits): neither part rose beyond the reference's own start states: 95% of such "
        "starts stay at or below 0.48 epistemic bits. Start state by start state, the rise is "
        "epistemic in 0 of 12" in shifted.overall()
    )
    assert "more data here" not in shifted.overall()
    outliers = _starts_report([0.3] * 10 + [1.0] * 2).with_reference(reference)
    assert outliers.cause() == "epistemic"  # the mean 0.42 rose 1.4x, by two starts
    assert outliers.overall().endswith(
        "the rise is epistemic, the model has not seen states like this: more data here would "
        "reduce it. Start state by start state, the rise is epistemic in 2 of 12 and aleatoric "
        f"in 0. {NOT_JUDGED} No check of these forecasts against real episodes is attached to "
        "this report (with_forecast_check)."
    )
    # a stricter level: fewer of the reference's own starts above it
    assert own.reference.quantile == 0.95
    strict = reference.with_reference(reference, quantile=0.5)
    assert strict.reference.epistemic_high == pytest.approx(0.3)  # the 11th smallest of 20
    with pytest.raises(ValueError, match=r"quantile: expected a share of start states in \(0, 1\)"):
        hand_report().with_reference(reference, quantile=1.0)
    with pytest.raises(ValueError, match=r"reference.epistemic_high: expected bits >= 0"):
        Reference(0.4, 0.2, epistemic_high=-0.1)


def test_a_forecast_check_that_did_not_pass_opens_every_summary():
    """The check of the agent's forecasts against real episodes of other starts: a bias makes
    the report untrustworthy and its bits causeless; a passed check closes the overview."""
    from rcvae_torchrl.training import OutcomeCheck

    g = torch.Generator().manual_seed(0)
    real = torch.rand(20, 5, generator=g) < 0.3  # 20 held-out starts, 5 real episodes each
    optimistic = OutcomeCheck.from_outcomes(torch.full((20,), 0.9), real, what="the forecasts")
    assert optimistic.biased
    report = _starts_report([0.7, 0.2]).with_forecast_check(optimistic)
    on_others = f"forecast check on other start states: {optimistic.describe()}"
    assert not report.trustworthy and report.warning == on_others
    for i in range(2):
        text = report.summary(index=i)
        assert text.startswith(
            "Warning: forecast check on other start states: the forecasts are too optimistic: "
            "from 20 start states"
        )
        assert "with the warning above this split does not say" in text
        assert "the model has not seen states like this" not in text
    assert report.overall().startswith("Warning: forecast check on other start states: the")
    fair = OutcomeCheck.from_outcomes(real.float().mean(1).clamp(0.05, 0.95), real)
    assert fair.passed
    checked = _starts_report([0.7, 0.2]).with_forecast_check(fair)
    assert checked.trustworthy and checked.summary(index=0).startswith("P(success within 30 s)")
    assert checked.overall().endswith(f" Forecast check on other start states: {fair.describe()}.")
    few = OutcomeCheck.from_outcomes(torch.full((4,), 0.3), real[:4])  # too few starts to tell
    assert (
        "are not measured by the outcome check: 4 start states"
        in hand_report().with_forecast_check(few).warning
    )
    both = replace_warning(_starts_report([0.7]), "the world model has not learned b")
    assert both.with_forecast_check(optimistic).warning.startswith(
        "the world model has not learned b; forecast check on other start states: the forecasts"
    )
    # against a reference per live step, the causeless bits are those bits too, named so
    live = {"aleatoric": 4.0, "epistemic": 1.0, "total": 5.0}
    compared = hand_report(live=live).with_reference(hand_report(live=live))
    assert (
        "Uncertainty: 4.00 bits per live step aleatoric and 1.00 epistemic of 5.00; with the "
        "warning above"
    ) in compared.with_forecast_check(optimistic).summary()
    with pytest.raises(TypeError, match="check: expected an OutcomeCheck"):
        hand_report().with_forecast_check(0.3)


def replace_warning(report: CompetencyReport, warning: str) -> CompetencyReport:
    import dataclasses

    return dataclasses.replace(report, model_warning=warning)


def test_episodes_that_end_sooner_are_compared_per_live_step():
    """Time means that fell only because the imagined episodes ended sooner (failing early)
    are not read as less doubt: two reports with bits per live step compare those."""
    reference = hand_report(
        aleatoric=4.0,
        epistemic=1.0,
        total=5.0,
        live={
            "aleatoric": 4.0,
            "epistemic": 1.0,
            "total": 5.0,
        },
    )
    early = hand_report(
        aleatoric=0.5,
        epistemic=0.25,
        total=0.75,
        live={
            "aleatoric": 4.2,
            "epistemic": 2.0,
            "total": 6.2,
        },
    )
    compared = early.with_reference(reference)
    assert compared.reference.per_live_step and compared.cause() == "epistemic"
    assert (
        "(of only 1 start state), epistemic uncertainty rose 2.0x (1.00 -> 2.00 bits per live "
        "step) and aleatoric stayed at 1.0x (4.00 -> 4.20 bits per live step): the rise is "
        "epistemic"
    ) in compared.summary()
    assert "mean P(success within 30 s) = 0.84. Against" in compared.overall()
    # without bits per live step on both sides, the time means (which fell) are compared
    plain = hand_report(aleatoric=0.5, epistemic=0.25, total=0.75).with_reference(reference)
    assert not plain.reference.per_live_step and plain.cause() is None
    assert "(1.00 -> 0.25 bits)" in plain.summary() and "fell below" in plain.summary()
    with pytest.raises(ValueError, match="reference: its bits are per live step, but this report"):
        hand_report().with_reference(Reference(1.0, 1.0, per_live_step=True))
    with pytest.raises(ValueError, match="per_live_step: the report has no bits per live step"):
        hand_report().mean_bits(per_live_step=True)


def test_a_model_that_failed_its_checks_is_flagged_in_every_summary(env, starts, plan):
    class Failed:
        passed = False

        def message(self):
            return "the world model has not learned obs[3] (one-step error 1 vs 1)"

    env.ensemble.checks = Failed()
    report = make_assessor(env).assess(starts, actions=plan, generator=seeded())
    assert not report.trustworthy
    for i in range(3):
        text = report.summary(index=i)
        assert text.startswith("Warning: the world model has not learned obs[3]")
        # its aleatoric / epistemic split is no evidence: no cause is given for the doubt
        assert "this split does not say whether more data would help" in text
        assert "Most of the doubt" not in text and "by an error they all make" not in text
    env.ensemble.checks = Passed()
    passed = make_assessor(env).assess(starts, actions=plan, generator=seeded())
    # self-checks passed, and no forecast check yet: nothing has shown the forecasts right
    assert passed.warning == "" and not passed.trustworthy
    assert passed.with_forecast_check(_passed_check(task=passed.task)).trustworthy


def _passed_check(task=None):
    """A forecast check that passed: forecasts of 0.5 against 60 starts' 40 runs drawn at 0.5."""
    from rcvae_torchrl.training import OutcomeCheck

    real = torch.rand(60, 40, generator=seeded(3)) < 0.5
    check = OutcomeCheck.from_outcomes(torch.full((60,), 0.5, dtype=torch.float64), real, task=task)
    assert check.passed
    return check


def test_a_forecast_check_vouches_only_for_reports_of_its_task(env, starts, plan):
    """A pendulum trial: a check that passed on a balance task made a swing-up report of the
    same model 'trustworthy' (0.686 forecast against 0.520 real). A report knows its task (the
    boundary's predicates, the deadline, the world model's weights) and so does a check made
    from one; a check of another task is refused, and one of bare numbers ties to none."""
    from rcvae_torchrl.training import OutcomeCheck

    report = make_assessor(env).assess(starts, actions=plan, generator=seeded())
    again = make_assessor(env).assess(starts[:2], actions=plan[:2], generator=seeded(5))
    assert report.task and again.task == report.task  # other starts, the same task
    real = torch.rand(60, 40, generator=seeded(3)) < 0.5
    forecast = torch.full((60,), 0.5, dtype=torch.float64)
    same = OutcomeCheck.from_outcomes(forecast, real, task=report.task)
    assert report.with_forecast_check(same).trustworthy
    assert OutcomeCheck.from_dict(same.as_dict()).task == report.task

    def refused(tasked, named):
        said = rf"^check: made for another task than this report's: {named}; check this"
        with pytest.raises(ValueError, match=said):
            report.with_forecast_check(OutcomeCheck.from_outcomes(forecast, real, task=tasked.task))

    wider = make_assessor(
        env,
        boundary=SuccessBoundary.ball(
            obs_indices("ball"), 0.05, target=obs_indices("target"), time_limit=T, dt=DT
        ),
    ).assess(starts, actions=plan, generator=seeded())
    sooner = make_assessor(env, boundary=boundary(time_limit=T - 1), horizon=T).assess(
        starts, actions=plan, generator=seeded()
    )
    other_model = make_assessor(make_env(make_ensemble(seed=1))).assess(
        starts, actions=plan, generator=seeded()
    )
    # the refusal names the part that differs, not two digests
    for tasked, named in [
        (wider, r"another boundary \(its predicates' code or values\)"),
        (sooner, rf"another deadline \({T - 1} steps there, {T} steps here\)"),
        (other_model, r"another world model \(its weights, config or functions\)"),
    ]:
        assert tasked.task != report.task, named
        refused(tasked, named)
    bare = report.with_forecast_check(OutcomeCheck.from_outcomes(forecast, real))
    assert not bare.trustworthy
    assert bare.warning.startswith(
        "the forecast check attached was built from bare forecasts, which ties it to no task"
    )
    assert bare.summary(index=0).startswith("Warning: the forecast check attached was built")
    # a report built by hand knows no task, and takes any check
    assert _starts_report([0.3]).with_forecast_check(_passed_check()).trustworthy
    said = r"^task: expected the task of the forecasts' report, got another boundary \(its pr"
    with pytest.raises(ValueError, match=said):
        OutcomeCheck.from_outcomes(report, torch.ones(3, 2, dtype=torch.bool), task=wider.task)
    with pytest.raises(TypeError, match=r"task: expected a report's task \(a str\), got int"):
        OutcomeCheck.from_outcomes(forecast, real, task=3)


def test_a_model_without_self_checks_is_never_presented_as_trustworthy(env, starts, plan):
    env.ensemble.checks = None  # trained with checks=False, or not trained
    report = make_assessor(env).assess(starts, actions=plan, generator=seeded())
    assert not report.trustworthy
    text = report.summary(index=0)
    assert text.startswith("Warning: the world model has no self-checks (trained with checks=Fa")
    assert "ensemble.checks = rcvae_torchrl.training.check_model(ensemble, held_out" in text
    assert "with the warning above this split does not say" in text


def replace_top_k(report: CompetencyReport, top_k: int) -> CompetencyReport:
    return CompetencyReport(report.data, report.dim_names, 600, report.dt, 0.95, top_k)


def dominant(report: CompetencyReport, index: int) -> str:
    s = report.data[index]["uncertainty", "summary"]
    return "epistemic" if s["epistemic"] > s["aleatoric"] else "aleatoric"


def check_summary_numbers(report: CompetencyReport, index: int) -> str:
    """The paragraph of ``index`` quotes the report's own numbers, by the documented rules."""
    one = report.data[index]
    text = report.summary(index=index)
    c, u = one["competency"], one["uncertainty"]
    p, low, high = (float(c[k]) for k in ("p_success", "p_success_low", "p_success_high"))
    assert text.startswith(
        f"P(success within {T * DT:g} s) = {p:.2f} (95% interval {low:.2f}–{high:.2f})."
    )
    kind = dominant(report, index)
    bits, total = float(u["summary", kind]), float(u["summary", "total"])
    assert f"Most of the doubt is {kind} ({bits:.2f} of {total:.2f} bits)" in text
    top = torch.argsort(u["time_mean", "total"], descending=True, stable=True)[:2].tolist()
    named = ", ".join(
        f"{OBSERVATION_NAMES[d]} (time mean {float(u['time_mean', 'total'][d]):.2f} bits, peak at "
        f"t = {round((int(u['peak_step'][d]) + 1) * DT, 6):g} s)"
        for d in top
    )
    assert text.endswith(f"Most uncertain: {named}.")
    return text


def test_summary_when_epistemic_dominates():
    model = make_ensemble()
    set_decoder(model, torch.tensor([[-2.0], [0.0], [2.0]]), -20.0)  # members move apart
    report = make_assessor(make_env(model)).assess(
        torch.zeros(1, S), actions=torch.zeros(T, A), generator=seeded()
    )
    u = report.data[0]["uncertainty", "summary"]
    assert u["epistemic"] > 5 * u["aleatoric"]
    text = check_summary_numbers(report, 0)
    assert "epistemic" in text and "the model has not seen states like this" in text


def test_summary_when_aleatoric_dominates():
    model = make_ensemble()
    with torch.no_grad():
        for param in model.parameters():
            param.copy_(param[:1].expand_as(param))  # every member = member 0
    set_decoder(model, torch.zeros(E, 1), 5.0)  # wide, identical noise
    assessor = make_assessor(make_env(model), bin_width=0.05, samples_per_member=100)
    report = assessor.assess(torch.zeros(1, S), actions=torch.zeros(T, A), generator=seeded())
    u = report.data[0]["uncertainty", "summary"]
    assert u["aleatoric"] > 5 * u["epistemic"]
    text = check_summary_numbers(report, 0)
    assert "aleatoric" in text and "the members agree that the states vary this much" in text


def test_summary_of_a_batch(env, starts, plan):
    report = make_assessor(env).assess(starts, actions=plan, generator=seeded())
    paragraphs = report.summary().split("\n\n")
    assert len(paragraphs) == 3
    for i, paragraph in enumerate(paragraphs):
        assert paragraph == f"Start state {i}: {check_summary_numbers(report, i)}"
    assert str(report) == report.summary()
    assert report[1].summary() == report.summary(index=1)
    grid = make_assessor(env).assess(starts[:2].expand(2, 2, S), actions=torch.zeros(T, A))
    assert "Start state (1, 0): P(success" in grid.summary()
    assert grid.summary(index=(1, 0)) == grid[1, 0].summary()
    with pytest.raises(ValueError, match="index: expected one start state"):
        grid.summary(index=1)


# ----------------------------------------------------------------- errors
def test_a_policy_reading_the_real_envs_entries_is_named(env):
    # in imagination the world model gives a policy "observation" alone
    policy = TensorDictModule(
        lambda cos, sin: torch.zeros(*cos.shape[:-1], A),
        in_keys=["cos", "sin"],
        out_keys=["action"],
    )
    with pytest.raises(KeyError, match=r"policy: reads \['cos', 'sin'\], but in imagination"):
        make_assessor(env).assess(torch.zeros(2, S), policy=policy)
    writes_act = TensorDictModule(lambda s: s[..., :A], in_keys=["observation"], out_keys=["act"])
    with pytest.raises(KeyError, match=r"policy: writes \['act'\], not 'action'; give it out_k"):
        make_assessor(env).assess(torch.zeros(2, S), policy=writes_act)


def test_argument_errors(env):
    with pytest.raises(ValueError, match=r"bin_width: expected a scalar or a tensor of shape"):
        make_assessor(env, bin_width=torch.full((3,), 0.1))
    with pytest.raises(ValueError, match="horizon: expected a positive integer, got 0"):
        make_assessor(env, horizon=0)
    with pytest.raises(ValueError, match="horizon: expected a positive integer, got -3"):
        make_assessor(env, horizon=-3)
    with pytest.raises(ValueError, match="dim_names: expected 14 names"):
        make_assessor(env, dim_names=["x"])
    with pytest.raises(ValueError, match="samples_per_member: expected a positive integer"):
        make_assessor(env, samples_per_member=0)
    with pytest.raises(ValueError, match=r"dt: expected the boundary's dt = 0\.05"):
        make_assessor(env, dt=0.1)
    with pytest.raises(
        TypeError, match="model_env: expected a world model with an ensemble and an imagine method"
    ):
        CompetencyAssessor(object(), boundary(), bin_width=0.1)
    single = RCVAEEnsembleEnv(RCVAEEnsemble(CONFIG, 1), pusher_reward, pusher_success)
    with pytest.raises(ValueError, match="E >= 2 members"):
        CompetencyAssessor(single, boundary(), bin_width=0.1)
    with pytest.raises(TypeError, match="boundary: expected a SuccessBoundary"):
        CompetencyAssessor(env, lambda obs: obs, bin_width=0.1)


def test_a_world_model_is_recognised_by_its_attributes(env):
    """A wrapper that forwards ``ensemble`` and ``imagine`` dynamically (as ``nn.Module`` serves
    its submodules) is accepted: protocol ``isinstance`` checks read attributes statically from
    Python 3.12 on and would refuse it."""

    class Forwarding:
        def __getattr__(self, name):
            return getattr(env, name)

    assert CompetencyAssessor(Forwarding(), boundary(), bin_width=0.1).model_env is not None


def test_assess_errors(env, starts, plan):
    assessor = make_assessor(env)
    with pytest.raises(ValueError, match="got both"):
        assessor.assess(starts, policy=lambda obs: obs[..., :A], actions=plan)
    with pytest.raises(ValueError, match="got neither"):
        assessor.assess(starts)
    with pytest.raises(ValueError, match=r"actions: expected shape \[T, A\] or \[\*B, T, A\]"):
        assessor.assess(starts, actions=plan[..., :1])  # wrong A
    with pytest.raises(ValueError, match=r"actions: expected shape"):
        assessor.assess(starts, actions=plan[:2])  # wrong B
    with pytest.raises(ValueError, match=r"actions: expected T = horizon = 6 steps, got T = 4"):
        assessor.assess(starts, actions=plan[:, :4])
    with pytest.raises(ValueError, match="actions: expected finite values"):
        assessor.assess(starts, actions=torch.full((T, A), float("nan")))
    outside = torch.zeros(T, A)
    outside[2, 1] = 7.0  # the env's bounds are [-1, 1]: the model env would clip it to 1
    with pytest.raises(
        ValueError,
        match=r"^actions: expected actions inside the env's action_spec bounds \[\[-1.0, -1.0\], "
        r"\[1.0, 1.0\]\], got 3 of 18 outside, by up to 6; clip them",
    ):
        assessor.assess(starts, actions=outside)
    # a closed-loop policy acting outside them too: the real episodes refuse it
    with pytest.raises(
        ValueError,
        match=r"^policy: expected actions inside the env's action_spec bounds \[\[-1.0, -1.0\], "
        r"\[1.0, 1.0\]\], got \d+ of \d+ outside at step 0 of the imagined episodes, by up to "
        r"[\d.]+; clip them in the policy: the real env's episodes \(run_episodes, "
        r"real_outcomes\) refuse them",
    ):
        assessor.assess(starts, policy=lambda obs: 10 * obs[..., :A])
    assessor.assess(starts, policy=lambda obs: (10 * obs[..., :A]).clamp(-1, 1))  # clipped: fine
    bad = starts.clone()
    bad[1, 3] = float("nan")
    with pytest.raises(ValueError, match=r"start_states: expected finite values.*\[1\]"):
        assessor.assess(bad, actions=plan)
    with pytest.raises(ValueError, match=r"start_states: expected shape \[\*B, S=14\]"):
        assessor.assess(starts[:, :5], actions=plan)
    with pytest.raises(KeyError, match="start: expected the start states"):
        assessor.assess(TensorDict({"obs": starts}, batch_size=[3]), actions=plan)
    with pytest.raises(TypeError, match=r"^start_states: expected dtype torch.float32 \(the mo"):
        assessor.assess(starts.double(), actions=plan)
    no_limit = make_assessor(env, boundary=boundary(time_limit=None, dt=None))
    with pytest.raises(ValueError, match="horizon: a closed-loop assessment needs a horizon"):
        no_limit.assess(starts, policy=lambda obs: torch.zeros(*obs.shape[:-1], A))
    free = no_limit.assess(starts, actions=plan[:, :4])  # open loop: T from the actions
    assert free.data["uncertainty", "total"].shape == (3, 4, S)
    assert free.summary(index=0).startswith("P(success within 4 steps)")
    for dtype in (torch.float64, torch.int64):  # named as the policy's, before any clamp
        with pytest.raises(
            TypeError, match=f"policy: expected actions of dtype torch.float32 .*, got {dtype}"
        ):
            assessor.assess(
                starts, policy=lambda obs, d=dtype: torch.zeros(*obs.shape[:-1], A, dtype=d)
            )
    with pytest.raises(TypeError, match=r"generator: expected a torch\.Generator or None"):
        assessor.assess(starts, actions=plan, generator=3)
    with pytest.raises(TypeError, match="return_rollouts: expected True or False, got 'yes'"):
        assessor.assess(starts, actions=plan, return_rollouts="yes")


def test_episode_end_measures_the_uncertainty_of_the_episode(env, starts, plan):
    # A success region every imagined state is in: every episode ends at step 0, so from step 1
    # on no uncertainty is left; without episode_end the imagined states still spread.
    always = SuccessBoundary(lambda s: s[..., 0] > -1e9, time_limit=T, dt=DT)
    ended = make_assessor(env, boundary=always, episode_end=True)
    free = make_assessor(env, boundary=always)
    a = ended.assess(starts, actions=plan, generator=seeded()).data["uncertainty", "total"]
    b = free.assess(starts, actions=plan, generator=seeded()).data["uncertainty", "total"]
    assert torch.equal(a[:, 0], b[:, 0])  # the step where the outcome is decided is still live
    assert a[:, 1:].abs().max().item() < 1e-9
    assert b[:, 1:].sum().item() > 1.0
    shuffled = make_assessor(env, episode_end=True, bias_correction="shuffle", generator=seeded())
    out = shuffled.assess(starts, actions=plan, generator=seeded()).data["uncertainty"]
    assert torch.allclose(out["aleatoric"] + out["epistemic"], out["total"], atol=1e-5)


def test_per_sample_nan_and_a_nan_distance_are_refused_by_name(env, starts, plan):
    """NaN from a user's function of finite imagined states is an error, not a stored value
    (per_sample) or a failure (a boundary's distance); inf may stand for 'never'."""
    never = {"x": lambda o: torch.where(o[..., 0] > 1e9, 0.0, torch.inf)}
    report = make_assessor(env, per_sample=never).assess(starts, actions=plan, generator=seeded())
    assert torch.isinf(report.data["per_sample", "x"]).all()
    nan = {"x": lambda o: torch.where(o[..., 0] > 0, o[..., 0], torch.nan)}
    with pytest.raises(ValueError, match=r"^per_sample\['x'\]: expected no NaN .*, got \d+ NaN"):
        make_assessor(env, per_sample=nan).assess(starts, actions=plan, generator=seeded())
    broken = SuccessBoundary.within_distance(lambda o: o[..., 0] * torch.nan, 0.03, time_limit=T)
    with pytest.raises(ValueError, match=rf"^distance: expected no NaN .*, got {3 * T} NaN"):
        broken.success_over_time(torch.zeros(3, T, S))
    with pytest.raises(TypeError, match="distance: expected a callable, got float"):
        SuccessBoundary.within_distance(0.5, 0.03)


def test_survival_forecast_is_the_chance_of_no_failure_within_the_limit(env, starts, plan):
    """A survival boundary's P(success) is the share of imagined episodes with no failure in
    the limit's steps; the summary says so; a horizon shorter than the limit is refused."""
    limit = T - 2
    rollout = env.imagine(starts, plan[:, :limit], samples_per_member=N, generator=seeded())
    # a threshold some imagined episodes cross: the median of their peaks
    threshold = float(rollout["observation"][..., 8].abs().amax(-1).median())

    def drifted(o: torch.Tensor) -> torch.Tensor:
        return o[..., 8].abs() > threshold

    first_failure = drifted(rollout["observation"]).any(-1)  # [E, N, B], within the limit
    want = 1.0 - first_failure.float().mean((0, 1))
    assert 0.0 < want.mean().item() < 1.0  # the check can tell a wrong answer

    survive = SuccessBoundary.survival(drifted, time_limit=limit, dt=DT)
    report = make_assessor(env, boundary=survive, horizon=T).assess(
        starts, actions=plan, generator=seeded()
    )
    assert torch.allclose(report.competency["p_success"], want)
    assert torch.equal(report.data["competency", "failure"], first_failure.permute(2, 0, 1))
    assert report.summary(index=0).startswith(f"P(no failure for {limit * DT:g} s) = ")
    assert "mean P(no failure for" in report.overall()
    with pytest.raises(
        ValueError, match=rf"horizon: .*expected a horizon of at least {limit}, got 2"
    ):
        make_assessor(env, boundary=survive, horizon=2)


def test_a_planner_agent_is_reset_per_chunk_and_seeded_with_the_assessment(env, starts):
    """A planner as the agent: its warm start does not leak from one chunk (or one call) into
    the next, and under a seed its candidates (its own generator) and their scores (the model
    env's) are drawn from the chunk's seed, so the forecast is reproducible and the
    generators are left as they were."""
    from rcvae_torchrl.planners import CEMPlanner

    planner = CEMPlanner(env, horizon=2, num_candidates=6, top_k=2, iterations=1, seed=3)
    assessor = make_assessor(env, policy=planner, start_chunk=2, samples_per_member=2)
    resets = []
    reset = planner.reset
    planner.reset = lambda: (resets.append(1), reset())[1]
    before = planner.generator.get_state(), env.generator.get_state()
    first = assessor.assess(starts, seed=0)
    assert len(resets) == 2  # one per chunk of 2 of the 3 start states
    assert torch.equal(planner.generator.get_state(), before[0])
    assert torch.equal(env.generator.get_state(), before[1])
    planner(env.reset(TensorDict({"observation": starts[:1]}, batch_size=[1])))  # kept plan
    planner.generator.manual_seed(99)  # and other generator states
    env.generator.manual_seed(98)
    again = assessor.assess(starts, seed=0)
    assert_same(first.data, again.data)
    other = assessor.assess(starts, seed=1).data["uncertainty", "total"]
    assert not torch.equal(first.data["uncertainty", "total"], other)


def test_parts_cut_at_chunks_give_the_whole_s_rows(env, starts):
    """``first_chunk``: start states assessed in parts, each told at which chunk of the whole
    it begins, give the whole's rows bit for bit under the seed, with a planner as the agent
    (its draws seeded per chunk too); a part not told draws as the whole's first chunks do.
    An offset without a seed, or a negative one, is refused."""
    from rcvae_torchrl.planners import CEMPlanner

    planner = CEMPlanner(env, horizon=2, num_candidates=6, top_k=2, iterations=1, seed=3)
    assessor = make_assessor(env, policy=planner, start_chunk=1, samples_per_member=2)
    whole = assessor.assess(starts, seed=0).data
    first = assessor.assess(starts[:1], seed=0).data
    rest = assessor.assess(starts[1:], seed=0, first_chunk=1).data
    assert_same(whole, torch.cat([first, rest]))
    untold = assessor.assess(starts[1:], seed=0).data
    assert not torch.equal(untold["uncertainty", "total"], whole[1:]["uncertainty", "total"])
    with pytest.raises(ValueError, match=r"first_chunk: expected a seed with it.*no seed"):
        assessor.assess(starts[1:], generator=seeded(), first_chunk=1)
    with pytest.raises(ValueError, match=r"first_chunk: expected an integer >= 0, got -1"):
        assessor.assess(starts, seed=0, first_chunk=-1)


def test_a_horizon_shorter_than_the_deadline_is_said(env, starts):
    """A horizon short of the boundary's time limit answers an earlier deadline: the assessor
    warns once, naming both, and the report's time limit is the horizon's."""
    with pytest.warns(UserWarning, match=r"^horizon: 3 steps = .* shorter than the boundary's"):
        short = make_assessor(env, horizon=3, boundary=boundary(time_limit=T))
    assert short.assess(starts, actions=torch.zeros(3, A)).time_limit == 3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make_assessor(env, horizon=T + 2)  # longer: the deadline is the boundary's
        make_assessor(env, horizon=3, boundary=boundary(time_limit=None, dt=DT))  # none


def test_a_time_limit_short_of_one_step_is_refused():
    with pytest.raises(ValueError, match=r"^time_limit_s: expected at least one step of dt = "):
        boundary(time_limit=None, time_limit_s=DT / 2)
    assert boundary(time_limit=None, time_limit_s=DT).time_limit == 1


def test_too_narrow_bins_are_named_as_the_report_names_the_dimensions(starts, plan):
    """Without dim_names the assessor names dimensions by the model's names, in its report and
    in the uncertainty metric's warning of bins so narrow each sample has its own."""
    import dataclasses

    names = tuple(f"s{i}" for i in range(S))
    model = make_ensemble()
    model.config = dataclasses.replace(CONFIG, observation_names=names)
    assessor = make_assessor(make_env(model), dim_names=None, bin_width=1e-9)
    assert assessor.dim_names == names
    with pytest.warns(UserWarning, match=r"^bin_width: in s0 \(width 1e-09, at 100% of the steps"):
        report = assessor.assess(starts, actions=plan, seed=0)
    assert set(report.data["uncertainty", "by_dim"].keys()) == set(names)
    # the summary names such a dimension as at the ceiling of its samples, not as uncertain
    # (a trial's walker: "Most uncertain: orientations[10] (mean 5.91 bits)", log2 60)
    ceiling = f"log2 {E * N} = {math.log2(E * N):.2f} bits: each sample in a bin of its own"
    assert f"; at the ceiling of its {E * N} samples, {ceiling}" in report.summary(index=0)
    fine = make_assessor(make_env(model), dim_names=None).assess(starts, actions=plan, seed=0)
    assert "Most uncertain" in fine.summary(index=0) and "ceiling" not in fine.summary(index=0)


def test_a_reference_measured_otherwise_is_refused(env, starts, plan):
    """Bits from other bins, another bias correction, other samples per member or another
    horizon are on another scale: a reference report measured so is refused, naming what
    differs; one measured alike is taken."""
    report = make_assessor(env).assess(starts, actions=plan, seed=0)
    alike = make_assessor(env).assess(starts[:2], actions=plan[:2], seed=1)
    assert report.with_reference(alike).reference is not None
    assert report.measure["samples_per_member"] == N and report.measure["estimator"] == "histogram"
    for kwargs, said in (
        ({"bin_width": resolution_tensor() * 4}, "bin_width"),
        (
            {"bias_correction": "none"},
            "bias_correction: the reference's 'none', this report's 'shuffle'",
        ),
        (
            {"samples_per_member": 2 * N},
            f"samples_per_member: the reference's {2 * N}, this report's {N}",
        ),
    ):
        other = make_assessor(env, **kwargs).assess(starts, actions=plan, seed=0)
        with pytest.raises(ValueError, match=r"^reference: its bits were measured otherwise"):
            other.with_reference(report)
        with pytest.raises(ValueError, match=said.replace("*", r"\*")):
            report.with_reference(other)
    longer = make_assessor(env, horizon=T + 2, boundary=boundary(time_limit=T + 2))
    longer_report = longer.assess(starts, actions=torch.zeros(T + 2, A), seed=0)
    with pytest.raises(ValueError, match=rf"imagined steps: the reference's {T + 2}, this"):
        report.with_reference(longer_report)
    # a Reference kept as JSON keeps how it was measured, and is refused alike (a trial's
    # service compared a report with the reference of another horizon and samples, silently)
    other = make_assessor(env, samples_per_member=2 * N).assess(starts, actions=plan, seed=0)
    for measured, said in (
        (longer_report, rf"imagined steps: the reference's {T + 2}, this report's {T}"),
        (other, f"samples_per_member: the reference's {2 * N}, this report's {N}"),
    ):
        kept = measured.with_reference(measured).reference
        read = Reference(**json.loads(json.dumps(dataclasses.asdict(kept))))
        with pytest.raises(ValueError, match=said):
            report.with_reference(read)
    kept = alike.with_reference(alike).reference
    read = Reference(**json.loads(json.dumps(dataclasses.asdict(kept))))
    assert read.measure is not None and report.with_reference(read).reference == read
    bare = Reference(kept.aleatoric, kept.epistemic)  # made by hand: nothing to compare
    assert report.with_reference(bare).reference == bare


def test_a_check_of_sure_forecasts_vouches_for_sure_forecasts_alone(env, plan):
    """A near-exact model of a deterministic env forecasts 0 or 1: a check of such starts,
    all right, and fewer than 10 in doubt, passes for sure forecasts, and vouches for a report
    of sure forecasts, not for one whose forecasts lie between."""
    from rcvae_torchrl.training import OutcomeCheck

    starts = torch.randn(30, S, generator=seeded(12)) * 0.1
    made = make_assessor(env).assess(starts, actions=plan[0], generator=seeded())
    p = made.competency["p_success"]
    sure = (p <= 1e-3) | (p >= 1 - 1e-3)
    assert 21 <= int(sure.sum()) and int((~sure).sum()) < 10  # a bound within 0.2 needs 21
    real = (p > 0.5)[:, None]  # one run each, as forecast
    check = OutcomeCheck.from_outcomes(made, real)
    assert check.began_settled is not None and not bool(check.began_settled.any())
    assert not check.measured and check.sure_only and check.passed
    data = made.data.clone()
    data["competency", "p_success"] = (p > 0.5).to(p.dtype)
    rounded = dataclasses.replace(made, data=data)
    assert rounded.with_forecast_check(check).trustworthy
    data["competency", "p_success"][1] = 0.4
    between = dataclasses.replace(made, data=data).with_forecast_check(check)
    assert not between.trustworthy
    assert between.warning.endswith(
        "the forecast check vouches for forecasts of 0 or 1 alone (it had too few start states "
        "in doubt to check others), and 1 of these 30 forecasts lie between (0.001 to 0.999)"
    )
    # starts already in the success region show nothing of the model: not counted as sure
    began = dataclasses.replace(check, began_settled=torch.ones(30, dtype=torch.bool))
    assert began.sure == 0 and not began.passed


def test_a_forecast_check_does_not_vouch_for_start_states_unlike_its_own(env, plan):
    """A cart-pole trial: a check that passed on hanging starts made a report of starts with
    the cart moving fast 'trustworthy' (0.14 forecast against 0.44 real). The check keeps its
    start states; a report whose starts lie outside them, more than chance allows, is not
    trustworthy, and each such start is cautioned."""
    from rcvae_torchrl.training import OutcomeCheck

    g = seeded(11)
    own = torch.randn(60, S, generator=g) * 0.1  # the check's starts
    alike = torch.randn(3, S, generator=g) * 0.1
    report = make_assessor(env).assess(alike, actions=plan, generator=seeded())
    real = torch.rand(60, 40, generator=seeded(3)) < 0.5
    forecast = torch.full((60,), 0.5, dtype=torch.float64)
    check = OutcomeCheck.from_outcomes(forecast, real, task=report.task, start_states=own)
    checked = report.with_forecast_check(check)
    assert checked.trustworthy and not bool(checked.uncovered.any())
    assert "unlike those the forecast check" not in checked.summary()
    far = make_assessor(env).assess(alike + 1.0, actions=plan, generator=seeded())
    moved = far.with_forecast_check(check)
    assert bool(moved.uncovered.all()) and not moved.trustworthy
    assert moved.warning.startswith(
        "the forecast check vouches for start states like its own, and 3 of these 3 lie "
        "farther from all of them than its own lie from one another, more than chance allows"
    )
    assert (
        "Caution: this start state is unlike those the forecast check was made on, which does "
        "not vouch for its forecast."
    ) in moved.summary(index=0)
    assert " 3 of the 3 start states are unlike those the forecast check was made on" in (
        moved.overall()
    )
    # vouching for none of them says nothing against the model's split, which still speaks:
    # against a reference, what rose is what tells that the starts lie outside what it learned
    unsplit = "this split does not say whether more data would help"
    assert unsplit not in moved.overall() and unsplit not in moved.summary(index=0)
    assert "Most of the doubt is " in moved.overall()
    compared = moved.with_reference(report).overall()
    assert unsplit not in compared and compared.startswith("Warning: the forecast check vouches")
    assert "the rise is epistemic, the model has not seen states like this" in compared
    failed = OutcomeCheck.from_outcomes(
        torch.full((60,), 0.9, dtype=torch.float64), real, task=report.task, start_states=own
    )
    assert not failed.passed
    assert unsplit in far.with_forecast_check(failed).overall()  # biased: no cause given
    # one start outside of three is within chance: cautioned, still trustworthy
    one_off = torch.cat([alike[:2], alike[2:] + 1.0])
    mixed = make_assessor(env).assess(one_off, actions=plan, generator=seeded())
    mixed = mixed.with_forecast_check(check)
    assert mixed.uncovered.tolist() == [False, False, True] and mixed.trustworthy
    assert "Caution: this start state is unlike" in mixed.summary(index=2)
    assert "Caution: this start state is unlike" not in mixed.summary(index=0)
    # a check made from a report keeps that report's start states
    from_report = OutcomeCheck.from_outcomes(report, torch.ones(3, 2, dtype=torch.bool))
    assert torch.equal(from_report.start_states, alike.double())
    # where the check was made, said as it is: other start states, these, or some of them
    assert checked.overall().endswith(f" Forecast check on other start states: {check.describe()}.")
    same = OutcomeCheck.from_outcomes(
        torch.full((3,), 0.5, dtype=torch.float64),
        real[:3],
        task=report.task,
        start_states=alike,
        min_starts=1,
    )
    on_these = report.with_forecast_check(same)
    said = f"orecast check on these start states: {same.describe()}"
    assert said in (on_these.overall() + on_these.warning)
    partly = OutcomeCheck.from_outcomes(
        torch.full((61,), 0.5, dtype=torch.float64),
        torch.cat([real, real[:1]]),
        task=report.task,
        start_states=torch.cat([own, alike[:1]]),
    )
    some = report.with_forecast_check(partly).overall()
    assert f"Forecast check on 1 of these 3 start states and others: {partly.describe()}." in some


def test_one_sample_per_member_is_refused_when_built(env):
    """A trial: one sample per member (the shuffle correction then left out) read "Most of the
    doubt is epistemic (5.47 of 5.47 bits)": a member's spread from one sample is 0."""
    for correction in ({}, {"bias_correction": "none"}, {"bias_correction": "shuffle"}):
        with pytest.raises(
            ValueError,
            match=r"^samples_per_member: expected at least 2 imagined episodes per member "
            r"\(the aleatoric part is each member's own spread: from one sample it is 0",
        ):
            make_assessor(env, samples_per_member=1, **correction)
    assert make_assessor(env, samples_per_member=2).measure["bias_correction"] == "shuffle"


def test_a_spread_too_wide_is_said_beside_the_split_of_the_doubt(env, starts, plan):
    """Self-checks that found the model's spread wider than its errors do not fail it, but
    its aleatoric bits there overstate the noise: every paragraph and the overview say so."""
    import dataclasses

    from rcvae_torchrl.training import ModelChecks

    zeros = torch.zeros(S, dtype=torch.float64)
    checks = ModelChecks(
        OBSERVATION_NAMES, zeros, zeros + 1, zeros + 1, zeros, zeros + 1, 5, (0, 1), 0.05,
        covered=torch.full((S,), 30.0), episodes=32, coverage_steps=20, interval=0.9,
        covered_half=torch.tensor([30.0] + [16.0] * (S - 1)), half_interval=0.5,
    )  # fmt: skip
    env.ensemble.checks = checks
    assert checks.passed and checks.underconfident == (0,)
    report = make_assessor(env).assess(starts, actions=plan, generator=seeded())
    caution = f"Caution: {checks.wide_sentence()}."
    assert report.warning == "" and report.model_caution == checks.wide_sentence()
    assert caution in report.summary(index=0) and caution in report.overall()
    referenced = report.with_reference(report)
    assert caution in referenced.summary(index=1)
    env.ensemble.checks = dataclasses.replace(checks, covered_half=None)
    assert make_assessor(env).assess(starts, actions=plan, generator=seeded()).model_caution == ""


def test_identical_members_read_little_epistemic_doubt_by_default():
    """A quadruped trial: the histogram's plug-in split read 80 epistemic bits from members'
    undersampling (2.7 corrected). The assessor corrects it by default: members that are
    copies of one another read a fraction of the plug-in's epistemic bits."""
    model = make_ensemble()
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(p[:1].expand_as(p))  # every member member 0
    env = make_env(model)
    starts = torch.randn(4, S, generator=seeded(2)) * 0.1
    plan = torch.zeros(T, A)
    default = make_assessor(env).assess(starts, actions=plan, seed=0)
    plug_in = make_assessor(env, bias_correction="none").assess(starts, actions=plan, seed=0)
    assert default.measure["bias_correction"] == "shuffle"
    corrected = float(default.data["uncertainty", "summary", "epistemic"].mean())
    raw = float(plug_in.data["uncertainty", "summary", "epistemic"].mean())
    assert raw > 0.5 and corrected < 0.25 * raw


def test_a_start_already_in_the_success_or_failure_region_is_said_to_be_settled(env, plan):
    """A point-mass trial: starts already in the target (or the obstacle) got P = 1 (or 0)
    with nothing said. The report keeps which starts lie in either region and says so in
    their paragraphs; the others' paragraphs say nothing of it."""
    starts = torch.zeros(3, S)
    ball, target = obs_indices("ball"), obs_indices("target")
    starts[0, target] = torch.tensor([0.5, 0.5])
    starts[0, ball] = torch.tensor([0.5, 0.51])  # within 0.03 of the target
    starts[1, ball] = torch.tensor([0.9, 0.9])  # far from it, and in the "failure" region
    starts[2, ball] = torch.tensor([-0.5, 0.0])
    obstacle = lambda o: o[..., ball[0]] > 0.8  # noqa: E731
    report = make_assessor(env, boundary=boundary(failure=obstacle)).assess(
        starts, actions=plan, seed=0
    )
    assert report.data["start_state", "in_success"].tolist() == [True, False, False]
    assert report.data["start_state", "in_failure"].tolist() == [False, True, False]
    said = "The start state already lies in the {} region: its outcome is mostly settled"
    assert said.format("success") in report.summary(index=0)
    assert said.format("failure") in report.summary(index=1)
    assert "already lies" not in report.summary(index=2)


def test_a_boundary_in_days_writes_its_times_in_days(starts, plan):
    """An inventory trial: a step of one day (dt=1) was written "P(no failure for 30 s)" and
    "peak at t = 3 s"; a boundary's time_unit names the unit of dt in every time written,
    and seconds stay the default."""
    model = make_ensemble()
    env = RCVAEEnsembleEnv(model, pusher_reward, pusher_success, seed=0)
    days = boundary(dt=1.0, time_unit="days")
    report = make_assessor(env, boundary=days).assess(starts, actions=plan, seed=0)
    text = report.summary(index=0)
    assert f"within {T:g} days" in text and "peak at t = " in text and " days)" in text
    assert " s)" not in text and " s:" not in text
    assert report.time_unit == "days" and report[0:1].time_unit == "days"
    seconds = make_assessor(env, boundary=boundary()).assess(starts, actions=plan, seed=0)
    assert f"within {T * DT:g} s" in seconds.summary(index=0) and seconds.time_unit == "s"
    with pytest.warns(UserWarning, match=r"horizon: 4 steps = 4 days, shorter than .* = 6 days"):
        make_assessor(env, boundary=days, horizon=4)
    for bad in ("", 3):
        with pytest.raises(TypeError, match="time_unit: expected the name of dt's unit"):
            boundary(dt=1.0, time_unit=bad)


def test_a_stateful_agent_starts_every_batch_of_imagined_episodes_afresh(starts):
    """An LSTM trial: the assessor reset the agent per chunk of starts, but imagination runs
    a chunk's episodes in batches of 1,024 per member, and the later batches began with the
    last one's memory (a planner's warm start too). Through the bounds check's wrapper, every
    batch now begins with the agent's reset."""
    from rcvae_torchrl.rollout import ActionBounds

    class Counting:
        def __init__(self) -> None:
            self.steps, self.first_steps = 0, []

        def reset(self) -> None:
            self.steps = 0

        def __call__(self, s: torch.Tensor) -> torch.Tensor:
            if self.steps == 0:
                self.first_steps.append(s.shape[1])
            self.steps += 1
            return torch.zeros(*s.shape[:-1], A)

    env = make_env(make_ensemble())
    env.action_bounds = ActionBounds(-torch.ones(A), torch.ones(A))
    agent = Counting()
    make_assessor(env, samples_per_member=400, policy=agent).assess(starts, seed=0)
    assert agent.first_steps == [1024, 3 * 400 - 1024]  # two batches, each from step 0


def test_a_report_rebuilt_with_other_steps_than_imagined_is_refused(env, starts, plan):
    """A trial rebuilt a 3-s report with steps=50 (1 s): it read "P(success within 1 s) =
    1.00" with the 3-s P, and was scored against 1-s real outcomes."""
    assessor = make_assessor(env)
    report = assessor.assess(starts, actions=plan, seed=0)
    again = assessor.report(report.data)  # the steps the data imagined: the same report
    assert again.time_limit == report.time_limit == T
    assert again.summary() == report.summary()
    with pytest.raises(
        ValueError,
        match=rf"^steps: expected the {T} steps data imagined \(its bits are per step of them\), "
        rf"got {T - 2}: .* judge the rollouts again \(success_on_grid, per_sample\)",
    ):
        assessor.report(report.data, steps=T - 2)
