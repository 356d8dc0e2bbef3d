"""What each spawned rank runs (importable by name in the spawned processes)."""

from __future__ import annotations

import importlib.util
import os
import signal
import time
import warnings
from pathlib import Path

import torch
from torchrl.envs import DMControlEnv

from rcvae_torchrl import distributed
from rcvae_torchrl.agent import RealOutcomes, draw_starts, real_outcomes, reset_by_seed
from rcvae_torchrl.competency import CompetencyAssessor, SuccessBoundary
from rcvae_torchrl.data import ActionNoise, prepare_env
from rcvae_torchrl.envs import (
    ball_to_target,
    make_batched_pusher_env,
    reset_to_state,
)
from rcvae_torchrl.envs.scripted import make_scripted_policy
from rcvae_torchrl.model_env import RCVAEEnsembleEnv
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.training import TrainConfig, train_ensemble
from tests.pusher_fixtures import pusher_starts

_spec = importlib.util.spec_from_file_location(
    "training_fixtures", Path(__file__).resolve().parents[1] / "training" / "conftest.py"
)
fixtures = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fixtures)

CONFIG = TrainConfig(max_steps=40, batch_windows=16, window=8, val_every=10, val_windows=32)


def linear_data():
    train = fixtures.linear_episodes(12, 40, seed=0)
    val = fixtures.linear_episodes(4, 40, seed=1)
    val[fixtures.TRAJ_KEY] += 100
    return train, val


def small_ensemble(members: int = 4, seed: int = 0) -> RCVAEEnsemble:
    torch.manual_seed(seed)
    return RCVAEEnsemble(RCVAEConfig(3, 1, hidden_dim=16, latent_dim=2, mlp_dim=16), members)


def train(
    out: str,
    ckpt: str | None = None,
    kill_rank: int = -1,
    kill_at: int = -1,
    config: TrainConfig = CONFIG,
) -> None:
    """Train the 4-member ensemble; rank ``kill_rank`` kills itself (SIGKILL) at step
    ``kill_at`` (before that validation's checkpoint); rank 0 saves the result to ``out``."""

    class KillAt:
        def log_scalar(self, name, value, step):
            if distributed.rank() == kill_rank and step == kill_at:
                os.kill(os.getpid(), signal.SIGKILL)

    train_data, val_data = linear_data()
    result = train_ensemble(
        small_ensemble(),
        train_data,
        val_data,
        config,
        checkpoint_path=ckpt,
        resume=ckpt is not None,
        logger=KillAt(),
        progress=False,
        checks=False,
    )
    if distributed.is_main():
        torch.save(
            {
                "weights": result.ensemble.state_dict(),
                "steps": result.steps,
                "best_val": result.best_val,
                "history": result.history,
            },
            out,
        )


# ---------------------------------------------------------------------- forecasts
def make_assessor():
    """A tiny untrained 3-member world model and its assessor (x[0] > 0.05 within 8 steps)."""
    torch.manual_seed(0)
    model = RCVAEEnsemble(RCVAEConfig(3, 1, hidden_dim=8, latent_dim=2, mlp_dim=8), 3)
    g = torch.Generator().manual_seed(0)
    obs = torch.randn(100, 3, generator=g) * 0.1
    model.fit_normalizer(obs, torch.rand(100, 1, generator=g) * 2 - 1, next_observations=obs * 1.1)
    env = RCVAEEnsembleEnv(
        model,
        lambda observation, action: -observation[..., :1],
        lambda observation: observation[..., 0] > 0.05,
    )
    boundary = SuccessBoundary(lambda s: s[..., 0] > 0.05, time_limit=8, dt=0.1)
    return CompetencyAssessor(
        env,
        boundary,
        bin_width=0.05,
        samples_per_member=6,
        start_chunk=2,
        bias_correction="shuffle",
        per_sample={"x": lambda o: o[..., 0]},
    )


def forecast_starts() -> torch.Tensor:
    return torch.randn(7, 3, generator=torch.Generator().manual_seed(1)) * 0.2


def policy(observation: torch.Tensor) -> torch.Tensor:
    return (1.0 - 3.0 * observation[..., :1]).clamp(-1, 1)


def forecast(out: str, seed: int) -> None:
    """Every rank saves the report it gets (``out`` formatted with its rank) and the error of
    a sharded assessment without a seed."""
    assessor = make_assessor()
    try:
        assessor.assess(forecast_starts(), policy=policy)
        error = ""
    except ValueError as err:
        error = str(err)
    report = assessor.assess(forecast_starts(), policy=policy, seed=seed)
    with warnings.catch_warnings(record=True) as caught:  # one chunk for two ranks
        warnings.simplefilter("always")
        assessor.assess(forecast_starts()[:1], policy=policy, seed=seed)
    idle = [str(w.message) for w in caught if "get no work" in str(w.message)]
    saved = {"data": report.data, "error": error, "idle": idle}
    torch.save(saved, out.format(rank=distributed.rank()))


# ---------------------------------------------------------------------- real outcomes
def point_mass():
    env, _ = prepare_env(DMControlEnv("point_mass", "easy"))
    env.append_transform(ActionNoise(1.0))
    return env


def push(td):
    return td.set("action", -5 * td["observation"][..., :2].clamp(-0.2, 0.2))


def near(observation):
    return observation[..., :2].norm(dim=-1) < 0.2


def distance(observation):
    return observation[..., :2].norm(dim=-1)


def outcomes(out: str | None = None) -> dict[str, RealOutcomes]:
    """Outcomes of a noisy point mass (3 starts x 3 runs, one env) and of a noisy Pusher in a
    batched env of 2 (2 starts x 3 runs); every rank saves what it gathered."""
    env = point_mass()
    one_env = real_outcomes(
        env,
        push,
        draw_starts(env, [0, 1, 2]),
        runs_per_start=3,
        reset_to_state=reset_by_seed,
        max_steps=25,
        success=near,
        trace=distance,
        seed=1,
        progress=False,
    )
    batched = real_outcomes(
        make_batched_pusher_env(2, "stochastic", action_noise_std=1.0, time_limit=2.0),
        make_scripted_policy(),
        pusher_starts(2),
        runs_per_start=3,
        reset_to_state=reset_to_state,
        max_steps=40,
        trace=ball_to_target,
        seed=2,
        progress=False,
        policy_rows=64,  # the scripted pusher's actions then do not depend on the batch
    )
    result = {"one_env": one_env, "batched": batched}
    if out is not None:
        saved = {k: v.as_dict() for k, v in result.items()}
        torch.save(saved, out.format(rank=distributed.rank()))
    return result


def train_each_rank(out: str, config: TrainConfig, members: int = 4) -> None:
    """Train the ensemble; every rank saves what it returns to ``<out>.rank<r>``."""
    train_data, val_data = linear_data()
    result = train_ensemble(
        small_ensemble(members), train_data, val_data, config, progress=False, checks=False
    )
    torch.save(
        {"weights": result.ensemble.state_dict(), "history": result.history},
        f"{out}.rank{distributed.rank()}",
    )


def staged(run_dir: str, reuse_from: str | None, out: str) -> None:
    """Two stages on every rank: ``make`` (rank 0 alone) writes ``a.pt``, the sharded
    ``use`` sums it on every rank (rank 0 writes ``b.pt``); each rank saves which stage
    functions it called and the summaries it got to ``out`` (``{rank}`` filled in)."""
    from rcvae_torchrl.io import load_torch, save_torch
    from rcvae_torchrl.stages import StageRunner

    called = []
    root = Path(run_dir)

    def make():
        called.append("make")
        # rank 0 alone: a sharing call acts as one process (the other ranks never join it)
        assert distributed.all_gather("make") == ["make"] and distributed.world_size() == 1
        save_torch(root / "a.pt", torch.arange(4.0))
        return {"n": 4}

    def use():
        called.append("use")
        total = float(load_torch(root / "a.pt", "a").sum())
        if distributed.is_main():
            save_torch(root / "b.pt", torch.tensor(total))
        return {"total": total}

    settings = {"seed": 0, "data": {"n": 4}, "score": {"scale": 2.0 if reuse_from else 1.0}}
    runner = StageRunner(
        root,
        lambda line: None,
        settings=settings,
        stage_settings={"make": ["seed", "data"]},
        reuse_from=reuse_from,
    )
    runner.run("make", make, ("a.pt",))
    runner.run("use", use, ("b.pt",), sharded=True)
    torch.save(
        {"called": called, "summaries": runner.summaries}, out.format(rank=distributed.rank())
    )


def train_in_parts(out: str) -> None:
    """Two ensembles (drawn with seeds 0 and 1) trained at once, each on its part of the ranks
    (:func:`~rcvae_torchrl.distributed.parts`); each part's rank 0 saves its ensemble's weights
    to ``<out>.part<p>``, and every rank what the helpers said within its part and after it to
    ``<out>.rank<r>``."""
    train_data, val_data = linear_data()
    global_rank = distributed.rank()
    errors = []
    for n in (distributed.world_size() + 1, 2):  # more parts than ranks; then nested parts
        try:
            with distributed.parts(n), distributed.parts(1):
                pass
        except ValueError as error:
            errors.append(str(error))
    if global_rank == 0:  # the last to come: no rank may use (or destroy) a group before it
        time.sleep(0.5)
    arrived = time.time()
    with distributed.parts(2) as part:
        seen = {
            "arrived": arrived,
            "entered": time.time(),
            "part": (part.index, part.parts),
            "rank": distributed.rank(),
            "world": distributed.world_size(),
            "gathered": distributed.all_gather(global_rank),
            "broadcast": distributed.broadcast(global_rank, src=distributed.world_size() - 1),
            "replicas": None,
        }
        if distributed.is_active():
            try:
                distributed.replicas(2)
            except ValueError as error:
                seen["replicas"] = str(error)
        result = train_ensemble(
            small_ensemble(seed=part.index), train_data, val_data, CONFIG, progress=False,
            checks=False,
        )  # fmt: skip
        if distributed.is_main():
            torch.save(result.ensemble.state_dict(), f"{out}.part{part.index}")
    seen["after"] = (distributed.rank(), distributed.world_size())
    seen["errors"] = errors
    with distributed.alone():  # no collective call: each rank on its own
        seen["alone"] = (
            distributed.rank(),
            distributed.world_size(),
            distributed.is_active(),
            distributed.all_gather(global_rank),
            distributed.broadcast(global_rank),
        )
        with distributed.parts(2) as part:
            seen["alone"] += ((part.index, part.parts),)
    torch.save(seen, f"{out}.rank{global_rank}")


def jobs_over_ranks(run_dir: str, out: str) -> None:
    """The Pusher recipe's ``Study.over_ranks`` with jobs ``a`` (done: ``stage/a.pt`` exists)
    and ``b``: every rank saves the jobs it ran and what the call returned to
    ``<out>.rank<r>``."""
    from types import SimpleNamespace

    from recipes.pusher_competency.pipeline import Study

    ran = []

    def job(name: str) -> str:
        ran.append(name)
        return f"{name} on {distributed.rank()} of {distributed.world_size()}"

    study = SimpleNamespace(dir=Path(run_dir), say=lambda line: None, job=job)
    study._missing = lambda stage, names: Study._missing(study, stage, names)
    results, elsewhere = Study.over_ranks(study, "stage", ["a", "b"], "job")
    torch.save(
        {"ran": ran, "results": results, "elsewhere": elsewhere}, f"{out}.rank{distributed.rank()}"
    )
