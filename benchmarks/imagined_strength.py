"""The actuator strength a stochastic Pusher model imagines, against the real one.

With ``data.stochastic_strength`` the real arm draws its strength once per episode, uniformly in
a range, and nothing in the observation shows it. This script measures the strength a trained
stochastic world model imagines: the scripted pusher acts in the real env (strength at the
range's middle) from ``--starts`` start states; its commands are replayed open loop in the real
env at every strength of a grid, and in the model (``--samples`` per member). Each imagined
episode, per time window, gets the grid strength whose real replay its joint velocities match
best (least squares). Printed and written to ``benchmarks/results/imagined_strength.json``:

- per time window: the imagined strengths' median, 10 % and 90 % quantiles and the mean of each
  member, beside the real range's;
- the correlation of an episode's imagined strength between time windows (a strength held for
  the episode correlates; one redrawn every step does not);
- with history: the model fed ``--history`` real steps of an episode of known strength (low,
  middle, high of the range) first, then imagining the next 30 steps: what it infers.

    python benchmarks/imagined_strength.py RUN_DIR [--starts 20] [--samples 10]
                                           [--history 0 10 30] [--out imagined_strength]

``RUN_DIR`` is a study run made with a strength range (its ``study_config.json`` gives the
range, its ``models/stochastic.pt`` the model).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from _report import conditions, print_table, write_json
from tensordict import TensorDict

from rcvae_torchrl.agent import draw_starts
from rcvae_torchrl.envs import (
    CONTROL_TIMESTEP,
    make_batched_pusher_env,
    make_pusher_env,
    obs_indices,
)
from rcvae_torchrl.envs.scripted import make_scripted_policy
from rcvae_torchrl.rollout import imagine
from rcvae_torchrl.training import load_ensemble
from recipes.pusher_competency.pusher import MODEL_FUNCTIONS

WINDOWS = ((0, 10), (10, 30), (30, 60), (60, 120), (120, 240))  # steps
START_SEED = 12_345
GRID_STEP = 0.025


def real_run(
    strength: float, starts: torch.Tensor, steps: int, actions: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """States ``[B, steps + 1, S]`` and commands ``[B, steps, A]`` of the real arm at a fixed
    strength from ``starts``: the scripted pusher's (closed loop) or the given ``actions``."""
    n = starts.shape[0]
    env = make_batched_pusher_env(
        n,
        "stochastic",
        action_noise_std=0.0,
        actuator_strength=(strength, strength),
        time_limit=steps * CONTROL_TIMESTEP,
        terminate_on_success=False,
        seed=0,
    )
    policy = make_scripted_policy()
    td = env.reset(TensorDict(observation=starts, batch_size=[n]), set_state=True)
    states, commands = [td["observation"]], []
    for t in range(steps):
        if actions is None:
            action = policy(td.select("observation").clone())["action"].clamp(-1, 1)
        else:
            action = actions[:, t]
        td["action"] = action
        commands.append(action)
        td = env.step(td)["next"]
        states.append(td["observation"])
    return torch.stack(states, 1), torch.stack(commands, 1)


def matched_strength(
    trajectories: torch.Tensor, bank: torch.Tensor, grid: torch.Tensor, window: tuple[int, int]
) -> torch.Tensor:
    """Per trajectory ``[..., B, T + 1, S]``, the grid strength whose real replay (``bank``
    ``[G, B, T + 1, S]``) its joint velocities match best over ``window``: ``[..., B]``."""
    joints = obs_indices("joint_vel")
    a, b = window
    mine = trajectories[..., a + 1 : b + 1, joints]
    ref = bank[:, :, a + 1 : b + 1, joints]
    ref = ref.view(len(grid), *([1] * (mine.dim() - 3)), *ref.shape[1:])
    return grid[((mine.unsqueeze(0) - ref) ** 2).sum((-1, -2)).argmin(0)]


def quantiles(x: torch.Tensor) -> list[float]:
    return [round(float(v), 3) for v in torch.quantile(x.flatten(), torch.tensor([0.1, 0.5, 0.9]))]


@torch.no_grad()
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--starts", type=int, default=20)
    parser.add_argument("--samples", type=int, default=10, help="imagined episodes per member")
    parser.add_argument("--history", type=int, nargs="+", default=[0, 10, 30])
    parser.add_argument("--out", default="imagined_strength")
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = json.loads((args.run_dir / "study_config.json").read_text())
    low, high = config["data"]["stochastic_strength"]
    middle, steps = (low + high) / 2, WINDOWS[-1][1]
    grid = torch.arange(max(low - 0.1, GRID_STEP), high + 0.1 + 1e-9, GRID_STEP)
    model = load_ensemble(args.run_dir / "models" / "stochastic.pt", functions=MODEL_FUNCTIONS)
    seeds = range(START_SEED, START_SEED + args.starts)
    starts = draw_starts(make_pusher_env("stochastic"), seeds)["observation"]
    _, commands = real_run(middle, starts, steps)
    bank = torch.stack([real_run(float(g), starts, steps, commands)[0] for g in grid])
    g = torch.Generator().manual_seed(0)
    rollouts = imagine(model, starts, commands, samples_per_member=args.samples, generator=g)
    first = starts.expand(*rollouts.batch_size[:3], starts.shape[-1]).unsqueeze(-2)
    imagined = torch.cat([first, rollouts["observation"]], dim=-2)  # [E, N, B, T + 1, S]
    real_q = [round(low + q * (high - low), 3) for q in (0.1, 0.5, 0.9)]
    rows, per_window = [], []
    for window in WINDOWS:
        found = matched_strength(imagined, bank, grid, window)  # [E, N, B]
        per_window.append(found.flatten(1))
        members = [round(float(m), 3) for m in found.mean((1, 2))]
        seconds = f"{window[0] * CONTROL_TIMESTEP:g}-{window[1] * CONTROL_TIMESTEP:g} s"
        rows.append([seconds, *quantiles(found), *real_q, str(members)])
    print_table(
        f"imagined strength, no history ({args.run_dir})",
        ["window", "q10", "median", "q90", "real q10", "real median", "real q90", "member means"],
        rows,
    )
    correlation = torch.corrcoef(torch.stack([w.flatten() for w in per_window]))
    print("correlation of an episode's imagined strength between the windows:")
    print(correlation.numpy().round(2))
    history_rows = []
    span = high - low
    for strength in (low + span / 8, middle, high - span / 8):
        states, episode_commands = real_run(strength, starts, max(args.history) + 30)
        for k in args.history:
            later = episode_commands[:, k : k + 30]
            replay = torch.stack([real_run(float(s), states[:, k], 30, later)[0] for s in grid])
            found = imagine_after(model, states, episode_commands, k, args.samples, g)
            match = matched_strength(found, replay, grid, (0, 30))
            history_rows.append([round(strength, 3), k, *quantiles(match)])
    print_table(
        "imagined strength of the next 1.5 s after k real steps of an episode of known strength",
        ["true strength", "history steps", "q10", "median", "q90"],
        history_rows,
    )
    write_json(
        args.out,
        {
            "benchmark": "imagined_strength",
            "run_dir": str(args.run_dir),
            "strength_range": [low, high],
            "starts": args.starts,
            "samples_per_member": args.samples,
            "windows_s": [[a * CONTROL_TIMESTEP, b * CONTROL_TIMESTEP] for a, b in WINDOWS],
            "no_history": [dict(zip(["window", "q10", "median", "q90"], r[:4])) for r in rows],
            "member_means": [r[-1] for r in rows],
            "window_correlation": correlation.tolist(),
            "with_history": [
                dict(zip(["strength", "history_steps", "q10", "median", "q90"], r))
                for r in history_rows
            ],
            "conditions": conditions(),
        },
    )


def imagine_after(model, states, commands, k, samples, generator) -> torch.Tensor:
    """The model fed the real ``states[:, :k]`` and their commands (teacher forced), then
    imagining 30 steps of the episode's next commands from ``states[:, k]``:
    ``[E, N, B, 31, S]``."""
    e, n, b = model.ensemble_size, samples, states.shape[0]
    hidden = model.initial_hidden((n, b), states, generator)

    def every(x: torch.Tensor) -> torch.Tensor:
        return x.expand(e, n, *x.shape)

    for t in range(k):
        hidden = model.step(hidden, every(states[:, t]), every(commands[:, t]),
                            generator=generator).hidden  # fmt: skip
    state, out = every(states[:, k]), [every(states[:, k])]
    for t in range(k, k + 30):
        step = model.step(hidden, state, every(commands[:, t]), generator=generator)
        hidden, state = step.hidden, step.observation
        out.append(state)
    return torch.stack(out, dim=-2)


if __name__ == "__main__":
    main()
