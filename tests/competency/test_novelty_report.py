"""The assessor's novelty entries and the report's words on start states unlike the training
states (the world model's StateNovelty)."""

import dataclasses
import warnings

import pytest
import torch
from test_assessor import DT, E, S, T, make_assessor, make_ensemble, make_env, set_decoder

from rcvae_torchrl.competency import Reference, SuccessBoundary
from rcvae_torchrl.envs import OBSERVATION_NAMES
from rcvae_torchrl.training import StateNovelty


def _novelty() -> StateNovelty:
    """Training states around 0 with spread 0.1 in every dimension (as make_ensemble's data)."""
    g = torch.Generator().manual_seed(5)
    return StateNovelty.fit(
        torch.randn(3000, S, generator=g) * 0.1, torch.randn(1000, S, generator=g) * 0.1
    )


def _starts() -> torch.Tensor:
    starts = torch.randn(3, S, generator=torch.Generator().manual_seed(1)) * 0.1
    starts[2, OBSERVATION_NAMES.index("ball_vx")] = 2.0  # 20 spreads out
    return starts


def test_entries_are_the_starts_ratio_and_the_share_of_imagined_states_beyond_the_level():
    model = make_ensemble()
    model.novelty = _novelty()
    plan = torch.zeros(T, 2)
    report = make_assessor(make_env(model)).assess(
        _starts(), actions=plan, seed=0, return_rollouts=True
    )
    entries = report.data["novelty"]
    assert torch.allclose(entries["start"], model.novelty.ratio(_starts(), starts=True))
    imagined = report.data["rollout", "observation"]  # [B, E, N, T, S]
    picked = imagined[:, :, :2].reshape(3, -1, S)  # T = 6 < 20 steps: every step
    share = (model.novelty.ratio(picked) > 1).float().mean(-1)
    assert torch.equal(entries["imagined"], share)
    # the first step at which most of those samples are beyond the level, -1 where none is
    most = (model.novelty.ratio(imagined[:, :, :2]) > 1).float().mean((1, 2)) > 0.5  # [B, T]
    first = [row.nonzero()[0, 0].item() if row.any() else -1 for row in most]
    assert entries["leaves"].dtype == torch.int64 and entries["leaves"].tolist() == first
    assert report.novel.tolist() == [bool(s >= 0.1) for s in share[:2]] + [True]
    # no novelty check, no entries and no words
    model.novelty = None
    plain = make_assessor(make_env(model)).assess(_starts(), actions=plan, seed=0)
    assert "novelty" not in plain.data.keys() and plain.novel is None
    assert "unlike" not in plain.summary() + plain.overall()


def test_a_start_unlike_the_training_states_is_cautioned_with_its_dimension():
    model = make_ensemble()
    model.novelty = _novelty()
    set_decoder(model, torch.zeros(E, 1), -6.0)  # imagined states stay at their start
    report = make_assessor(make_env(model)).assess(_starts(), actions=torch.zeros(T, 2), seed=0)
    assert report.data["novelty", "imagined"][:2].tolist() == [0.0, 0.0]
    far = report.summary(index=2)
    ratio = float(model.novelty.ratio(_starts()[2], starts=True))
    assert (
        f"Caution: the start state is unlike the states the model was trained on "
        f"({ratio:.1f}x as far from the training states as 99% of held-out states are: "
        "ball_vx = 2 (training " in far
    )
    # its imagined states stay where it starts: unlike the training states too
    assert report.data["novelty", "imagined"][2] == 1.0
    assert "), and so are 100% of its imagined states: the forecast" in far
    assert "the forecast extrapolates, however much the members agree." in far
    assert "Caution" not in report.summary(index=0)
    assert report.overall().endswith(
        " Novelty: 1 of 3 start states are unlike the states the model was trained on, and 0 "
        "more imagine more of their states unlike them than in-distribution episodes do (over "
        "10%). No check of these forecasts against real episodes is attached to this "
        "report (with_forecast_check)."
    )


def test_imagined_states_that_leave_the_training_states_are_named():
    model = make_ensemble()
    model.novelty = _novelty()
    set_decoder(model, torch.full((E, 1), 8.0), -6.0)  # each step a move: they leave in steps
    report = make_assessor(make_env(model)).assess(_starts()[:2], actions=torch.zeros(T, 2), seed=0)
    share = report.data["novelty", "imagined"]
    assert bool((share >= 0.5).all()) and bool((report.data["novelty", "start"] <= 1).all())
    leaves = report.data["novelty", "leaves"]
    assert 0 < int(leaves[0]) < T - 1  # neither at the start nor at the horizon's end
    text = report.summary(index=0)
    assert (
        f"Caution: {float(share[0]):.0%} of the imagined states are unlike the states the model "
        "was trained on, more than ten times the share of held-out states (10%). The first "
        "step at which more than half of the samples are unlike them is "
        f"t = {round((int(leaves[0]) + 1) * DT, 6):g} s: the forecast extrapolates from there, "
        "however much the members agree." in text
    )
    # a report without the onset (one made before it existed) keeps the words it had
    older = report.data.clone()
    del older["novelty", "leaves"]
    assert (
        "(10%): the forecast extrapolates there, however much the members agree."
        in dataclasses.replace(report, data=older).summary(index=0)
    )
    assert (
        "Novelty: 0 of 2 start states are unlike the states the model was trained on, and 2 more"
        in (report.overall())
    )


def test_imagined_states_after_the_episode_ended_are_not_counted():
    """States past the boundary's success, failure or time limit decide nothing, and real
    episodes that end there have none (a trial's mountain car, stopped by its env at the goal,
    had 95% of its imagined states past the goal unlike the training states, and 19 of 20
    ordinary starts cautioned)."""
    from test_assessor import boundary

    model = make_ensemble()
    model.novelty = _novelty()
    set_decoder(model, torch.full((E, 1), 8.0), -6.0)  # they leave the training states in steps
    starts, plan = _starts()[:2], torch.zeros(T, 2)
    whole = make_assessor(make_env(model)).assess(starts, actions=plan, seed=0)
    leaves = whole.data["novelty", "leaves"]
    assert bool((leaves > 0).all()) and bool(whole.novel.all())
    # a deadline before they leave: ended there, and no sample past it counts
    soon = boundary(time_limit=int(leaves.min()))
    short = make_assessor(make_env(model), boundary=soon, horizon=T)
    short = short.assess(starts, actions=plan, seed=0)
    assert short.data["novelty", "leaves"].tolist() == [-1, -1] and not bool(short.novel.any())
    assert bool((short.data["novelty", "imagined"] < whole.data["novelty", "imagined"]).all())
    # a success at every state ends each episode at its first step: that state alone counts
    at_once = SuccessBoundary(lambda o: torch.ones(o.shape[:-1], dtype=torch.bool), time_limit=T)
    first = make_assessor(make_env(model), boundary=at_once).assess(starts, actions=plan, seed=0)
    step0 = make_assessor(make_env(model), boundary=boundary(time_limit=1), horizon=T)
    assert torch.equal(
        first.data["novelty", "imagined"],
        step0.assess(starts, actions=plan, seed=0).data["novelty", "imagined"],
    )


def test_a_doubt_as_in_the_reference_is_not_called_a_sign_of_seen_states_for_a_novel_start():
    model = make_ensemble()
    model.novelty = _novelty()
    set_decoder(model, torch.zeros(E, 1), -6.0)
    report = make_assessor(make_env(model)).assess(_starts(), actions=torch.zeros(T, 2), seed=0)
    bits = report.data["uncertainty", "summary"]
    # a reference with the bits of start 2 itself: neither part rose for it
    same = Reference(float(bits["aleatoric"][2]), float(bits["epistemic"][2]))
    text = report.with_reference(same).summary(index=2)
    assert (
        ": neither part rose 1.3x or more, the doubt is as in the reference although the start "
        "is unlike the training states (above): the members agree where none has data." in text
    )
    assert "no sign of states the model has not seen" not in text
    # a familiar start with the same doubt keeps the usual words
    familiar = Reference(float(bits["aleatoric"][0]), float(bits["epistemic"][0]))
    assert "no sign of states the model has not seen" in report.with_reference(familiar).summary(
        index=0
    )


def test_the_overall_paragraph_does_not_call_a_doubt_as_in_the_reference_a_sign_of_seen_states():
    model = make_ensemble()
    model.novelty = _novelty()
    set_decoder(model, torch.zeros(E, 1), -6.0)
    report = make_assessor(make_env(model)).assess(_starts(), actions=torch.zeros(T, 2), seed=0)
    aleatoric, epistemic = report.mean_bits()
    same = Reference(aleatoric, epistemic)  # the mean bits themselves: neither part rose
    text = report.with_reference(same).overall()
    assert (
        ": neither part rose 1.3x or more, the doubt is as in the reference although 1 of the 3 "
        "start states, or their imagined states, are unlike the training states (below): the "
        "members agree where none has data." in text
    )
    assert "no sign of states the model has not seen" not in text
    assert " Novelty: 1 of 3 start states are unlike" in text
    # without a cautioned start, the usual words
    familiar = make_assessor(make_env(model)).assess(
        _starts()[:2], actions=torch.zeros(T, 2), seed=0
    )
    text = familiar.with_reference(Reference(*familiar.mean_bits())).overall()
    assert "no sign of states the model has not seen" in text


def test_a_start_whose_imagined_states_alone_are_unlike_is_named_as_such():
    model = make_ensemble()
    model.novelty = _novelty()
    set_decoder(model, torch.full((E, 1), 8.0), -6.0)  # they leave the training states
    report = make_assessor(make_env(model)).assess(_starts()[:1], actions=torch.zeros(T, 2), seed=0)
    assert not bool(report.data["novelty", "start"][0] > 1) and bool(report.novel[0])
    bits = report.data["uncertainty", "summary"]
    same = Reference(float(bits["aleatoric"][0]), float(bits["epistemic"][0]))
    assert (
        "as in the reference although its imagined states are unlike the training states "
        "(above): the members agree where none has data." in report.with_reference(same).summary()
    )


def test_a_success_region_no_training_state_or_every_one_lies_in_is_named():
    """Data that never reached the goal (a trial's mountain car, random episodes): the model
    never saw a success, and every forecast of one extrapolates. And a Reacher trial's
    predicate on the target's position (always in range) held in every state: every forecast
    was 1, with nothing said."""
    model = make_ensemble()
    model.novelty = _novelty()  # training states around 0, spread 0.1
    far = SuccessBoundary(lambda o: o[..., 0] > 5.0, time_limit=T)
    everywhere = SuccessBoundary(lambda o: o[..., 0] > -5.0, time_limit=T)
    kept = r"3,000 training states the world model keeps \(ensemble.novelty.states, drawn from"
    for boundary, said in (
        (far, rf"none of the {kept} .* lies in the success region: the model never saw a success"),
        (everywhere, rf"all {kept} .* lie in the success region: a task met wherever the model"),
    ):
        with pytest.warns(UserWarning, match=rf"^boundary: {said}"):
            make_assessor(make_env(model), boundary=boundary)
    # a reach-avoid task whose failure region holds everywhere (a trial's '>' for '<='): P = 0
    blocked = SuccessBoundary(
        lambda o: o[..., 0] > 0.1, time_limit=T, failure=lambda o: o[..., 1] < 5.0
    )
    with pytest.warns(UserWarning, match=rf"^boundary: all {kept} .* lie in the failure region"):
        make_assessor(make_env(model), boundary=blocked)
    # a predicate of the wrong shape is named with what it was tried on
    wide = SuccessBoundary(lambda o: o[..., :1] > 0.1, time_limit=T)
    with pytest.raises(ValueError, match=r"^success, on the world model's 3,000 training states"):
        make_assessor(make_env(model), boundary=wide)
    near = SuccessBoundary(lambda o: o[..., 0] > 0.1, time_limit=T)
    stay = SuccessBoundary.survival(lambda o: o[..., 0] > 0.1, time_limit=T)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make_assessor(make_env(model), boundary=near)  # some training states lie there
        make_assessor(make_env(model), boundary=stay)  # survival: states in and out of failure
        model.novelty = None
        make_assessor(make_env(model), boundary=far)  # no states kept: nothing to tell


def test_a_report_without_a_novelty_check_says_novelty_was_not_judged():
    """A service's model loaded without a novelty check: its summaries said nothing of it, as
    if its starts had been judged like the training states."""
    model = make_ensemble()
    model.novelty = None
    report = make_assessor(make_env(model)).assess(_starts(), actions=torch.zeros(T, 2), seed=0)
    said = "Novelty not judged: the world model has no novelty check (ensemble.novelty"
    assert said in report.summary(index=0) and said in report.overall()
    model.novelty = _novelty()
    judged = make_assessor(make_env(model)).assess(_starts(), actions=torch.zeros(T, 2), seed=0)
    assert "Novelty not judged" not in judged.summary() + judged.overall()


def test_a_survival_whose_failure_region_holds_every_training_state_is_named():
    """A pendulum trial: a model of episodes that never stood up, on a task of balancing it
    upright; every training state lies in the failure region, and nothing said so."""
    model = make_ensemble()
    model.novelty = _novelty()  # training states around 0, spread 0.1
    fallen = SuccessBoundary.survival(lambda o: o[..., 0] < 5.0, time_limit=T)
    with pytest.warns(
        UserWarning,
        match=r"^boundary: none of the 3,000 training states the world model keeps "
        r"\(ensemble.novelty.states, drawn from its training episodes\) lies outside the "
        r"failure region: the model never saw a state it survives in, and every forecast of one "
        r"extrapolates, however much the members agree; train on episodes that stay out of it, "
        r"or check that the predicate reads the dimensions and units it means \(a slice past "
        r"the state's end, a target's position in place of the distance to it, steps for "
        r"seconds\)$",
    ):
        make_assessor(make_env(model), boundary=fallen)


def test_a_survival_whose_failure_region_holds_no_training_state_is_named():
    """An inventory trial: a stock-out predicate read the backlog (never negative) in place of
    the stock; the model had never seen a failure, imagined some past its data (P = 0.13 to
    0.50 where the real answer was 1.0), and nothing said so."""
    model = make_ensemble()
    model.novelty = _novelty()  # training states around 0, spread 0.1
    never = SuccessBoundary.survival(lambda o: o[..., 1] < -5.0, time_limit=T)
    with pytest.warns(
        UserWarning,
        match=r"^boundary: none of the 3,000 training states the world model keeps "
        r"\(ensemble.novelty.states, drawn from its training episodes\) lies in the failure "
        r"region: the model never saw a failure, so every failure it forecasts extrapolates "
        r"past its data and a forecast of none says only that it imagines none; train on "
        r"episodes that fail too, or check that the predicate reads the dimensions and units "
        r"it means",
    ):
        make_assessor(make_env(model), boundary=never)


def test_a_forecast_check_made_from_a_report_measures_starts_in_the_training_spread():
    """A check made from a report takes the unit of each dimension from the report's novelty
    check (the training states' spread), not from its own starts' spread."""
    from rcvae_torchrl.training import OutcomeCheck

    model = make_ensemble()
    model.novelty = _novelty()
    report = make_assessor(make_env(model)).assess(_starts(), actions=torch.zeros(T, 2), seed=0)
    check = OutcomeCheck.from_outcomes(report, torch.ones(3, 2, dtype=torch.bool))
    assert torch.equal(check.state_scale, model.novelty.scale.double())
    model.novelty = None
    plain = make_assessor(make_env(model)).assess(_starts(), actions=torch.zeros(T, 2), seed=0)
    assert OutcomeCheck.from_outcomes(plain, torch.ones(3, 2, dtype=torch.bool)).state_scale is None


def _novelty_with_actions(actions: torch.Tensor, held_out: torch.Tensor) -> StateNovelty:
    """The states' check of ``_novelty``, judging actions from training ``actions`` ``[N, 2]``
    and ``held_out`` ones (episodes of 10 steps)."""
    ids = torch.arange(held_out.shape[0]) // 10
    return _novelty().with_actions(actions, held_out, ids)


def test_imagined_actions_the_model_never_saw_are_cautioned():
    """A cart-pole trial: the model learned from a relaxed discrete action that took only ±1;
    a planner then chose values between at every step, and the forecast was 0.47 against
    0.75 real with nothing said. The states looked like the training states throughout."""
    g = torch.Generator().manual_seed(3)
    pushes = (torch.randint(0, 2, (400, 2), generator=g) * 2 - 1).float()  # ±1 only
    held_out = (torch.randint(0, 2, (200, 2), generator=g) * 2 - 1).float()
    model = make_ensemble()
    model.novelty = _novelty_with_actions(pushes, held_out)
    assert model.novelty.judges_actions and model.novelty.action_level == 0.05  # the floor
    set_decoder(model, torch.zeros(E, 1), -6.0)  # imagined states stay at their start
    starts = _starts()[:2]  # like the training states
    assessor = make_assessor(make_env(model))
    between = assessor.assess(starts, actions=torch.full((T, 2), 0.3), seed=0)
    assert between.data["novelty", "actions"].tolist() == [1.0, 1.0]
    assert between.data["novelty", "start"].lt(1).all() and between.novel.all()
    text = between.summary(index=0)
    assert (
        "Caution: 100% of the imagined steps take actions outside those the model was trained "
        "on (past the range its training actions took, or between the values they took), "
        "where in-distribution episodes have at most 5%: the model has not seen their effect"
    ) in text
    assert between.overall().endswith(
        "than in-distribution episodes do (over 10%) or act outside the training actions. No "
        "check of these forecasts against real episodes is attached to this report "
        "(with_forecast_check)."
    )
    # against a reference with the same doubt, the sentence names the actions as the reason
    bits = between.data["uncertainty", "summary"]
    same = Reference(float(bits["aleatoric"][0]), float(bits["epistemic"][0]))
    assert (
        "as in the reference although its imagined actions are unlike the training actions "
        "(above)" in between.with_reference(same).summary(index=0)
    )
    seen = assessor.assess(starts, actions=torch.ones(T, 2), seed=0)
    assert seen.data["novelty", "actions"].tolist() == [0.0, 0.0] and not seen.novel.any()
    assert "actions outside" not in seen.summary()
    # a closed-loop policy's actions are judged alike: one at 0.3 in one step of six
    mostly = torch.ones(T, 2)
    mostly[3] = 0.3
    once = assessor.assess(starts, actions=mostly, seed=0)
    assert torch.allclose(once.data["novelty", "actions"], torch.full((2,), 1 / T))
    assert once.novel.all()  # 17% of its steps, over the 5% level


def test_the_action_support_is_its_range_and_the_values_it_took():
    g = torch.Generator().manual_seed(4)
    soft = torch.rand(2000, 2, generator=g) - 0.5  # a soft policy's actions in [-0.5, 0.5]
    held = torch.rand(400, 2, generator=g) - 0.5
    check = _novelty_with_actions(soft, held)
    probe = torch.tensor([[0.0, 0.0], [0.45, -0.45], [1.0, 0.0], [0.0, -0.9], [0.52, 0.0]])
    # beyond the range by more than a bin (0.05) is unseen; within a bin of the edge is not
    assert check.unseen_actions(probe).tolist() == [False, False, True, True, False]
    assert check.action_level == 0.05  # held-out actions of the same policy: none unseen
    restored = StateNovelty.from_dict(check.as_dict())
    assert torch.equal(restored.unseen_actions(probe), check.unseen_actions(probe))
    assert restored.action_level == check.action_level
    # a check saved before actions were judged, or fitted on states alone, judges none
    old = {k: v for k, v in check.as_dict().items() if not k.startswith("action")}
    assert not StateNovelty.from_dict(old).judges_actions
    assert not StateNovelty.from_dict(old).unseen_actions(probe).any()
    bad = dict(check.as_dict(), action_bins=torch.ones(2, 20))
    with pytest.raises(ValueError, match=r"^novelty.action_bins: expected a bool tensor"):
        StateNovelty.from_dict(bad)
