"""A whole CompetencyReport saved and read back (``as_dict`` / ``from_dict``): it keeps what it
answers (task, agent, deadline) and how far it is to be trusted, where its bare ``data`` read
back through an assessor took the reading process's task and knew no agent."""

import dataclasses

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
    with pytest.raises(ValueError, match=r"^values: entries \['extra'\] are not a report's"):
        CompetencyReport.from_dict({**record, "extra": 1})
    with pytest.raises(ValueError, match=r"^values: expected the entries .* missing \['task'\]"):
        CompetencyReport.from_dict({k: v for k, v in record.items() if k != "task"})
    with pytest.raises(ValueError, match=r"^values\['kind'\]: expected 'CompetencyReport'"):
        CompetencyReport.from_dict({**record, "kind": "OutcomeCheck"})
    with pytest.raises(ValueError, match=r"^values\['data'\]: its tensors do not share the rep"):
        CompetencyReport.from_dict({**record, "batch_size": [5]})
    with pytest.raises(TypeError, match=r"^values\['agent'\]: expected a str or None"):
        CompetencyReport.from_dict({**record, "agent": 3})
    with pytest.raises(ValueError, match=r"^values\['time_limit'\]: expected a positive integer"):
        CompetencyReport.from_dict({**record, "time_limit": 0})


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
