"""Data-parallel training (``TrainConfig.data_parallel``): groups of gloo ranks share every
step's windows, ``DistributedDataParallel`` averaging their gradients."""

import dataclasses

import pytest
import torch
import workers
from _ranks import run_ranks
from torch.multiprocessing import ProcessExitedException, ProcessRaisedException

from rcvae_torchrl.data import make_window_buffer, sample_windows
from rcvae_torchrl.objectives import RCVAELoss
from rcvae_torchrl.training import TrainConfig, train_ensemble
from rcvae_torchrl.training import trainer as trainer_module

# budgets this small learn too little for the self-checks to pass
pytestmark = pytest.mark.filterwarnings("ignore::rcvae_torchrl.training.ModelCheckWarning")

PARALLEL = dataclasses.replace(workers.CONFIG, data_parallel=2)


def _group_mean_reference(config: TrainConfig, replicas: int):
    """The data-parallel update written out in one process: every step's windows drawn as a
    single process draws them, cut into ``replicas`` equal shares, each share's gradient taken
    with that replica's noise, the gradients averaged, then clipping and Adam as usual."""
    train, _ = workers.linear_data()
    model = workers.small_ensemble()
    model.fit_normalizer(
        train["observation"], train["action"], next_observations=train["next", "observation"]
    )
    members, cpu = range(model.ensemble_size), torch.device("cpu")
    windows_rng = trainer_module._generators(config.seed, members, trainer_module._WINDOWS, cpu)
    noise = trainer_module._NOISE
    losses = [
        RCVAELoss(model, generator=trainer_module._generators(config.seed, members, keys, cpu))
        for keys in [(noise,)] + [(noise, i) for i in range(1, replicas)]
    ]
    buffer = make_window_buffer(train, config.window)
    params = list(model.parameters())
    optimizer = trainer_module._adam(params, config.lr)
    share = config.batch_windows // replicas
    for step in range(config.max_steps):
        windows = sample_windows(
            buffer, config.batch_windows, config.window, len(members), windows_rng
        )
        mean = [torch.zeros_like(p) for p in params]
        for i, loss_fn in enumerate(losses):
            out = loss_fn(windows[:, i * share : (i + 1) * share])
            optimizer.zero_grad(set_to_none=True)
            (out["loss_reconstruction"] + out["loss_kl"]).backward()
            mean = [m + p.grad / replicas for m, p in zip(mean, params, strict=True)]
        for p, g in zip(params, mean, strict=True):
            p.grad = g
        for group in optimizer.param_groups:
            group["lr"] = config.lr_at(step)
        trainer_module.clip_grad_norm_per_member(params, config.grad_clip)
        optimizer.step()
    return model


def _load(out, rank):
    return torch.load(f"{out}.rank{rank}")


def _assert_same_weights(a, b):
    assert a.keys() == b.keys()
    for name in a:
        assert torch.equal(a[name], b[name]), name


def test_a_data_parallel_step_is_the_mean_of_the_shares_gradients(tmp_path):
    # one validation, at the end: the returned (best) weights are the last ones
    config = dataclasses.replace(PARALLEL, max_steps=6, val_every=6)
    run_ranks(workers.train_each_rank, str(tmp_path / "out"), config)
    reference = _group_mean_reference(config, replicas=2)
    for rank in (0, 1):  # the group's ranks hold the same weights
        _assert_same_weights(_load(tmp_path / "out", rank)["weights"], reference.state_dict())


def test_data_parallel_results_depend_on_the_group_size_not_the_number_of_groups(tmp_path):
    """4 ranks in 2 groups of 2 (2 members each) give the ensemble of 1 group of 2 ranks."""
    run_ranks(workers.train_each_rank, str(tmp_path / "one"), PARALLEL)
    run_ranks(workers.train_each_rank, str(tmp_path / "two"), PARALLEL, world=4)
    one, two = _load(tmp_path / "one", 0), _load(tmp_path / "two", 0)
    _assert_same_weights(one["weights"], two["weights"])
    assert one["history"] == two["history"]
    for rank in (1, 2, 3):
        _assert_same_weights(_load(tmp_path / "two", rank)["weights"], two["weights"])
    # and they differ from member sharding alone (each rank draws its own noise)
    run_ranks(workers.train_each_rank, str(tmp_path / "shards"), workers.CONFIG)
    shards = _load(tmp_path / "shards", 0)["weights"]
    assert not torch.equal(shards["gru.input_proj.weight"], one["weights"]["gru.input_proj.weight"])


def test_a_killed_data_parallel_rank_resumes(tmp_path):
    ckpt, out, whole = tmp_path / "run.pt", tmp_path / "out.pt", tmp_path / "whole.pt"
    run_ranks(workers.train, str(whole), None, -1, -1, PARALLEL)
    with pytest.raises(ProcessExitedException, match="SIGKILL"):
        run_ranks(workers.train, str(out), str(ckpt), 1, 30, PARALLEL)
    # one checkpoint for the group, from its first rank, with both ranks' noise generators
    assert not list(tmp_path.glob("run.members-*.pt")) and not out.exists()
    saved = torch.load(ckpt, weights_only=False)["training"]
    assert saved["state"]["step"] in (20, 30) and len(saved["replica_rng"]) == 2
    run_ranks(workers.train, str(out), str(ckpt), -1, -1, PARALLEL)
    _assert_same_weights(torch.load(out)["weights"], torch.load(whole)["weights"])
    assert torch.load(out)["history"] == torch.load(whole)["history"]
    assert ckpt.is_file() and not list(tmp_path.glob("run.members-*.pt"))


def test_resuming_with_another_group_size_is_refused(tmp_path):
    ckpt, out = tmp_path / "run.pt", tmp_path / "out.pt"
    with pytest.raises(ProcessExitedException, match="SIGKILL"):
        run_ranks(workers.train, str(out), str(ckpt), 1, 30, PARALLEL)
    with pytest.raises(ProcessRaisedException, match="holds an unfinished run of all members"):
        run_ranks(workers.train, str(out), str(ckpt), -1, -1, workers.CONFIG)
    assert torch.load(ckpt, weights_only=False)["training"]["config"]["data_parallel"] == 2


def test_a_group_size_that_does_not_divide_the_ranks_is_refused(tmp_path):
    config = dataclasses.replace(workers.CONFIG, data_parallel=4)
    with pytest.raises(
        ProcessRaisedException, match="data_parallel: expected a divisor of the world"
    ):
        run_ranks(workers.train_each_rank, str(tmp_path / "out"), config)


@pytest.mark.parametrize("value", [0, 3, 2.0, True])
def test_bad_data_parallel_settings_are_refused(value):
    with pytest.raises(ValueError, match="data_parallel"):
        dataclasses.replace(workers.CONFIG, data_parallel=value)


def test_without_a_process_group_data_parallel_changes_nothing():
    train, val = workers.linear_data()
    runs = [
        train_ensemble(workers.small_ensemble(), train, val, c, progress=False, checks=False)
        for c in (workers.CONFIG, PARALLEL)
    ]
    _assert_same_weights(runs[0].ensemble.state_dict(), runs[1].ensemble.state_dict())
