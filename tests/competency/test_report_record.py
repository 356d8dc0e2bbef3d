"""A whole CompetencyReport saved and read back (``as_dict`` / ``from_dict``): it keeps what it
answers (task, agent, deadline) and how far it is to be trusted, where its bare ``data`` read
back through an assessor took the reading process's task and knew no agent."""

import dataclasses
import math

import pytest
import torch
from tensordict.nn import TensorDictModule
from test_assessor import S, T, assert_same, boundary, make_assessor, make_ensemble, make_env
from test_novelty_report import _novelty

from rcvae_torchrl.competency import CompetencyReport
from rcvae_torchrl.io import load_torch, save_torch
from rcvae_torchrl.training import OutcomeCheck


def _policy(seed: int) -> TensorDictModule:
    torch.manual_seed(seed)
    net = torch.nn.Sequential(torch.nn.Linear(S, 2), torch.nn.Tanh())
    return TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


def _report(policy=None, **kwargs) -> tuple[CompetencyReport, torch.Tensor]:
    model = make_ensemble()
    model.novelty = _novelty()
    starts = torch.randn(4, S, generator=torch.Generator().manual_seed(1)) * 0.1
    starts[3, 6] = 2.0  # far from the training states: a novelty caution to keep
    assessor = make_assessor(make_env(model), **kwargs)
    report = assessor.assess(starts, policy=policy or _policy(0), seed=0)
    reference = assessor.assess(starts[:3], policy=policy or _policy(0), seed=1)
    real = torch.rand(60, 40, generator=torch.Generator().manual_seed(3)) < 0.5
    check = OutcomeCheck.from_outcomes(
        torch.full((60,), 0.5, dtype=torch.float64), real, task=report.task
    )
    check = dataclasses.replace(check, agent=report.agent)
    return report.with_reference(reference).with_forecast_check(check), starts


def test_a_saved_report_reads_back_whole(tmp_path):
    report, _ = _report()
    assert report.agent and report.novelty is not None and report.reference is not None
    save_torch(tmp_path / "report.pt", report.as_dict())
    back = CompetencyReport.from_dict(load_torch(tmp_path / "report.pt", "report"))
    assert_same(back.data, report.data)
    for name in ("task", "agent", "acting", "predicates", "time_limit", "dt", "dim_names"):
        assert getattr(back, name) == getattr(report, name), name
    assert back.reference == report.reference
    assert back.forecast_check.as_dict() == report.forecast_check.as_dict()
    assert back.novelty.as_dict().keys() == report.novelty.as_dict().keys()
    # every word, the novelty caution and the reference's comparison included
    assert back.summary() == report.summary() and "Caution: the start state" in back.summary()
    assert back.overall() == report.overall()
    assert (back.trustworthy, back.warning) == (report.trustworthy, report.warning)


def test_a_report_read_back_refuses_checks_of_another_task_or_agent(tmp_path):
    """The trial's case: the report's data read back through an assessor of another deadline
    was relabelled with that deadline, and lost its agent; read back whole, it keeps both."""
    report, _ = _report()
    save_torch(tmp_path / "report.pt", report.as_dict())
    back = CompetencyReport.from_dict(load_torch(tmp_path / "report.pt", "report"))
    # what the bare data gives: the reader's task, no agent
    sooner = make_assessor(make_env(report_model()), boundary=boundary(time_limit=T - 1))
    relabelled = sooner.report(report.data, steps=T)
    assert relabelled.task != report.task and relabelled.agent is None
    # the whole report refuses a check of that other deadline, naming it
    other = dataclasses.replace(back.forecast_check, task=relabelled.task)
    said = rf"another deadline \({T - 1} steps there, {T} steps here\)"
    with pytest.raises(ValueError, match=said):
        back.with_forecast_check(other)
    # and a check of another agent's real episodes (other weights)
    theirs = _report(policy=_policy(1))[0]
    assert theirs.agent != back.agent
    with pytest.raises(ValueError, match=r"^check: "):
        back.with_forecast_check(dataclasses.replace(back.forecast_check, agent=theirs.agent))


def report_model():
    model = make_ensemble()
    model.novelty = _novelty()
    return model


def test_a_damaged_or_foreign_record_is_refused_by_name():
    report, _ = _report()
    record = report.as_dict()
    with pytest.raises(
        ValueError, match=r"^values: entries \['extra'\] are not those of a CompetencyReport"
    ):
        CompetencyReport.from_dict({**record, "extra": 1})
    with pytest.raises(ValueError, match=r"^values: expected the entries .* missing \['task'\]"):
        CompetencyReport.from_dict({k: v for k, v in record.items() if k != "task"})
    with pytest.raises(ValueError, match=r"^values: a report's data alone \(report.data.to_dict"):
        CompetencyReport.from_dict(report.data.to_dict())  # as the recipes saved it before
    with pytest.raises(ValueError, match=r"^values\['kind'\]: expected 'CompetencyReport'"):
        CompetencyReport.from_dict({**record, "kind": "OutcomeCheck"})
    with pytest.raises(ValueError, match=r"^values\['data'\]: its tensors do not share the rep"):
        CompetencyReport.from_dict({**record, "batch_size": [5]})
    with pytest.raises(TypeError, match=r"^values\['agent'\]: expected a str or None"):
        CompetencyReport.from_dict({**record, "agent": 3})
    with pytest.raises(ValueError, match=r"^values\['time_limit'\]: expected a positive integer"):
        CompetencyReport.from_dict({**record, "time_limit": 0})
    # labels that contradict the record's own task, or out of range (a trial's edits, each
    # taken before and said falsely in the summary: "P(success within 0.15 s)" of a 6-step P)
    contradicting = [
        ({"time_limit": 3}, ValueError, r"^values\['time_limit'\]: not the deadline the rec"),
        ({"dt": 0.1}, ValueError, r"^values\['dt'\]: not the dt the record's task says"),
        ({"predicates": "x" * 64}, ValueError, r"^values\['predicates'\]: not the boundary"),
        ({"confidence": 7}, ValueError, r"^values\['confidence'\]: expected"),
        ({"top_k": -1}, ValueError, r"^values\['top_k'\]: expected an integer >= 0"),
        ({"dt": "0.05"}, TypeError, r"^values\['dt'\]: expected seconds per step"),
        ({"spread_tolerance": [1.5, 1.0, 2.0]}, ValueError, r"^values\['spread_tolerance'\]"),
        ({"survival": "yes"}, TypeError, r"^values\['survival'\]: expected True or False"),
        ({"batch_size": 4}, TypeError, r"^values\['batch_size'\]: expected a list of sizes"),
        ({"dim_names": ["a"]}, ValueError, r"^values\['dim_names'\]: expected one name per"),
        ({"keys": {"uncertainty": "uncertainty"}}, ValueError, r"^values\['keys'\]: expected"),
        ({"novelty": [1, 2]}, TypeError, r"^values\['novelty'\]: expected None or a dict"),
        ({"reference": {"bogus": 1}}, ValueError, r"^values\['reference'\]: not a record of"),
    ]
    for change, error, said in contradicting:
        with pytest.raises(error, match=said):
            CompetencyReport.from_dict({**record, **change})
    edited = report.as_dict()
    edited["data"]["competency"]["p_success"] = torch.full((4,), 3.0, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^values\['data'\]: p_success holds values outside"):
        CompetencyReport.from_dict(edited)
    edited = report.as_dict()
    competency = edited["data"]["competency"]
    competency["p_success_low"], competency["p_success_high"] = (
        torch.full((4,), 0.9, dtype=torch.float64),
        torch.full((4,), 0.1, dtype=torch.float64),
    )
    with pytest.raises(ValueError, match=r"^values\['data'\]: p_success_low exceeds p_succ"):
        CompetencyReport.from_dict(edited)
    listed = report.as_dict()
    listed["data"]["competency"]["p_success"] = [0.5] * 4
    with pytest.raises(TypeError, match=r"\['p_success'\]: expected a tensor"):
        CompetencyReport.from_dict(listed)
    nan_start = report.as_dict()
    nan_start["data"]["observation"] = torch.full_like(nan_start["data"]["observation"], math.nan)
    with pytest.raises(ValueError, match=r"^values\['data'\]: the start states .* NaN or inf"):
        CompetencyReport.from_dict(nan_start)
    del edited["data"]["competency"]
    with pytest.raises(ValueError, match=r"^values\['data'\]: expected the report's competency"):
        CompetencyReport.from_dict(edited)


def test_a_record_is_a_copy_of_the_report_and_the_report_read_back_of_the_record():
    """A trial filled a record's tensor after as_dict(), and the report's P changed with it."""
    report, _ = _report()
    p = report.competency["p_success"].clone()
    record = report.as_dict()
    record["data"]["competency"]["p_success"].fill_(0.123)
    assert torch.equal(report.competency["p_success"], p)
    record = report.as_dict()
    back = CompetencyReport.from_dict(record)
    record["data"]["competency"]["p_success"].fill_(0.123)
    assert torch.equal(back.competency["p_success"], p)


def _clamped(prev, state):
    return state.clamp(-1.0, 1.0)


def _clamped_faster(prev, state):  # the same name in the config, other physics
    return (state * 1.15).clamp(-1.0, 1.0)


def test_the_same_weights_with_another_state_constraint_are_another_task():
    """A pendulum trial: a check made with the model's own constraint function vouched for the
    same weights loaded with another function of the same name (forecast 0.599 against 0.825
    real, a per-start error of 0.53, ``trustworthy=True``): the task held the weights alone."""
    from test_assessor import CONFIG, Passed

    from rcvae_torchrl.models import ModelFunctions, RCVAEConfig, RCVAEEnsemble

    config = RCVAEConfig(**{**dataclasses.asdict(CONFIG), "state_constraint": "clamped"})

    def model(fn):
        made = RCVAEEnsemble(
            config, 3, functions=ModelFunctions(state_constraints={"clamped": fn}), seed=0
        )
        made.fit_normalizer(torch.zeros(10, S), torch.zeros(10, 2))
        made.checks = Passed()
        return made

    own, swapped = model(_clamped), model(_clamped_faster)
    assert all(torch.equal(v, swapped.state_dict()[k]) for k, v in own.state_dict().items())
    starts = torch.zeros(2, S)
    plan = torch.zeros(T, 2)
    mine = make_assessor(make_env(own)).assess(starts, actions=plan, seed=0)
    theirs = make_assessor(make_env(swapped)).assess(starts, actions=plan, seed=0)
    assert mine.task != theirs.task
    real = torch.rand(60, 40, generator=torch.Generator().manual_seed(3)) < 0.5
    check = OutcomeCheck.from_outcomes(
        torch.full((60,), 0.5, dtype=torch.float64), real, task=mine.task
    )
    assert mine.with_forecast_check(check).trustworthy
    said = r"another world model \(its weights, config or functions\); check this"
    with pytest.raises(ValueError, match=said):
        theirs.with_forecast_check(check)
    # and another config of the same weights (a wider log-std bound) is another model too
    wider = dataclasses.replace(config, max_log_std=config.max_log_std + 1)
    wider = RCVAEEnsemble(wider, 3, functions=own.functions)
    wider.load_state_dict(own.state_dict())
    assert own.behaviour()["config"] != wider.behaviour()["config"]


def test_reports_of_a_batch_of_any_shape_are_scored_start_by_start():
    """A trial's [2, 3] report was refused by score_forecast ("expected 2 rows (one per start
    state), got (6, 2)") and by the outcome check, and an unbatched one counted its 3 members
    as starts."""
    from rcvae_torchrl.agent import RealOutcomes, score_forecast

    model = make_ensemble()
    starts = torch.randn(2, 3, S, generator=torch.Generator().manual_seed(1)) * 0.1
    report = make_assessor(make_env(model)).assess(starts, actions=torch.zeros(T, 2), seed=0)
    assert report.batch_size == (2, 3) and report.flattened().batch_size == (6,)
    success = torch.rand(6, 30, generator=torch.Generator().manual_seed(2)) < 0.5
    first = torch.where(success, 0, T)
    outcomes = RealOutcomes(success, first, first + 1, starts=starts.reshape(6, S))
    flat = score_forecast(report.flattened(), outcomes)
    assert score_forecast(report, outcomes) == flat
    check = OutcomeCheck.from_outcomes(report, outcomes)
    assert torch.equal(check.forecast, report.competency["p_success"].reshape(-1).double())
    one = make_assessor(make_env(model)).assess(starts[0, 0], actions=torch.zeros(T, 2), seed=0)
    assert one.batch_size == () and one.flattened().batch_size == (1,)
    scored = score_forecast(one, outcomes[0:1])
    assert scored["gap"] == pytest.approx(
        abs(float(one.competency["p_success"]) - float(success[0].double().mean())), abs=1e-6
    )
