"""The model-based RL loop with micro budgets: history rows, files on disk, resuming rounds.

The loop has no length knob for its MPC episodes: each runs to the Pusher's 30 s limit (600
steps; the tiny untrained model never succeeds), about 3 s with this planner budget.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, replace
from pathlib import Path

import pytest
import torch

from rcvae_torchrl.agent import AgentConfig, PlannerConfig, run_model_based_agent
from rcvae_torchrl.data import TRAJ_KEY, load_episodes
from rcvae_torchrl.training import TrainConfig, load_ensemble

CONFIG = AgentConfig(
    rounds=2,
    scripted_episodes=2,
    random_episodes=1,
    data_time_limit=2.0,
    mpc_episodes=1,
    mpc_time_limit=1.0,
    ensemble_size=2,
    hidden_dim=16,
    train=TrainConfig(max_steps=10, batch_windows=4, window=8, val_every=5, val_windows=8),
    planner=PlannerConfig(horizon=4, num_candidates=16, top_k=4, iterations=1, particles=2),
)
ROUND_FILES = ("model.pt", "train.pt", "mpc_episodes.pt")
HISTORY_KEYS = {
    "round",
    "train_steps",
    "val_loss",
    "mpc_success_rate",
    "mpc_median_steps",
    "frames",
}


@pytest.fixture(autouse=True)
def single_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _snapshot(out: Path) -> dict[str, tuple[int, int]]:
    return {
        str(p.relative_to(out)): (p.stat().st_mtime_ns, p.stat().st_size)
        for p in out.rglob("*")
        if p.is_file()
    }


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """One round, then two (the first reused), then two again (both reused)."""
    out = tmp_path_factory.mktemp("agent")
    torch.set_num_threads(1)
    one = run_model_based_agent(replace(CONFIG, rounds=1), out, progress=False)
    after_one = _snapshot(out)
    two = run_model_based_agent(CONFIG, out, progress=False)
    after_two = _snapshot(out)
    start = time.perf_counter()
    again = run_model_based_agent(CONFIG, out, progress=False)
    seconds = time.perf_counter() - start
    return {
        "out": out,
        "one": one,
        "two": two,
        "again": again,
        "after_one": after_one,
        "after_two": after_two,
        "after_again": _snapshot(out),
        "again_s": seconds,
    }


def test_history_has_one_row_per_round(runs):
    history = runs["two"].history
    assert [row["round"] for row in history] == [0, 1]
    for row in history:
        assert set(row) == HISTORY_KEYS
        assert row["train_steps"] == CONFIG.train.max_steps
        assert torch.isfinite(torch.tensor(row["val_loss"]))
        assert 0.0 <= row["mpc_success_rate"] <= 1.0
        assert 1 <= row["mpc_median_steps"] <= 600
    assert history[0]["frames"] < history[1]["frames"] == runs["two"].data.shape[0]
    assert json.loads((runs["out"] / "history.json").read_text()) == history


def test_files_on_disk(runs):
    out = runs["out"]
    assert (out / "data_initial.pt").is_file()
    for k in range(CONFIG.rounds):
        for name in ROUND_FILES:
            assert (out / f"round_{k}" / name).is_file()
    assert json.loads((out / "config.json").read_text()) == json.loads(json.dumps(asdict(CONFIG)))
    final = load_ensemble(out / "round_1" / "model.pt")
    for name, value in final.state_dict().items():
        torch.testing.assert_close(value, runs["two"].ensemble.state_dict()[name])


def test_data_gathers_the_initial_and_the_mpc_episodes(runs):
    out, data = runs["out"], runs["two"].data
    initial = load_episodes(out / "data_initial.pt")
    episodes = [load_episodes(out / f"round_{k}" / "mpc_episodes.pt") for k in range(2)]
    assert data.shape[0] == initial.shape[0] + sum(e.shape[0] for e in episodes)
    ids = torch.unique(data[TRAJ_KEY])
    expected = CONFIG.scripted_episodes + CONFIG.random_episodes + 2 * CONFIG.mpc_episodes
    assert ids.numel() == expected  # MPC episodes got new ids
    assert int(episodes[0][TRAJ_KEY].min()) > int(initial[TRAJ_KEY].max())
    assert set(episodes[0].keys(True, True)) == set(initial.keys(True, True))


def test_resume_reuses_finished_rounds(runs):
    before, after = runs["after_one"], runs["after_two"]
    reused = {k: v for k, v in before.items() if k != "history.json" and k != "config.json"}
    assert reused and all(after[k] == v for k, v in reused.items())  # round 0 not redone
    assert runs["two"].history[0] == runs["one"].history[0]
    assert any(k.startswith("round_1/") for k in after)


def test_a_finished_run_is_not_redone(runs):
    changed = {
        k
        for k, v in runs["after_again"].items()
        if runs["after_two"].get(k) != v and k != "config.json"
    }
    assert not changed
    assert runs["again"].history == runs["two"].history
    assert runs["again"].data.shape == runs["two"].data.shape
    assert runs["again_s"] < 30  # loads two rounds, runs no episode
