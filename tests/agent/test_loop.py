"""The model-based RL loop with micro budgets on the Pusher: history rows, files on disk,
resuming rounds."""

from __future__ import annotations

import json
import time
from dataclasses import asdict, replace
from pathlib import Path

import pytest
import torch

from rcvae_torchrl.agent import AgentConfig, AgentTask, PlannerConfig, run_model_based_agent
from rcvae_torchrl.data import TRAJ_KEY, load_episodes
from rcvae_torchrl.envs import make_pusher_env, obs_indices, pusher_reward, pusher_success
from rcvae_torchrl.envs.scripted import ScriptedPusher
from rcvae_torchrl.models import RCVAEConfig
from rcvae_torchrl.training import TrainConfig, load_ensemble
from recipes.pusher_competency.data import collect_pusher_data

CONFIG = AgentConfig(
    rounds=2,
    mpc_episodes=1,
    max_steps=20,
    ensemble_size=2,
    train=TrainConfig(max_steps=10, batch_windows=4, window=8, val_every=5, val_windows=8),
    planner=PlannerConfig(
        horizon=4, num_candidates=16, top_k=4, iterations=1, particles=2, policy_prior=True
    ),
)
TASK = AgentTask(
    make_env=lambda: make_pusher_env(time_limit=1.0),
    model=RCVAEConfig(
        14, 2, hidden_dim=16, mlp_dim=16, passthrough_dims=tuple(obs_indices("target"))
    ),
    reward_fn=pusher_reward,
    success_fn=pusher_success,
    terminate_on_success=True,
    prior=ScriptedPusher(),
)
INITIAL_EPISODES = 3
ROUND_FILES = ("model.pt", "train.pt", "mpc_episodes.pt")
HISTORY_KEYS = {
    "round",
    "train_steps",
    "val_loss",
    "mpc_success_rate",
    "mpc_median_steps",
    "frames",
}


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
    initial = collect_pusher_data(
        scripted_episodes=2,
        random_episodes=1,
        time_limit=2.0,
        random_time_limit=2.0,
        num_envs=1,
        progress=False,
    )

    def run(config):
        return run_model_based_agent(config, TASK, initial, out, progress=False)

    one = run(replace(CONFIG, rounds=1))
    after_one = _snapshot(out)
    two = run(CONFIG)
    after_two = _snapshot(out)
    start = time.perf_counter()
    again = run(CONFIG)
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
        "initial": initial,
    }


def test_history_has_one_row_per_round(runs):
    history = runs["two"].history
    assert [row["round"] for row in history] == [0, 1]
    for row in history:
        assert set(row) == HISTORY_KEYS
        assert row["train_steps"] == CONFIG.train.max_steps
        assert torch.isfinite(torch.tensor(row["val_loss"]))
        assert 0.0 <= row["mpc_success_rate"] <= 1.0
        assert 1 <= row["mpc_median_steps"] <= CONFIG.max_steps
    assert history[0]["frames"] < history[1]["frames"] == runs["two"].data.shape[0]
    assert json.loads((runs["out"] / "history.json").read_text()) == history


def test_files_on_disk(runs):
    out = runs["out"]
    for k in range(CONFIG.rounds):
        for name in ROUND_FILES:
            assert (out / f"round_{k}" / name).is_file()
    assert json.loads((out / "config.json").read_text()) == json.loads(json.dumps(asdict(CONFIG)))
    final = load_ensemble(out / "round_1" / "model.pt")
    for name, value in final.state_dict().items():
        torch.testing.assert_close(value, runs["two"].ensemble.state_dict()[name])


def test_data_gathers_the_initial_and_the_mpc_episodes(runs):
    out, data, initial = runs["out"], runs["two"].data, runs["initial"]
    episodes = [load_episodes(out / f"round_{k}" / "mpc_episodes.pt") for k in range(2)]
    assert data.shape[0] == initial.shape[0] + sum(e.shape[0] for e in episodes)
    ids = torch.unique(data[TRAJ_KEY])
    expected = INITIAL_EPISODES + 2 * CONFIG.mpc_episodes
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
