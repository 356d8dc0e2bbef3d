"""StateNovelty: distances against closed-form ones, the level's false-alarm rate, words,
checkpoints, training and the assessor's report."""

import dataclasses
import math

import pytest
import torch
from scipy.stats import binom

from rcvae_torchrl.io import load_torch, save_torch
from rcvae_torchrl.training import (
    CheckpointError,
    StateNovelty,
    TrainConfig,
    load_ensemble,
    save_ensemble,
    train_ensemble,
)
from rcvae_torchrl.training.novelty import spread_steps
from tests.training.conftest import linear_episodes


def _gaussian(n: int, seed: int, dim: int = 3) -> torch.Tensor:
    return torch.randn(n, dim, generator=torch.Generator().manual_seed(seed))


def test_distance_is_the_kth_neighbour_in_spreads():
    # two training states on a line, spread 1 in x and 2 in y (std with correction 0)
    states = torch.tensor([[-1.0, -2.0], [1.0, 2.0], [-1.0, 2.0], [1.0, -2.0]])
    novelty = StateNovelty.fit(states, states, k=1)
    assert novelty.scale.tolist() == [1.0, 2.0]
    # (3, 2) is 2 spreads from (1, 2) in x, 0 in y: RMS over 2 dims = 2 / sqrt(2)
    assert float(novelty.distance(torch.tensor([3.0, 2.0]))) == pytest.approx(math.sqrt(2))
    # the 2nd neighbour of (1, 2) is (-1, 2) or (1, -2): 2 spreads in one dimension either way
    second = StateNovelty.fit(states, states, k=2)
    assert float(second.distance(torch.tensor([1.0, 2.0]))) == pytest.approx(math.sqrt(2))
    # batches keep their shape
    assert novelty.distance(torch.zeros(2, 5, 2)).shape == (2, 5)


def test_the_level_calls_about_one_minus_quantile_of_in_distribution_states_unlike():
    novelty = StateNovelty.fit(_gaussian(4000, 0), _gaussian(2000, 1), quantile=0.95)
    fresh = _gaussian(2000, 2)
    flagged = int(novelty.unlike(fresh).sum())
    # a conformal level: P(unlike) <= 5 %; two-sided 99.9 % binomial bounds around 5 %
    low, high = binom.ppf([0.0005, 0.9995], 2000, 0.05)
    assert low <= flagged <= high
    # states 7 spreads out in one of three dimensions are all unlike
    far = fresh.clone()
    far[:, 1] = 7.0
    assert bool(novelty.unlike(far).all())


def _on_circle(n: int, seed: int, radius: float = 1.0) -> torch.Tensor:
    """10 Gaussian dimensions, then a target on a circle (each coordinate within [-1, 1])."""
    g = torch.Generator().manual_seed(seed)
    angle = torch.rand(n, generator=g) * 2 * math.pi
    target = radius * torch.stack([angle.cos(), angle.sin()], dim=-1)
    return torch.cat([torch.randn(n, 10, generator=g), target], dim=-1)


def test_a_group_judged_on_its_own_finds_a_combination_new_only_in_its_dimensions():
    """A start whose target lies inside the circle every training target lies on: each
    coordinate within its range, and near the training states in all 12 dimensions together,
    but far from them in the target's own two. The group finds it; in-distribution starts are
    still called unlike at about the nominal rate, and other states (imagined ones) are judged
    in all dimensions together."""
    train, held_out, fresh = _on_circle(4000, 0), _on_circle(2000, 1), _on_circle(2000, 2)
    inside = _on_circle(200, 3, radius=0.4)
    joint = StateNovelty.fit(train, held_out, quantile=0.95)
    grouped = StateNovelty.fit(train, held_out, quantile=0.95, groups=[(10, 11)])
    assert grouped.groups == ((10, 11),) and grouped.group_scales[0] > 1
    assert float(joint.unlike(inside, starts=True).float().mean()) < 0.2  # diluted
    assert bool(grouped.unlike(inside, starts=True).all())
    torch.testing.assert_close(grouped.ratio(inside), joint.ratio(inside))  # not a start
    low, high = binom.ppf([0.0005, 0.9995], 2000, 0.05)
    for novelty in (joint, grouped):
        assert low <= int(novelty.unlike(fresh, starts=True).sum()) <= high
    # the group's distance, scaled to the joint one's level, where it is the larger
    views = grouped._views(inside)
    scaled = torch.maximum(views[:, 0], views[:, 1] * grouped.group_scales[0])
    torch.testing.assert_close(grouped.distance(inside, starts=True), scaled)
    names = [f"x{i}" for i in range(10)] + ["target[0]", "target[1]"]
    assert grouped.describe(inside[0], names, start=True).endswith(
        "(every dimension within its training range: the combination of target[0], target[1] "
        "is new)"
    )
    # a value a little past its range beside it: the group, the cause, is named first
    edge = inside[0].clone()
    edge[0] = grouped.high[0] + 0.2 * grouped.scale[0]
    assert bool(grouped.outside(edge)[0]) and grouped._range_ratio(edge) <= 1
    said = grouped.describe(edge, names, start=True).split(" are: ")[1]
    assert said.startswith(
        "the combination of target[0], target[1] is new (past the central 99 % of the "
        "training values too: x0 = "
    )
    far = inside[0].clone()
    far[0] = grouped.high[0] + 50 * grouped.scale[0]  # far out: that alone calls it unlike
    assert grouped._range_ratio(far) > 1
    said = grouped.describe(far, names, start=True).split(" are: ")[1]
    assert said.startswith("x0 = ") and said.endswith(
        "; the combination of target[0], target[1] is new"
    )
    # kept in checkpoints; an old record without groups reads as none
    record = grouped.as_dict()
    read = StateNovelty.from_dict(record)
    assert read.groups == grouped.groups and read.group_scales == grouped.group_scales
    assert torch.equal(read.distance(inside, starts=True), grouped.distance(inside, starts=True))
    old = {k: v for k, v in joint.as_dict().items() if not k.startswith("group")}
    assert StateNovelty.from_dict(old).groups == ()
    with pytest.raises(ValueError, match=r"^groups: expected each group as distinct dimensions"):
        StateNovelty.fit(train, held_out, groups=[(10, 12)])
    with pytest.raises(ValueError, match=r"^group_scales: expected one positive scale per"):
        dataclasses.replace(grouped, group_scales=(1.0, 2.0))


def test_groups_are_scaled_on_the_start_states_they_judge():
    """Starts differ from the states in general (a target far at the start, reached soon
    after): each group is put on the joint distance's scale over the first states, so the
    start level stays near the joint one's and fresh starts are called unlike at about the
    nominal rate. Scaled over all states, the target's small spread there set the start level
    several times higher."""
    g = torch.Generator().manual_seed(0)

    def states(n: int, target_spread: float) -> torch.Tensor:
        return torch.cat(
            [torch.randn(n, 10, generator=g), torch.randn(n, 2, generator=g) * target_spread], -1
        )

    train = torch.cat([states(3900, 0.1), states(100, 1.0)])
    firsts = torch.zeros(4000, dtype=torch.bool)
    firsts[3900:] = True
    episodes = torch.cat([torch.arange(3900) % 100, torch.arange(100)])
    args = dict(firsts=firsts, episodes=episodes, held_out_starts=states(300, 1.0), quantile=0.95)
    joint = StateNovelty.fit(train, states(2000, 0.1), **args)
    grouped = StateNovelty.fit(train, states(2000, 0.1), groups=[(10, 11)], **args)
    assert grouped.start_level / joint.start_level < 1.3
    fresh = states(2000, 1.0)
    low, high = binom.ppf([0.0005, 0.9995], 2000, 0.05)
    assert low <= int(grouped.unlike(fresh, starts=True).sum()) <= high
    # a start within the level, every dimension in its range: said to be so, no combination
    calm = fresh[~grouped.unlike(fresh, starts=True) & ~grouped.outside(fresh).any(-1)][0]
    names = [f"x{i}" for i in range(10)] + ["target[0]", "target[1]"]
    assert grouped.describe(calm, names, start=True).endswith(
        "are (within the level: like the training states)"
    )


def test_distances_do_not_depend_on_the_batch_they_come_in():
    """cdist's fast path rounds small distances (about 1e-4 where states repeat a value
    exactly): the nearest are measured again exactly, so a state's distance is the same alone
    or among others, and a training state's own distance is 0."""
    g = torch.Generator().manual_seed(0)
    train = torch.cat([torch.randn(3000, 10, generator=g) * 30, torch.ones(3000, 2)], dim=-1)
    novelty = StateNovelty.fit(train, train[:500] + 0.1, k=1)
    states = train[:40].clone()
    alone = torch.stack([novelty.distance(state[None])[0] for state in states])
    torch.testing.assert_close(novelty.distance(states), alone, rtol=0, atol=1e-6)
    assert float(alone.abs().max()) < 1e-6


def test_entry_groups_are_the_entries_of_several_dimensions():
    from rcvae_torchrl.training import entry_groups

    names = ("position[0]", "position[1]", "speed", "target[0]", "target[1]", "target[2]")
    assert entry_groups(names) == ((0, 1), (3, 4, 5))
    assert entry_groups(("a", "b", "c")) == () and entry_groups(None) == ()
    assert entry_groups(("v[0]", "v[1]")) == ()  # one entry: the joint distance is its own


def test_too_few_held_out_states_keep_the_quantile_they_can_cover():
    novelty = StateNovelty.fit(_gaussian(200, 0), _gaussian(9, 1), quantile=0.99)
    assert novelty.held_out == 9 and novelty.quantile == pytest.approx(0.9)
    assert novelty.level == pytest.approx(float(novelty.distance(_gaussian(9, 1)).max()))


def test_the_draw_keeps_every_kept_state():
    states = _gaussian(1000, 0)
    firsts = torch.zeros(1000, dtype=torch.bool)
    firsts[::100] = True
    novelty = StateNovelty.fit(states, _gaussian(50, 1), max_states=20, firsts=firsts)
    assert 20 <= novelty.states.shape[0] <= 30
    kept = (novelty.states[:, None] == states[firsts][None]).all(-1).any(0)
    assert bool(kept.all())


def test_describe_names_the_dimensions_outside_the_training_range():
    novelty = StateNovelty.fit(_gaussian(2000, 0), _gaussian(500, 1))
    text = novelty.describe(torch.tensor([0.0, 9.0, -0.2]), ["x", "speed", "z"])
    assert text.startswith(f"{float(novelty.ratio(torch.tensor([0.0, 9.0, -0.2]))):.1f}x as far")
    assert "speed = 9 (training " in text and "x =" not in text and "z =" not in text
    both = novelty.describe(torch.tensor([-8.0, 9.0, 0.0]), ["x", "speed", "z"])
    assert both.index("speed") < both.index("x =")  # the farther first
    # a state inside every range whose combination is new
    corner = StateNovelty.fit(
        torch.tensor([[0.0, 0.0], [1.0, 1.0]]).repeat(50, 1) + 0.01 * _gaussian(100, 3, 2),
        torch.tensor([[0.0, 0.0], [1.0, 1.0]]).repeat(10, 1) + 0.01 * _gaussian(20, 4, 2),
    )
    assert "the combination is new" in corner.describe(torch.tensor([0.0, 1.0]))
    # past one dimension's central 99 %, within the level: a cart-pole trial read "0.9x as
    # far from the training states as 99% of held-out states are: x = 3 (training ...)"
    past = torch.tensor([2.9, 0.0, 0.0])
    assert bool(novelty.outside(past)[0]) and float(novelty.ratio(past)) <= 1
    assert novelty.describe(past, ["x", "speed", "z"]).endswith(
        "are (within the level: like the training states as a whole, though past the central "
        f"99 % of their values in x = 2.9 (training {float(novelty.low[0]):.3g} to "
        f"{float(novelty.high[0]):.3g}))"
    )


def test_a_hair_past_a_range_is_not_named_and_a_new_combination_names_its_farthest_dimensions():
    """Training states pile up at the end of a dimension (a cosine of 1): a state there sits
    a rounding past the central 99 %, which is no reason; the dimensions it differs in from
    its nearest training states are."""
    g = torch.Generator().manual_seed(7)
    a = torch.rand(3000, generator=g)
    pile = 1 - 1e-5 * torch.rand(3000, generator=g)  # just below 1
    states = torch.stack(
        [torch.where(a < 0.5, pile, a), a, -a, torch.rand(3000, generator=g)], -1
    )  # dim 0 is about 1 in half the states; dims 1 and 2 move together
    novelty = StateNovelty.fit(states[:2500], states[2500:])
    assert float(novelty.high[0]) < 1.0  # the 99 % range ends a rounding below the pile
    new = torch.tensor([1.0, 0.3, -0.6, 0.5])  # dim 2 = -0.6 never goes with dim 1 = 0.3
    assert novelty.outside(new).tolist() == [False, False, False, False]
    assert bool(novelty.unlike(new))
    text = novelty.describe(new, ["cos", "a", "minus_a", "free"], top=2)
    head = "(every dimension within its training range: the combination is new, farthest from "
    assert text.endswith(head + "the nearest training states in a, minus_a)") or text.endswith(
        head + "the nearest training states in minus_a, a)"
    )  # the two that do not go together, not the cosine at its edge
    # past the range by more than a twentieth of a spread: named
    far = new.clone()
    far[3] = 1.5
    assert novelty.outside(far).tolist() == [False, False, False, True]
    assert "free = 1.5 (training " in novelty.describe(far, ["cos", "a", "minus_a", "free"])


def test_a_dimension_constant_in_training_makes_any_other_value_unlike():
    states = torch.cat([_gaussian(300, 0, 2), torch.full((300, 1), 0.5)], -1)
    held = torch.cat([_gaussian(100, 1, 2), torch.full((100, 1), 0.5)], -1)
    novelty = StateNovelty.fit(states, held)
    assert not bool(novelty.unlike(torch.tensor([0.0, 0.0, 0.5])))
    assert bool(novelty.unlike(torch.tensor([0.0, 0.0, 0.51])))


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"states": torch.zeros(10, 3, dtype=torch.long)}, TypeError, "states: expected a float"),
        ({"states": torch.zeros(10)}, ValueError, r"states: expected shape \[N, D\]"),
        ({"held_out": torch.zeros(10, 2)}, ValueError, "held_out: expected 3 state dim"),
        ({"held_out": torch.full((4, 3), math.nan)}, ValueError, "held_out: expected finite"),
        ({"k": 0}, ValueError, "k: expected"),
        ({"k": 20}, ValueError, "states: expected more than k = 20"),
        ({"quantile": 1.0}, ValueError, r"quantile: expected a share in \(0, 1\)"),
        ({"firsts": torch.ones(3, dtype=torch.bool)}, ValueError, r"firsts: expected a bool"),
        ({"episodes": torch.ones(20)}, ValueError, r"episodes: expected an integer tensor"),
    ],
)
def test_bad_input_is_named(kwargs, error, match):
    args = {"states": _gaussian(20, 0), "held_out": _gaussian(5, 1), **kwargs}
    with pytest.raises(error, match=match):
        StateNovelty.fit(args.pop("states"), args.pop("held_out"), max_states=10, **args)


def test_from_episodes_and_training_fit_one_kept_in_checkpoints(small_ensemble, tmp_path):
    train, val = linear_episodes(12, 40, seed=0), linear_episodes(4, 40, seed=1)
    val["collector", "traj_ids"] += 100
    novelty = StateNovelty.from_episodes(train, val, seed=3)
    # every state and next state of the training episodes (fewer than max_states: all kept)
    assert novelty.states.shape == (2 * 12 * 40, 3) and novelty.held_out == 2 * 4 * 40
    config = TrainConfig(max_steps=20, batch_windows=4, window=5, val_every=10, seed=3)
    result = train_ensemble(small_ensemble(), train, val, config, progress=False, checks=False)
    fitted = result.ensemble.novelty
    assert result.novelty is fitted
    assert result.ensemble.select_members([1]).novelty is fitted  # the data's, any members
    assert torch.equal(fitted.states, novelty.states) and fitted.level == novelty.level
    path = save_ensemble(result.ensemble, tmp_path / "m.pt")
    loaded = load_ensemble(path).novelty
    assert torch.equal(loaded.states, fitted.states) and loaded.as_dict().keys() == (
        fitted.as_dict().keys()
    )
    probe = torch.tensor([[0.0, 0.0, 0.0], [0.0, 30.0, 0.0]])
    assert loaded.unlike(probe).tolist() == [False, True]
    off = train_ensemble(
        small_ensemble(), train, val, config, progress=False, checks=False, novelty=False
    )
    assert off.ensemble.novelty is None and off.novelty is None
    # a corrupt or mismatched record is a CheckpointError naming it
    payload = load_torch(path)
    payload["novelty"]["level"] = -1.0
    save_torch(tmp_path / "bad.pt", payload)
    with pytest.raises(CheckpointError, match=r"novelty\) are corrupt.*novelty.level"):
        load_ensemble(tmp_path / "bad.pt")
    payload["novelty"] = StateNovelty.fit(_gaussian(20, 0, 2), _gaussian(5, 1, 2)).as_dict()
    save_torch(tmp_path / "other.pt", payload)
    with pytest.raises(CheckpointError, match="have 2 dimensions, the model's observations 3"):
        load_ensemble(tmp_path / "other.pt")


def test_from_episodes_names_missing_entries():
    train = linear_episodes(3, 10)
    with pytest.raises(KeyError, match=r"val_data: expected 'observation' and \('next'"):
        StateNovelty.from_episodes(train, train.exclude(("next", "observation")))
    with pytest.raises(TypeError, match="train_data: expected a TensorDict"):
        StateNovelty.from_episodes(torch.zeros(3), train)


def _decaying_episodes(n: int, seed: int, steps: int = 30) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat states [n * steps, 2] and episode ids: starts spread over a box at rest, every
    episode decaying to the origin (dense there, sparse where the starts are)."""
    g = torch.Generator().manual_seed(seed)
    start = torch.rand(n, 2, generator=g) * 2 - 1
    decay = 0.7 ** torch.arange(steps, dtype=torch.float32)
    states = start[:, None] * decay[None, :, None] + 0.01 * torch.randn(n, steps, 2, generator=g)
    ids = torch.arange(n)[:, None].expand(n, steps)
    return states.reshape(-1, 2), (ids + 1000 * seed).reshape(-1)


def _spreading_episodes(n: int, seed: int, steps: int = 30) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat states [n * steps, 2] and episode ids: every episode starts at (1, 1) but for a
    reset's noise of 1e-3, then wanders off (a random walk of steps 0.1)."""
    g = torch.Generator().manual_seed(seed)
    start = 1.0 + 1e-3 * torch.randn(n, 1, 2, generator=g)
    walk = torch.cat([torch.zeros(n, 1, 2), 0.1 * torch.randn(n, steps - 1, 2, generator=g)], 1)
    ids = torch.arange(n)[:, None].expand(n, steps)
    return (start + walk.cumsum(1)).reshape(-1, 2), (ids + 1000 * seed).reshape(-1)


def test_a_start_along_the_training_episodes_course_is_like_the_training_states():
    """Resets that all give one state but for a little noise: their first states' level is
    tiny, and it called every state of an episode's course a new start (a trial's hopper:
    43 of 43 training states taken mid-episode). A start's level is now never below the
    states' in general (measured over them, with every view of a start: its range's too);
    a start far from every training state is still new."""
    train, ids = _spreading_episodes(200, 0)
    held, _ = _spreading_episodes(40, 1)
    firsts = torch.zeros(ids.numel(), dtype=torch.bool)
    firsts[::30] = True
    novelty = StateNovelty.fit(train, held, firsts=firsts, episodes=ids, held_out_starts=held[::30])
    assert novelty.start_level >= novelty.level and novelty.start_held_out == 0
    assert novelty.range_scale > 0.5  # its range view scaled to that level, not to the tiny one
    fresh, _ = _spreading_episodes(1000, 2)
    course = fresh.reshape(1000, 30, 2)[:, 10]  # new episodes' states at step 10, as starts
    assert int(novelty.unlike(course, starts=True).sum()) <= binom.ppf(0.999, 1000, 0.01)
    assert bool(novelty.unlike(torch.tensor([[4.0, -2.0]]), starts=True).all())
    assert "as 99% of held-out states are" in novelty.describe(course[0], start=True)


def test_one_dimension_far_out_of_its_range_makes_a_start_new_however_many_others():
    """In 24 dimensions together one dimension a spread past its training range was diluted
    below the level (a trial's walker: its torso at 2 m, within the level); the range view
    calls it new, and fresh in-distribution starts are still called new at about the nominal
    rate (the start level is measured on the largest view)."""
    g = torch.Generator().manual_seed(3)
    train, held = torch.randn(6000, 24, generator=g), torch.randn(2000, 24, generator=g)
    novelty = StateNovelty.fit(train, held, quantile=0.95)
    assert novelty.range_scale > 0
    far = torch.randn(200, 24, generator=g)
    far[:, 7] = 3.5  # the training range ends near 2.5 spreads
    alone = StateNovelty.fit(train, held, quantile=0.95)._views(far, starts=False)[:, 0]
    assert float((alone / novelty.level > 1).float().mean()) < 0.5  # diluted, all together
    assert bool(novelty.unlike(far, starts=True).all())
    fresh = torch.randn(2000, 24, generator=g)
    low, high = binom.ppf([0.0005, 0.9995], 2000, 0.05)
    assert low <= int(novelty.unlike(fresh, starts=True).sum()) <= high
    assert "dim 7 = 3.5 (training " in novelty.describe(far[0], start=True)
    # kept in its record; a record from before it judges no range
    assert StateNovelty.from_dict(novelty.as_dict()).range_scale == novelty.range_scale
    older = {k: v for k, v in novelty.as_dict().items() if k != "range_scale"}
    assert StateNovelty.from_dict(older).range_scale == 0.0


def test_start_states_and_episodes_are_judged_by_levels_of_their_own():
    train, ids = _decaying_episodes(200, 0)
    held, held_ids = _decaying_episodes(30, 1)
    firsts = torch.zeros(ids.numel(), dtype=torch.bool)
    firsts[::30] = True
    novelty = StateNovelty.fit(
        train,
        held,
        firsts=firsts,
        episodes=ids,
        held_out_starts=held[::30],
        held_out_episodes=held_ids,
    )
    # the start level: 30 held-out first states and 200 training ones, each left out with
    # its episode; 230 distances reach the 99 % quantile
    assert novelty.start_held_out == 230 and novelty.start_quantile == pytest.approx(0.99)
    assert novelty.start_level > novelty.level  # starts lie where the states are sparse
    fresh, _ = _decaying_episodes(1000, 2)
    starts = fresh[::30]
    # new in-distribution starts: beyond the states' level often, beyond their own rarely
    assert float(novelty.unlike(starts).float().mean()) > 0.2
    flagged = int(novelty.unlike(starts, starts=True).sum())
    assert flagged <= binom.ppf(0.999, 1000, 0.01)
    assert "of held-out episodes' first states are" in novelty.describe(
        torch.tensor([3.0, 0.0]), start=True
    )
    # the episode level: the share of an episode's 20 spread states beyond the states' level
    assert novelty.episodes_measured == 230 and 0 < novelty.episode_level < 1
    episodes = fresh.reshape(1000, 30, 2)[:, spread_steps(30)]  # as the check looks at them
    shares = novelty.unlike(episodes).float().mean(-1)
    assert int((shares > novelty.episode_level).sum()) <= binom.ppf(0.999, 1000, 0.01)
    away = novelty.unlike(episodes[:10] + torch.tensor([0.0, 3.0])).float().mean(-1)
    assert bool((away > novelty.episode_level).all())
    # kept in its record
    again = StateNovelty.from_dict(novelty.as_dict())
    assert (again.start_level, again.episode_level, again.episodes_measured) == (
        novelty.start_level,
        novelty.episode_level,
        novelty.episodes_measured,
    )
    bad = {**novelty.as_dict(), "episode_level": 1.5}
    with pytest.raises(ValueError, match=r"novelty\.episode_level: expected a float in"):
        StateNovelty.from_dict(bad)


def _spiking_episodes(n: int, seed: int, steps: int = 30) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat states [n * steps, 21] and episode ids: every episode starts at rest, all zeros but
    for a reset's noise of 1e-3; dimension 0 then wanders off (a random walk of steps 0.1),
    and dimensions 1-20 (a contact's forces) are 0 but for spikes of about 30 (exponential) in
    0.2 % of the steps, past the central 99 % of their values."""
    g = torch.Generator().manual_seed(seed)
    states = torch.zeros(n, steps, 21)
    states[:, 1:, 0] = (0.1 * torch.randn(n, steps - 1, generator=g)).cumsum(1)
    spikes = torch.rand(n, steps - 1, 20, generator=g) < 0.002
    sizes = -30.0 * torch.rand(n, steps - 1, 20, generator=g).log()
    states[:, 1:, 1:] = sizes * spikes
    states += 1e-3 * torch.randn(n, 1, 21, generator=g)
    ids = torch.arange(n)[:, None].expand(n, steps)
    return states.reshape(-1, 21), (ids + 1000 * seed).reshape(-1)


def test_a_start_past_its_range_is_new_where_resets_repeat_and_other_dimensions_spike():
    """A quadruped trial: starts thrown at 2 m/s were like the training states. Its resets
    repeat one state (every view scaled to their tiny level left the range view unheard) and
    its force sensors spike far past their range by nature (which set the range's level). Each
    dimension's excess is read in units of its own largest, and every view is scaled to the
    level the starts are judged by: a start past dimension 0's range is new, starts along the
    course are new about as rarely as the level says."""
    train, ids = _spiking_episodes(400, 0)
    held, held_ids = _spiking_episodes(80, 1)
    firsts = torch.zeros(ids.numel(), dtype=torch.bool)
    firsts[::30] = True
    novelty = StateNovelty.fit(
        train, held, firsts=firsts, episodes=ids, held_out_starts=held[::30],
        held_out_episodes=held_ids,
    )  # fmt: skip
    levels = novelty.range_levels  # the spiking dimensions run far past their range
    assert levels is not None and float(levels[1:].min()) > 2 * float(levels[0])
    thrown = torch.zeros(20, 21)
    thrown[:, 0] = 1.5 * float(train[:, 0].abs().max())  # past everything training saw
    assert bool(novelty.unlike(thrown, starts=True).all())
    fresh, _ = _spiking_episodes(1000, 2)
    course = fresh.reshape(1000, 30, 21)[:, 10]
    assert int(novelty.unlike(course, starts=True).sum()) <= binom.ppf(0.999, 1000, 0.01)
    back = StateNovelty.from_dict(novelty.as_dict())
    assert torch.equal(back.range_levels, novelty.range_levels)
    older = {k: v for k, v in novelty.as_dict().items() if k != "range_levels"}
    assert StateNovelty.from_dict(older).range_levels is None
