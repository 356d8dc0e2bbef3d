"""The dynamics check: real episodes of the env the model learned pass it; an env whose
dynamics changed, through states like the training states, fails it, naming the dimension."""

from __future__ import annotations

import json
import warnings
from types import MappingProxyType

import pytest
import torch
from tensordict import TensorDict

from rcvae_torchrl.competency import CompetencyReport
from rcvae_torchrl.data import TRAJ_KEY
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.training import (
    DynamicsCheck,
    DynamicsNovelty,
    TrainConfig,
    check_dynamics,
    load_ensemble,
    save_ensemble,
    train_ensemble,
)
from rcvae_torchrl.training.dynamics import MIN_HELD_OUT, rank_p_values
from tests.competency.test_assessor import hand_report
from tests.training.conftest import linear_episodes

NAMES = ("x", "y", "z")


def episodes(n: int, steps: int, seed: int, gain: float = 0.5, first: int = 0) -> TensorDict:
    """Flat episodes of the linear system; ``gain`` is how hard the action pushes z."""
    return linear_episodes(n, steps, seed, gain=gain, first=first).exclude(("next", "done"))


@pytest.fixture(scope="module")
def trained():
    train, val = episodes(24, 40, 0), episodes(16, 40, 1, first=100)
    config = RCVAEConfig(3, 1, hidden_dim=16, latent_dim=2, mlp_dim=16, observation_names=NAMES)
    budget = TrainConfig(max_steps=400, batch_windows=16, window=8, val_every=100, lr=3e-3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the self-checks' verdicts are not this file's
        result = train_ensemble(
            RCVAEEnsemble(config, 3, seed=0), train, val, budget, progress=False
        )
    return result, train, val


def test_training_measures_it_on_the_held_out_episodes(trained):
    result, _, _ = trained
    dynamics = result.ensemble.dynamics
    assert result.dynamics is dynamics and isinstance(dynamics, DynamicsNovelty)
    assert dynamics.held_out == 16 and dynamics.steps == 20 and dynamics.dims == (0, 1, 2)
    # conformal: 16 held-out scores keep at most 16/17 of a new one below the level
    assert dynamics.quantile == pytest.approx(16 / 17)
    # the unit is the model's one-step error on training episodes: about the env's noise
    assert ((dynamics.scale > 0.03) & (dynamics.scale < 0.08)).all()
    assert ((dynamics.reference > 0.7) & (dynamics.reference < 1.4)).all()


def test_episodes_of_the_same_env_pass(trained):
    ensemble = trained[0].ensemble
    for seed in (5, 6, 7):
        check = check_dynamics(ensemble, episodes(20, 40, seed, first=1000))
        assert check.passed and check.episodes == 20 and check.short == 0
        assert check.named() == [] and "they move as the world model learned" in check.describe()
    many = check_dynamics(ensemble, episodes(400, 40, 9, first=5000))
    assert many.passed
    # beyond the held-out episodes' largest score: 1/17 = 5.9 % on average over held-out samples
    assert many.beyond / many.episodes < 0.09
    assert many.rate == pytest.approx(1 / 17)


def test_the_rank_test_holds_its_level_however_many_episodes_are_checked():
    """Scores of one distribution on both sides: 20 held-out episodes, 20 or 100 checked, three
    dimensions. The share of draws the test fails stays at or below alpha; a count beyond the
    held-out episodes' largest score, tested at its nominal rate 1/21, fails in-distribution
    draws far more often the more are checked (the held-out sample's largest score lets
    through more than 1/21 for some samples)."""
    g = torch.Generator().manual_seed(0)
    dims, alpha, draws = (0, 1, 2), 0.05, 1000
    from scipy.stats import binom

    for checked in (20, 100):
        failed_rank = failed_count = 0
        for _ in range(draws):
            held = torch.rand(20, 3, generator=g, dtype=torch.float64)
            new = torch.rand(checked, 3, generator=g, dtype=torch.float64)
            p = rank_p_values(new, held, dims)
            failed_rank += float(p.min()) * 3 < alpha
            beyond = int((new.max(1).values > held.max(1).values.max()).sum())
            failed_count += beyond > 0 and binom.sf(beyond - 1, checked, 1 / 21) < alpha
        assert failed_rank / draws <= alpha + 0.015
        if checked == 100:
            assert failed_count / draws > 2 * alpha
    none = rank_p_values(torch.zeros(0, 3, dtype=torch.float64), held, dims)
    assert bool(none.isnan().all())


def test_a_changed_env_fails_and_names_the_dimension_it_moves(trained):
    """The action pushes z 20 % harder: the states stay like the training states, while the
    one-step errors in z rise; 20 episodes tell it."""
    ensemble = trained[0].ensemble
    shifted = episodes(20, 40, 5, gain=0.6, first=1000)
    check = check_dynamics(ensemble, shifted)
    assert not check.passed and check.beyond >= 8 and check.p_value < 1e-4
    assert [name.split(" ")[0] for name in check.named()] == ["z"]
    assert float(check.ratios[2]) > 1.4 and float(check.ratios[:2].max()) < 1.3
    assert float(check.p_values[2]) < 1e-5 and float(check.p_values[:2].min()) > 0.01
    # the held-out episodes' errors times the tolerance (1.1) are what the test ranks against:
    # with none, the same episodes' p-value is smaller still
    assert check_dynamics(ensemble, shifted, tolerance=1.0).p_value < check.p_value
    text = check.describe()
    assert f"{check.beyond} of 20 real episodes" in text and "moves otherwise" in text
    assert "larger in z (" in text
    # the states themselves are mostly within the novelty check's level
    assert float((ensemble.novelty.ratio(shifted["observation"]) > 1).float().mean()) < 0.2


def test_short_episodes_are_left_out_and_counted(trained):
    """An episode of 20 frames holds the 20 transitions scored; one of 19 is too short."""
    ensemble = trained[0].ensemble
    data = torch.cat(
        [episodes(3, 40, 5), episodes(2, 12, 6, first=10), episodes(2, 20, 7, first=20)]
    )
    check = check_dynamics(ensemble, data)
    assert (check.episodes, check.short) == (5, 2)
    exact = check_dynamics(ensemble, episodes(3, 20, 7)).p_values
    assert torch.equal(exact, check_dynamics(ensemble, episodes(3, 40, 7)).p_values)
    assert check_dynamics(ensemble, episodes(3, 19, 7)).short == 3
    none = check_dynamics(ensemble, episodes(2, 12, 6))
    assert not none.measured and not none.passed and "no episode long enough" in none.describe()
    assert none.named() == []  # no dimension was tested: none is named


def test_another_model_is_refused(trained):
    ensemble = trained[0].ensemble
    data = episodes(5, 40, 5)
    with pytest.raises(ValueError, match="not the world model this check was measured with"):
        check_dynamics(ensemble.select_members([0, 1]), data, novelty=ensemble.dynamics)
    with pytest.raises(ValueError, match=r"no dynamics check.*select_members"):
        check_dynamics(ensemble.select_members([0, 1]), data)
    with pytest.raises(ValueError, match="dtype"):
        check_dynamics(ensemble.select_members([0, 1, 2]).double(), data, novelty=ensemble.dynamics)
    with pytest.raises(TypeError, match="novelty: expected a DynamicsNovelty"):
        check_dynamics(ensemble, data, novelty="x")


def test_bad_episodes_are_refused_by_name(trained):
    ensemble = trained[0].ensemble
    data = episodes(3, 40, 5)
    nan = data.clone()
    nan["observation"][7, 1] = float("nan")
    with pytest.raises(ValueError, match=r"episodes\['observation'\].*NaN"):
        check_dynamics(ensemble, nan)
    wide = data.clone()
    wide["action"] = torch.zeros(data.shape[0], 2)
    with pytest.raises(ValueError, match=r"episodes\['action'\]: expected \[frames, 1\]"):
        check_dynamics(ensemble, wide)
    with pytest.raises(ValueError, match="without"):
        check_dynamics(ensemble, data.exclude(TRAJ_KEY))
    with pytest.raises(TypeError, match="episodes: expected a flat TensorDict"):
        check_dynamics(ensemble, data["observation"])
    with pytest.raises(ValueError, match=r"reshape\(-1\)"):
        check_dynamics(ensemble, data.reshape(3, 40))
    # observations and next observations in two dtypes: read as the model's
    mixed = data.clone()
    mixed["observation"] = mixed["observation"].double()
    assert check_dynamics(ensemble, mixed).episodes == 3
    # episodes of one frame each: too short, counted (the episode-order check once crashed)
    single = check_dynamics(ensemble, data[:3].clone().set(TRAJ_KEY, torch.arange(3)))
    assert (single.episodes, single.short) == (0, 3)
    with pytest.raises(ValueError, match="alpha"):
        check_dynamics(ensemble, data, alpha=0.0)
    with pytest.raises(ValueError, match="tolerance: expected a finite factor >= 1"):
        check_dynamics(ensemble, data, tolerance=0.9)


def test_too_few_held_out_episodes_measure_none(trained):
    _, train, _ = trained
    few = episodes(MIN_HELD_OUT - 1, 40, 3, first=200)
    config = RCVAEConfig(3, 1, hidden_dim=8, latent_dim=2, mlp_dim=8)
    budget = TrainConfig(max_steps=4, batch_windows=4, window=8, val_every=2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = train_ensemble(
            RCVAEEnsemble(config, 2, seed=0), train, few, budget, progress=False, checks=False
        )
    assert result.dynamics is None and result.ensemble.dynamics is None
    said = [str(w.message) for w in caught if str(w.message).startswith("dynamics:")]
    assert said == [
        f"dynamics: not measured, val_data holds {MIN_HELD_OUT - 1} episodes of at least 20 "
        f"frames ({MIN_HELD_OUT} needed): ensemble.dynamics is None, so check_dynamics has no "
        "held-out errors to rank real episodes against. Give it a reference of episodes of the "
        "env the model learned (DynamicsNovelty.fit(ensemble, train_data, episodes, "
        "steps=...), passed as check_dynamics(..., novelty=...)), or train with "
        "dynamics=False to measure none"
    ]
    with warnings.catch_warnings(record=True) as caught:  # asked for none: no warning
        warnings.simplefilter("always")
        train_ensemble(
            RCVAEEnsemble(config, 2, seed=0), train, few, budget, progress=False, checks=False,
            dynamics=False,
        )  # fmt: skip
    assert not [w for w in caught if str(w.message).startswith("dynamics:")]
    with pytest.raises(ValueError, match=f"at least {MIN_HELD_OUT} episodes"):
        DynamicsNovelty.fit(result.ensemble, train, few)


def test_training_on_short_episodes_measures_none(trained):
    """Training episodes all shorter than the transitions scored: no unit to measure, and no
    crash after the training run (the held-out episodes are long enough)."""
    _, _, val = trained
    config = RCVAEConfig(3, 1, hidden_dim=8, latent_dim=2, mlp_dim=8)
    budget = TrainConfig(max_steps=4, batch_windows=4, window=8, val_every=2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = train_ensemble(
            RCVAEEnsemble(config, 2, seed=0), episodes(40, 15, 0), val, budget, progress=False
        )
    assert result.dynamics is None
    assert any(
        str(w.message).startswith(
            "dynamics: not measured, train_data holds no episode of at least 20 frames"
        )
        for w in caught
    )
    with pytest.raises(ValueError, match=r"no episode of at least 20 frames.*steps="):
        DynamicsNovelty.fit(result.ensemble, episodes(4, 15, 0), val)


def test_a_steady_push_within_the_noise_fails_the_shift_test_alone(trained):
    """A constant push on z of 0.6 times the noise every step (a slope): each step's error
    grows too little for the size test, but every episode's errors lean one way; with
    ``shift=True`` 20 episodes tell it, naming z and the way its predictions miss. The same
    env's episodes pass both."""
    ensemble = trained[0].ensemble
    for seed in (5, 6, 7):
        pushed = linear_episodes(20, 40, seed, first=1000, drift=0.03).exclude(("next", "done"))
        assert check_dynamics(ensemble, pushed).passed  # the size test alone
        check = check_dynamics(ensemble, pushed, shift=True)
        assert not check.passed and check.p_value < 1e-3
        assert [name.split(" ")[0] for name in check.named()] == ["z"]
        assert float(check.shift_p_values[2]) * 6 < 0.01  # Bonferroni over both tests
        assert float(check.shift_p_values[:2].min()) > 0.01
        assert float(check.shifts[2]) < -0.3  # the model predicts z too low
        assert ", shifted in z (its errors shifted by -0." in check.describe()
        assert "and their shift, p = " in check.describe()
        same = check_dynamics(ensemble, episodes(20, 40, seed, first=1000), shift=True)
        assert same.passed and same.named() == []
    # a dimension that fails both tests is named once, with both
    both = DynamicsCheck(
        episodes=20, short=0, beyond=3, rate=0.05, alpha=0.01, tolerance=1.1,
        p_values=torch.tensor([0.5, 0.5, 1e-6], dtype=torch.float64),
        ratios=torch.tensor([1.0, 1.0, 3.0], dtype=torch.float64),
        names=NAMES, model="m",
        shift_p_values=torch.tensor([0.5, 1e-5, 1e-4], dtype=torch.float64),
        shifts=torch.tensor([0.0, 0.3, -0.45], dtype=torch.float64),
    )  # fmt: skip
    assert both.p_value == pytest.approx(6e-6)  # 6 tests: 3 dimensions, 2 tests each
    assert both.named() == [
        "z (3.0 times its held-out error, its errors shifted by -0.45 of their unit)",
        "y (its errors shifted by +0.30 of their unit)",
    ]
    assert ", larger or shifted in z (3.0 times" in both.describe()
    # copies of one episode count as many draws: the check warns
    one = episodes(1, 40, 3)
    copies = torch.cat(
        [one.clone().set(TRAJ_KEY, torch.full_like(one[TRAJ_KEY], i)) for i in range(5)]
    )
    with pytest.warns(UserWarning, match="4 of the 5 episodes scored repeat another one"):
        check_dynamics(ensemble, copies, shift=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # distinct episodes: no warning
        check_dynamics(ensemble, episodes(5, 40, 3), shift=True)
    # the shift's level over many draws of one distribution, as the size test's
    g = torch.Generator().manual_seed(1)
    failed = 0
    for _ in range(500):
        held = torch.randn(20, 3, generator=g, dtype=torch.float64)
        new = torch.randn(20, 3, generator=g, dtype=torch.float64)
        p = rank_p_values(new, held, (0, 1, 2), alternative="two-sided")
        failed += float(p.min()) * 3 < 0.01  # Bonferroni over the dimensions
    assert failed / 500 <= 0.02
    with pytest.raises(ValueError, match="alternative"):
        rank_p_values(new, held, (0,), alternative="less")


def test_kept_in_checkpoints_and_records(trained, tmp_path):
    ensemble = trained[0].ensemble
    path = save_ensemble(ensemble, tmp_path / "model.pt")
    loaded = load_ensemble(path)
    mine, theirs = ensemble.dynamics.as_dict(), loaded.dynamics.as_dict()
    for key, value in mine.items():
        same = torch.equal if isinstance(value, torch.Tensor) else (lambda a, b: a == b)
        assert same(value, theirs[key]), key
    data = episodes(20, 40, 5, gain=0.6, first=1000)
    # the loaded model is the same model: its check is the saved one's
    assert check_dynamics(loaded, data).beyond == check_dynamics(ensemble, data).beyond
    check = check_dynamics(ensemble, data)
    again = DynamicsCheck.from_dict(MappingProxyType(check.as_dict()))  # any mapping
    assert (again.beyond, again.episodes, again.passed) == (check.beyond, 20, False)
    measured = DynamicsNovelty.from_dict(ensemble.dynamics.as_dict())
    assert measured.level == ensemble.dynamics.level
    with pytest.raises(ValueError, match="dims"):
        DynamicsNovelty.from_dict({**ensemble.dynamics.as_dict(), "dims": [7]})
    few = ensemble.dynamics.held_out_scores[:3]
    with pytest.raises(ValueError, match="at least 10 held-out episodes"):
        DynamicsNovelty.from_dict({**ensemble.dynamics.as_dict(), "held_out_scores": few})
    with pytest.raises(ValueError, match="p_values"):
        DynamicsCheck.from_dict({**check.as_dict(), "p_values": torch.tensor([2.0, 0.5, 0.5])})
    # edited records that would turn a failed check into a passed one are refused
    record = ensemble.dynamics.as_dict()
    for bad in (float("nan"), -1.0, float("inf")):
        scale = record["scale"].clone()
        scale[2] = bad
        with pytest.raises(ValueError, match="scale"):
            DynamicsNovelty.from_dict({**record, "scale": scale})
    with pytest.raises(ValueError, match="level"):
        DynamicsNovelty.from_dict({**record, "level": -1.0})
    with pytest.raises(TypeError, match="names"):
        DynamicsNovelty.from_dict({**record, "names": "xyz"})
    with pytest.raises(ValueError, match=r"entries \['extra'\] are not those of a DynamicsNov"):
        DynamicsNovelty.from_dict({**record, "extra": 1})
    failing = check.as_dict()
    with pytest.raises(ValueError, match="a p-value in every dimension tested"):
        DynamicsCheck.from_dict({**failing, "p_values": [None] * 3, "ratios": [None] * 3})
    with pytest.raises(ValueError, match="ratios"):
        DynamicsCheck.from_dict({**failing, "ratios": [1.0, -1.0, 2.0]})
    for tolerance in (True, float("inf"), 0.5):
        with pytest.raises(ValueError, match="tolerance"):
            DynamicsCheck.from_dict({**failing, "tolerance": tolerance})
    with pytest.raises(TypeError, match="model"):
        DynamicsCheck.from_dict({**failing, "model": None})
    with pytest.raises(ValueError, match=r"entries \['extra'\] are not those of a DynamicsChe"):
        DynamicsCheck.from_dict({**failing, "extra": 1})
    with pytest.raises(ValueError, match="beyond"):
        DynamicsCheck.from_dict({**check.as_dict(), "beyond": 21})
    # the shift test: its figures kept in records, and refused where a record has no shifts
    shifted = check_dynamics(ensemble, data, shift=True)
    again = DynamicsCheck.from_dict(json.loads(json.dumps(shifted.as_dict())))
    torch.testing.assert_close(again.shift_p_values, shifted.shift_p_values, equal_nan=True)
    assert again.p_value == shifted.p_value and again.describe() == shifted.describe()
    assert "shift_p_values" not in check.as_dict()  # not tested: not recorded
    with pytest.raises(ValueError, match="shift_p_values, shifts: expected both or neither"):
        DynamicsCheck.from_dict({**shifted.as_dict(), "shifts": None})
    with pytest.raises(ValueError, match="shifts: expected values where p_values has them"):
        DynamicsCheck.from_dict({**shifted.as_dict(), "shifts": [None] * 3})
    torch.testing.assert_close(measured.held_out_shifts, ensemble.dynamics.held_out_shifts)
    older = {k: v for k, v in record.items() if k != "held_out_shifts"}  # before shifts
    assert DynamicsNovelty.from_dict(older).held_out_shifts is None
    with pytest.raises(ValueError, match="shift: the held-out errors hold no signed means"):
        check_dynamics(ensemble, data, novelty=DynamicsNovelty.from_dict(older), shift=True)
    with pytest.raises(TypeError, match="shift"):
        check_dynamics(ensemble, data, shift=1)
    with pytest.raises(ValueError, match="held_out_shifts"):
        DynamicsNovelty.from_dict({**record, "held_out_shifts": record["held_out_shifts"][:3]})


def _report(task: str = "") -> CompetencyReport:
    """Two start states' report (the competency tests' hand-made one) of ``task``."""
    data = torch.stack([hand_report(epistemic=e).data for e in (0.2, 0.5)])
    return CompetencyReport(data, ("a", "b", "c", "d"), 600, 0.05, 0.95, task=task)


def test_a_report_with_a_failed_check_is_not_trustworthy(trained):
    ensemble = trained[0].ensemble
    from rcvae_torchrl import fingerprint

    task = fingerprint.task_digest("p", 600, 0.05, ensemble.behaviour())
    failed = check_dynamics(ensemble, episodes(20, 40, 5, gain=0.6, first=1000))
    passed = check_dynamics(ensemble, episodes(20, 40, 6, first=1000))
    report = _report(task)
    assert "dynamics" not in report.warning
    bad = report.with_dynamics_check(failed)
    assert bad.warning.startswith("dynamics check: ") and not bad.trustworthy
    # the warning opens the overview; the split of the doubt is still given its cause (the
    # episodes may have left the training states, where the rise is the model's own account)
    assert bad.overall().startswith("Warning: dynamics check: ")
    assert "this split does not say" not in bad.overall()
    good = report.with_dynamics_check(passed)
    assert "dynamics check" not in good.warning
    assert "Dynamics check: their one-step errors against 1.1 times the held-out" in good.overall()
    assert "they move as the world model learned" in good.overall()
    # saved whole and read back, the check comes along; a record from before it reads as none
    again = CompetencyReport.from_dict(bad.as_dict())
    assert again.dynamics_check.beyond == failed.beyond and again.warning == bad.warning
    older = {k: v for k, v in report.as_dict().items() if k != "dynamics_check"}
    assert CompetencyReport.from_dict(older).dynamics_check is None
    # a record holding another model's check is refused as attaching it was
    theirs = check_dynamics(
        ensemble.select_members([0, 1]),
        episodes(5, 40, 5),
        novelty=DynamicsNovelty.fit(ensemble.select_members([0, 1]), *trained[1:]),
    )
    swapped = {**bad.as_dict(), "dynamics_check": theirs.as_dict()}
    with pytest.raises(ValueError, match=r"values\['dynamics_check'\]: made with another"):
        CompetencyReport.from_dict(swapped)
    broken = {**bad.as_dict(), "dynamics_check": {**failed.as_dict(), "model": 7}}
    with pytest.raises(ValueError, match=r"values\['dynamics_check'\]"):
        CompetencyReport.from_dict(broken)
    other = fingerprint.task_digest("p", 600, 0.05, ensemble.select_members([0]).behaviour())
    with pytest.raises(ValueError, match="another world model"):
        _report(other).with_dynamics_check(failed)
    with pytest.raises(TypeError, match="expected a DynamicsCheck"):
        report.with_dynamics_check(object())
    with pytest.raises(TypeError, match=r"attach it with report\.with_dynamics_check"):
        report.with_forecast_check(failed)
