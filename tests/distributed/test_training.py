"""Ensemble training over 2 gloo ranks equals the single-process run; a killed rank resumes."""

import dataclasses

import pytest
import torch
import workers
from _ranks import run_ranks
from torch.multiprocessing import ProcessExitedException

from rcvae_torchrl.training import train_ensemble

# budgets this small learn too little for the self-checks to pass
pytestmark = pytest.mark.filterwarnings("ignore::rcvae_torchrl.training.ModelCheckWarning")


@pytest.fixture(scope="module")
def single_process():
    train, val = workers.linear_data()
    return train_ensemble(
        workers.small_ensemble(), train, val, workers.CONFIG, progress=False, checks=False
    )


def _assert_same_weights(weights, ensemble):
    for name, value in ensemble.state_dict().items():
        assert torch.equal(weights[name], value), name


def test_sharded_training_equals_single_process(tmp_path, single_process):
    run_ranks(workers.train, str(tmp_path / "out.pt"))
    sharded = torch.load(tmp_path / "out.pt")
    _assert_same_weights(sharded["weights"], single_process.ensemble)
    assert sharded["steps"] == single_process.steps == 40
    assert torch.equal(sharded["best_val"], single_process.best_val)
    assert sharded["history"] == single_process.history


def test_sharded_training_on_bootstrap_resamples_equals_single_process(tmp_path):
    """Each member's resample of the episodes comes from (seed, member): the same on any rank."""
    config = dataclasses.replace(workers.CONFIG, bootstrap=True)
    train, val = workers.linear_data()
    single = train_ensemble(
        workers.small_ensemble(), train, val, config, progress=False, checks=False
    )
    run_ranks(workers.train, str(tmp_path / "out.pt"), None, -1, -1, config)
    _assert_same_weights(torch.load(tmp_path / "out.pt")["weights"], single.ensemble)


def test_a_killed_rank_resumes(tmp_path, single_process):
    ckpt, out = tmp_path / "run.pt", tmp_path / "out.pt"
    with pytest.raises(ProcessExitedException, match="SIGKILL"):
        run_ranks(workers.train, str(out), str(ckpt), 1, 30)
    blocks = sorted(p.name for p in tmp_path.glob("run.members-*.pt"))
    assert blocks == ["run.members-0-1.pt", "run.members-2-3.pt"] and not out.exists()
    killed = torch.load(tmp_path / "run.members-2-3.pt", weights_only=False)
    assert killed["training"]["state"]["step"] == 20  # its last validation before the kill
    run_ranks(workers.train, str(out), str(ckpt))
    resumed = torch.load(out)
    _assert_same_weights(resumed["weights"], single_process.ensemble)
    assert ckpt.is_file() and not list(tmp_path.glob("run.members-*.pt"))
    saved = torch.load(ckpt, weights_only=False)
    assert saved["training"]["state"]["finished"]
    _assert_same_weights(saved["state_dict"], single_process.ensemble)
