"""train_ensemble: learning, determinism, early stopping, logging, resume after kill -9."""

import dataclasses
import itertools
import logging
import signal
import subprocess
import sys
import textwrap

import pytest
import torch

from rcvae_torchrl.io import load_torch
from rcvae_torchrl.training import CheckpointError, TrainConfig, train_ensemble
from rcvae_torchrl.training.trainer import clip_grad_norm_per_member

CONFIG = TrainConfig(max_steps=40, batch_windows=16, window=8, val_every=10, val_windows=32)

# budgets this small learn too little for the self-checks to pass: their warnings are expected
pytestmark = pytest.mark.filterwarnings("ignore::rcvae_torchrl.training.ModelCheckWarning")


def _weights(ensemble):
    return {k: v.clone() for k, v in ensemble.state_dict().items()}


def test_learns_and_logs(linear_data, small_ensemble, tmp_path):
    train, val = linear_data
    config = TrainConfig(max_steps=120, batch_windows=16, window=8, val_every=20, lr=3e-3)
    result = train_ensemble(
        small_ensemble(), train, val, config, checkpoint_path=tmp_path / "c.pt", progress=False
    )
    first, last = result.history[0]["val_loss"], result.history[-1]["best_val_loss"]
    assert last < first - 0.5, f"validation loss should fall: {first:.3f} -> {last:.3f}"
    assert result.best_val.shape == (3,) and torch.isfinite(result.best_val).all()
    logs = list((tmp_path / "logs").rglob("val_loss.csv"))
    assert logs and len(logs[0].read_text().strip().splitlines()) == len(result.history)


def test_same_seed_same_result(linear_data, small_ensemble):
    train, val = linear_data
    a = train_ensemble(small_ensemble(seed=1), train, val, CONFIG, progress=False).ensemble
    b = train_ensemble(small_ensemble(seed=1), train, val, CONFIG, progress=False).ensemble
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(x, y), name


def test_windows_from_episode_starts_change_the_training(linear_data, small_ensemble):
    """``episode_start_fraction`` puts windows at episode starts: a reproducible run that
    differs from the uniform one (a member's windows still come from its own generator)."""
    import dataclasses

    train, val = linear_data
    starts = dataclasses.replace(CONFIG, episode_start_fraction=0.5)
    a = train_ensemble(small_ensemble(seed=1), train, val, starts, progress=False).ensemble
    b = train_ensemble(small_ensemble(seed=1), train, val, starts, progress=False).ensemble
    c = train_ensemble(small_ensemble(seed=1), train, val, CONFIG, progress=False).ensemble
    assert all(torch.equal(x, y) for x, y in zip(a.parameters(), b.parameters()))
    assert not all(torch.equal(x, y) for x, y in zip(a.parameters(), c.parameters()))
    with pytest.raises(ValueError, match=r"episode_start_fraction: expected a float in \[0, 1\]"):
        TrainConfig(episode_start_fraction=1.5)


def test_bootstrap_resamples_change_the_training(linear_data, small_ensemble):
    """``bootstrap``: each member on its own resample of the episodes, reproducibly."""
    import dataclasses

    train, val = linear_data
    boot = dataclasses.replace(CONFIG, bootstrap=True)
    a = train_ensemble(small_ensemble(seed=1), train, val, boot, progress=False).ensemble
    b = train_ensemble(small_ensemble(seed=1), train, val, boot, progress=False).ensemble
    c = train_ensemble(small_ensemble(seed=1), train, val, CONFIG, progress=False).ensemble
    assert all(torch.equal(x, y) for x, y in zip(a.parameters(), b.parameters()))
    assert not all(torch.equal(x, y) for x, y in zip(a.parameters(), c.parameters()))
    with pytest.raises(ValueError, match="bootstrap: expected True or False, got 1"):
        TrainConfig(bootstrap=1)


def test_early_stopping(linear_data, small_ensemble):
    train, val = linear_data
    frozen = TrainConfig(
        max_steps=1000, batch_windows=8, window=8, val_every=5, lr=1e-30, patience=2
    )
    result = train_ensemble(small_ensemble(), train, val, frozen, progress=False)
    assert result.stopped_early and result.steps == 15  # best at 5, no gain at 10 and 15


_SCRIPT = textwrap.dedent(
    """
    import logging, os, signal, sys, torch
    logging.basicConfig(level=logging.INFO)  # the library's lines to stderr
    sys.path.insert(0, {tests!r})
    from conftest import linear_episodes
    from rcvae_torchrl.data import TRAJ_KEY
    from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
    from rcvae_torchrl.training import TrainConfig, train_ensemble

    class KillAt:
        def log_scalar(self, name, value, step):
            if step == {kill_at}:
                os.kill(os.getpid(), signal.SIGKILL)

    train, val = linear_episodes(12, 40, 0), linear_episodes(4, 40, 1)
    val[TRAJ_KEY] += 100
    torch.manual_seed(0)
    model = RCVAEEnsemble(RCVAEConfig(3, 1, hidden_dim=16, latent_dim=2, mlp_dim=16), 3)
    config = TrainConfig(max_steps=40, batch_windows=16, window=8, val_every=10, val_windows=32,
                         lr_final_fraction=0.1)
    result = train_ensemble(model, train, val, config, checkpoint_path={ckpt!r},
                            resume=True, logger=KillAt(), progress=False)
    torch.save(result.ensemble.state_dict(), {out!r})
    """
)


def _run(tmp_path, kill_at, ckpt, out):
    tests = str(__import__("pathlib").Path(__file__).parent)
    code = _SCRIPT.format(tests=tests, kill_at=kill_at, ckpt=str(ckpt), out=str(out))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=300)


def test_resume_after_kill_matches_an_uninterrupted_run(tmp_path):
    ckpt, out = tmp_path / "run.pt", tmp_path / "final.pt"
    killed = _run(tmp_path, kill_at=30, ckpt=ckpt, out=out)
    assert killed.returncode == -signal.SIGKILL, killed.stderr.decode()[-2000:]
    assert ckpt.exists() and not out.exists()
    resumed = _run(tmp_path, kill_at=-1, ckpt=ckpt, out=out)
    assert resumed.returncode == 0, resumed.stderr.decode()[-2000:]
    assert f"resuming from {ckpt} at step 20 of 40" in resumed.stderr.decode()  # saved at 20
    reference = _run(tmp_path, kill_at=-1, ckpt=tmp_path / "ref.pt", out=tmp_path / "ref_final.pt")
    assert reference.returncode == 0, reference.stderr.decode()[-2000:]
    a, b = torch.load(out), torch.load(tmp_path / "ref_final.pt")
    for name in a:
        assert torch.equal(a[name], b[name]), name


def test_cosine_learning_rate_schedule():
    config = TrainConfig(max_steps=100, lr=2e-3, lr_final_fraction=0.1)
    assert config.lr_at(0) == pytest.approx(2e-3)
    assert config.lr_at(50) == pytest.approx(0.5 * (2e-3 + 2e-4))
    assert config.lr_at(100) == pytest.approx(2e-4)
    rates = [config.lr_at(s) for s in range(101)]
    assert all(a >= b for a, b in itertools.pairwise(rates))
    constant = TrainConfig(max_steps=100, lr=2e-3)
    assert {constant.lr_at(s) for s in (0, 37, 100)} == {2e-3}
    with pytest.raises(ValueError, match=r"lr_final_fraction: expected a float in \(0, 1\]"):
        TrainConfig(lr_final_fraction=0.0)


def test_decayed_learning_rate_changes_training(linear_data, small_ensemble):
    train, val = linear_data
    decayed = TrainConfig(**{**CONFIG.__dict__, "lr_final_fraction": 0.01})
    a = train_ensemble(small_ensemble(seed=1), train, val, CONFIG, progress=False).ensemble
    b = train_ensemble(small_ensemble(seed=1), train, val, decayed, progress=False).ensemble
    assert not torch.equal(a.embed.weight, b.embed.weight)


def test_finished_run_is_not_trained_again(linear_data, small_ensemble, tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="rcvae_torchrl")
    train, val = linear_data
    ckpt = tmp_path / "c.pt"
    first = train_ensemble(
        small_ensemble(), train, val, CONFIG, checkpoint_path=ckpt, progress=False
    )
    again = train_ensemble(
        small_ensemble(seed=9),
        train,
        val,
        CONFIG,
        checkpoint_path=ckpt,
        resume=True,
        progress=False,
    )
    assert again.steps == first.steps == 40
    for x, y in zip(first.ensemble.state_dict().values(), again.ensemble.state_dict().values()):
        assert torch.equal(x, y)
    assert f"{ckpt} holds a finished run (40 steps): its best weights are loaded" in caplog.text


def test_a_checkpoint_from_before_a_new_setting_resumes(linear_data, small_ensemble, tmp_path):
    """A setting added to TrainConfig after a checkpoint was written had its default then."""
    train, val = linear_data
    ckpt = tmp_path / "c.pt"
    first = train_ensemble(
        small_ensemble(), train, val, CONFIG, checkpoint_path=ckpt, progress=False
    )
    payload = load_torch(ckpt)  # as written then: without the setting, and without a checksum
    del payload["training"]["config"]["bootstrap"]
    torch.save(payload, ckpt)
    again = train_ensemble(
        small_ensemble(seed=9), train, val, CONFIG, checkpoint_path=ckpt, resume=True
    )
    assert again.steps == first.steps
    with pytest.raises(CheckpointError, match="another TrainConfig"):
        train_ensemble(
            small_ensemble(),
            train,
            val,
            dataclasses.replace(CONFIG, bootstrap=True),
            checkpoint_path=ckpt,
            resume=True,
        )


def test_a_compiled_loss_trains_as_the_eager_one(linear_data, small_ensemble):
    """``compile=True``: the same run up to float rounding (fused kernels), not bit for bit."""
    train, val = linear_data
    config = dataclasses.replace(CONFIG, max_steps=10, val_every=5)
    eager = train_ensemble(small_ensemble(seed=1), train, val, config, progress=False)
    compiled = dataclasses.replace(config, compile=True)
    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    fused = train_ensemble(small_ensemble(seed=1), train, val, compiled, progress=False)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] >= 1  # it did compile
    assert fused.steps == eager.steps
    for (name, x), y in zip(
        eager.ensemble.state_dict().items(), fused.ensemble.state_dict().values()
    ):
        torch.testing.assert_close(y, x, rtol=1e-4, atol=1e-5, msg=name)
    with pytest.raises(ValueError, match="compile: expected True or False, got 1"):
        TrainConfig(compile=1)


def test_the_compiled_loss_is_called_with_the_garbage_collector_paused(
    linear_data, small_ensemble, compiled_calls_paused
):
    """A finalizer that changes torch's thread count during a trace fails it (the fresh-clone
    suite failed the test above so once): every call of the compiled loss runs with the
    collector paused. ``torch.compile`` is replaced by a recorder here."""
    import gc

    train, val = linear_data
    config = dataclasses.replace(CONFIG, max_steps=4, val_every=2, compile=True)
    train_ensemble(small_ensemble(seed=1), train, val, config, progress=False)
    assert compiled_calls_paused == [True] * 4 and gc.isenabled()


def test_bad_resume_arguments(linear_data, small_ensemble, tmp_path):
    train, val = linear_data
    with pytest.raises(ValueError, match="resume: expected a checkpoint_path"):
        train_ensemble(small_ensemble(), train, val, CONFIG, resume=True)
    ckpt = tmp_path / "c.pt"
    train_ensemble(small_ensemble(), train, val, CONFIG, checkpoint_path=ckpt, progress=False)
    other = TrainConfig(max_steps=50, batch_windows=16, window=8, val_every=10)
    with pytest.raises(CheckpointError, match="another TrainConfig"):
        train_ensemble(small_ensemble(), train, val, other, checkpoint_path=ckpt, resume=True)
    with pytest.raises(ValueError, match="window: expected >= 2"):
        TrainConfig(window=1)


def test_gradients_are_clipped_member_by_member():
    g = torch.Generator().manual_seed(0)
    grads = [torch.randn(3, 4, 5, generator=g), torch.randn(3, 7, generator=g)]
    grads[0][1] *= 100  # member 1 far above the bound, the others near it
    params = [torch.zeros_like(x, requires_grad=True) for x in grads]
    for p, x in zip(params, grads):
        p.grad = x.clone()
    norms = clip_grad_norm_per_member(params, max_norm=5.0)
    for m in range(3):
        alone = [torch.zeros_like(x[m], requires_grad=True) for x in grads]
        for p, x in zip(alone, grads):
            p.grad = x[m].clone()
        expected = torch.nn.utils.clip_grad_norm_(alone, 5.0)
        torch.testing.assert_close(norms[m], expected)
        for p, q in zip(params, alone):
            torch.testing.assert_close(p.grad[m], q.grad)
    assert norms[1] > 100 and torch.stack([p.grad[1].norm() ** 2 for p in params]).sum() < 25.01


def test_a_block_of_members_is_clipped_as_in_the_whole_ensemble():
    """A cart-pole trial trained 4 members in one process and 2 per rank on 2 ranks: the
    weights parted (by 0.09 to 0.30 after 3,000 steps) once clipping set in, as the members'
    norms were summed over the stacked tensors' axis, which rounds otherwise for 2 members
    than for 4. A block's norms and clipped gradients are now the whole ensemble's, bits and
    all."""
    shapes = [(4, 6, 32), (4, 32), (4, 32, 96), (4, 96), (4, 8), (4, 64, 16)] * 3

    def clipped(grads: list[torch.Tensor], members: slice) -> tuple[torch.Tensor, list]:
        params = [torch.zeros_like(x[members], requires_grad=True) for x in grads]
        for p, x in zip(params, grads, strict=True):
            p.grad = x[members].clone()
        return clip_grad_norm_per_member(params, 100.0), [p.grad for p in params]

    for trial in range(40):
        g = torch.Generator().manual_seed(trial)
        grads = [torch.randn(shape, generator=g) * 30 for shape in shapes]
        norms, whole = clipped(grads, slice(0, 4))
        assert (norms > 100).all()  # clipping in force
        for block in (slice(0, 2), slice(2, 4), slice(1, 2)):
            part, clipped_part = clipped(grads, block)
            assert torch.equal(part, norms[block]), (trial, block)
            assert all(torch.equal(a, b[block]) for a, b in zip(clipped_part, whole, strict=True))


def test_gradients_under_the_bound_are_left_as_they_are():
    g = torch.Generator().manual_seed(1)
    params = [torch.zeros(2, 3, 4, requires_grad=True), torch.zeros(2, 5, requires_grad=True)]
    for p in params:
        p.grad = torch.randn(p.shape, generator=g)
    before = [p.grad.clone() for p in params]
    norms = clip_grad_norm_per_member(params, max_norm=100.0)
    assert (norms < 100).all()
    assert all(torch.equal(p.grad, b) for p, b in zip(params, before, strict=True))


def test_a_training_loss_that_is_not_finite_stops_the_run_at_the_next_validation(
    linear_data, small_ensemble, tmp_path
):
    """A step reads nothing back from the device; the training loss is read at each
    validation, and a non-finite one ends the run there, naming the steps, before a
    checkpoint of the spoilt weights is written."""
    train, val = linear_data
    config = TrainConfig(max_steps=40, batch_windows=8, window=8, val_every=10, lr=1e30)
    ckpt = tmp_path / "c.pt"
    said = r"not finite at step 10 \(.*\), from a step in 1\.\.10 on; lower lr"
    with pytest.raises(FloatingPointError, match=said):
        train_ensemble(small_ensemble(), train, val, config, checkpoint_path=ckpt, progress=False)
    assert not ckpt.exists()


def test_one_training_episode_with_the_novelty_check_is_refused_before_training(
    linear_data, small_ensemble
):
    """A trial trained on one episode: the whole run finished, then the novelty check failed
    with "group_scales: expected one positive scale per group (2), got (nan, nan)", naming
    neither the data nor the way out."""
    from rcvae_torchrl.data import TRAJ_KEY
    from rcvae_torchrl.training import StateNovelty

    train, val = linear_data
    one = train[train[TRAJ_KEY] == train[TRAJ_KEY][0]]
    refused = (
        r"^train_data: the novelty check measures each training episode's first state against "
        r"the other episodes' states: expected at least 2 training episodes, got 1; collect "
        r"more, or train with novelty=False"
    )
    ensemble = small_ensemble()
    before = _weights(ensemble)
    with pytest.raises(ValueError, match=refused):
        train_ensemble(ensemble, one, val, CONFIG, progress=False)
    assert all(torch.equal(before[k], v) for k, v in ensemble.state_dict().items())  # untrained
    with pytest.raises(ValueError, match=refused):
        StateNovelty.from_episodes(one, val)
    result = train_ensemble(small_ensemble(), one, val, CONFIG, progress=False, novelty=False)
    assert result.novelty is None
