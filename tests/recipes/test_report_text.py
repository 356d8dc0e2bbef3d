"""The report's agent section reads as text and tables, not as Python dicts."""

from __future__ import annotations

from recipes.pusher_competency.config import AgentStudyConfig
from recipes.pusher_competency.report import DAGGER_COLUMNS, agent_section

AGENT = {
    "mpc_noisy_success_rate": 0.8666666666666667,
    "mpc_median_steps": 95.0,
    "pairs": 3120.0,
    "policy_success_before": 0.9,
    "train_mse": 0.031912826001644135,
    "val_mse": 0.004118418388068676,
    "epochs": 41.0,
    "dagger": [
        {"round": 0, "pairs": 1500.0, "train_mse": 0.0235, "val_mse": 0.0127, "epochs": 30.0},
        {
            "round": 1,
            "pairs": 3120.0,
            "policy_success_before": 0.9,
            "train_mse": 0.0319,
            "val_mse": 0.0041,
            "epochs": 41.0,
        },
    ],
    "policy_success_rate": 0.95,
    "policy_median_steps": 88.0,
    "seconds": 312.4,
}


def test_agent_section_is_readable():
    text = agent_section(AGENT, AgentStudyConfig(mpc_episodes=15, dagger_rounds=1))
    assert "{" not in text and "[" not in text  # no dict or list reprs
    lines = text.splitlines()
    assert lines[0] == (
        "Settings: 15 MPC episodes with action noise of std 0.3, then 1 DAgger round(s) of 10 "
        "policy episodes, the agent evaluated on 20 episodes."
    )
    assert "| MPC episodes (executed actions perturbed): success rate | 0.867 |" in lines
    assert "| the agent in its evaluation episodes: median steps | 88 |" in lines
    header = "| " + " | ".join(DAGGER_COLUMNS.values()) + " |"
    rows = lines[lines.index(header) + 2 :]
    assert rows == [
        "| 0 | 1500 | – | 0.024 | 0.013 | 30 |",
        "| 1 | 3120 | 0.900 | 0.032 | 0.0041 | 41 |",
    ]


def test_agent_section_without_dagger_rounds():
    text = agent_section({"policy_success_rate": 1.0}, AgentStudyConfig(dagger_rounds=0))
    assert "| the agent in its evaluation episodes: success rate | 1 |" in text
    assert "Distillation rounds" not in text and "| round |" not in text
