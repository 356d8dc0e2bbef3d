"""save_ensemble / load_ensemble: round trip and clear errors for bad files."""

import pytest
import torch

from rcvae_torchrl.io import CHECKSUM_KEY, atomic_write, load_torch, save_torch
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.rollout import imagine
from rcvae_torchrl.training import (
    FORMAT_VERSION,
    CheckpointError,
    TrainConfig,
    load_ensemble,
    save_ensemble,
    train_ensemble,
)


def _samples(ensemble):
    g = torch.Generator().manual_seed(5)
    return imagine(
        ensemble, torch.ones(2, 3), torch.zeros(2, 6, 1), samples_per_member=4, generator=g
    )["observation"]


def test_round_trip_keeps_weights_normaliser_and_config(tmp_path, small_ensemble):
    ensemble = small_ensemble()
    ensemble.fit_normalizer(torch.randn(50, 3) * 3 + 1, torch.rand(50, 1))
    path = save_ensemble(ensemble, tmp_path / "sub" / "model.pt", extra={"note": "x"})
    loaded = load_ensemble(path, expected_config=ensemble.config)
    assert loaded.config == ensemble.config and loaded.ensemble_size == 3
    torch.testing.assert_close(_samples(loaded), _samples(ensemble), rtol=0, atol=0)
    assert not list(tmp_path.glob("sub/.*.tmp")), "no temporary file left behind"


def test_a_float64_model_comes_back_in_float64(tmp_path, small_ensemble):
    """A trial's float64 model came back from load_ensemble as float32 (weights rounded by
    about 1.5e-8), which its own float64 env then refused."""
    ensemble = small_ensemble().double()
    ensemble.fit_normalizer(
        torch.randn(50, 3, dtype=torch.float64) * 3 + 1, torch.rand(50, 1, dtype=torch.float64)
    )
    loaded = load_ensemble(save_ensemble(ensemble, tmp_path / "double.pt"))
    assert loaded.dtype == torch.float64
    for (name, want), got in zip(ensemble.state_dict().items(), loaded.state_dict().values()):
        assert got.dtype == want.dtype and torch.equal(got, want), name
    assert load_ensemble(save_ensemble(small_ensemble(), tmp_path / "f.pt")).dtype == torch.float32


def test_missing_truncated_and_foreign_files(tmp_path, small_ensemble):
    with pytest.raises(CheckpointError, match=r"none\.pt.*the file is missing"):
        load_ensemble(tmp_path / "none.pt")
    path = save_ensemble(small_ensemble(), tmp_path / "m.pt")
    data = path.read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_ensemble(tmp_path / "cut.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint at all")
    with pytest.raises(
        CheckpointError, match=r"is not a torch file, or its start is damaged: it begins b'not a c"
    ):
        load_ensemble(tmp_path / "junk.pt")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="expected an rcvae_torchrl checkpoint"):
        load_ensemble(tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match=r"checkpoint '.*': is a directory, expected a file"):
        load_ensemble(tmp_path)
    with pytest.raises(ValueError, match=r"map_location: expected a device .*, got 'banana'"):
        load_ensemble(path, map_location="banana")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"map_location: 'cuda' asked for, but CUDA is not"):
            load_ensemble(path, map_location="cuda")


def _edit(path, tmp_path, change):
    """A checkpoint edited through the library's own file functions (its checksum remade)."""
    payload = load_torch(path)
    change(payload)
    return save_torch(tmp_path / "edited.pt", payload)


def test_a_changed_byte_of_the_weights_is_refused_not_loaded(tmp_path, small_ensemble):
    """A byte flipped on disk inside a tensor's data unpickles fine (the archive holds raw
    bytes): the checksum written with the content refuses it, naming the file."""
    ensemble = small_ensemble()
    ensemble.fit_normalizer(torch.randn(50, 3) * 3 + 1, torch.rand(50, 1))
    path = save_ensemble(ensemble, tmp_path / "m.pt")
    data = bytearray(path.read_bytes())
    std = ensemble.normalizer.state_std.numpy().tobytes()
    at = bytes(data).index(std)  # this tensor's bytes, stored as they are
    data[at + 2] ^= 0x40
    (tmp_path / "flipped.pt").write_bytes(bytes(data))
    raw = torch.load(tmp_path / "flipped.pt", weights_only=True)  # unpickles fine...
    changed = raw["state_dict"]["normalizer.state_std"]
    assert not torch.equal(changed, ensemble.normalizer.state_std)  # ...with another number
    with pytest.raises(CheckpointError, match=r"flipped\.pt' is corrupt: its content does not "):
        load_ensemble(tmp_path / "flipped.pt")
    # a file written before checksums (its payload without the entry) loads as it is
    raw = load_torch(path)
    assert CHECKSUM_KEY not in raw
    torch.save(raw, tmp_path / "unchecked.pt")
    loaded = load_ensemble(tmp_path / "unchecked.pt")
    torch.testing.assert_close(_samples(loaded), _samples(ensemble), rtol=0, atol=0)


def test_mismatched_version_config_and_weights(tmp_path, small_ensemble):
    path = save_ensemble(small_ensemble(), tmp_path / "m.pt")
    bumped = _edit(path, tmp_path, lambda p: p.update(format_version=FORMAT_VERSION + 1))
    with pytest.raises(CheckpointError, match="expected format version"):
        load_ensemble(bumped)
    other = RCVAEConfig(3, 1, hidden_dim=32)
    with pytest.raises(CheckpointError, match=r"config mismatch \(hidden_dim: expected 32, got "):
        load_ensemble(path, expected_config=other)
    wrong = _edit(path, tmp_path, lambda p: p["config"].update(hidden_dim=32))
    with pytest.raises(CheckpointError, match="weights do not match"):
        load_ensemble(wrong)
    bad_cfg = _edit(path, tmp_path, lambda p: p["config"].update(hidden_dim=-1))
    with pytest.raises(CheckpointError, match="invalid config"):
        load_ensemble(bad_cfg)


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path):
    target = tmp_path / "f.bin"
    atomic_write(target, lambda f: f.write(b"old"))

    def broken(f):
        f.write(b"half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(target, broken)
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.bin"]


def test_incomplete_and_non_finite_payloads(tmp_path, small_ensemble):
    path = save_ensemble(small_ensemble(), tmp_path / "m.pt")
    for key in ("config", "ensemble_size", "state_dict"):
        cut = _edit(path, tmp_path, lambda p, key=key: p.pop(key))
        with pytest.raises(CheckpointError, match=f"no '{key}' entry"):
            load_ensemble(cut)
    size = _edit(path, tmp_path, lambda p: p.update(ensemble_size="two"))
    with pytest.raises(CheckpointError, match="ensemble_size: expected a positive int, got 'two'"):
        load_ensemble(size)
    nan = _edit(path, tmp_path, lambda p: p["state_dict"]["normalizer.state_mean"].fill_(torch.nan))
    with pytest.raises(CheckpointError, match=r"'normalizer\.state_mean' holds NaN or infinite"):
        load_ensemble(nan)
    checks = _edit(path, tmp_path, lambda p: p.update(checks={"names": ["a"]}))
    with pytest.raises(
        CheckpointError,
        match="its self-check results are corrupt: ValueError: values: expected the entries ",
    ):
        load_ensemble(checks)


def test_metadata_that_would_not_load_back_is_refused(tmp_path, small_ensemble):
    """``load_ensemble`` reads with ``weights_only=True``: a Path in ``extra`` would make a
    sound file read as corrupt, so it is refused before anything is written."""
    from pathlib import Path

    with pytest.raises(TypeError, match=r"extra: expected tensors, numbers, strings.*PosixPath"):
        save_ensemble(small_ensemble(), tmp_path / "m.pt", extra={"data": Path("/data/x")})
    assert not (tmp_path / "m.pt").exists()
    with pytest.raises(TypeError, match="extra: expected a dict of metadata or None, got list"):
        save_ensemble(small_ensemble(), tmp_path / "m.pt", extra=[1])
    with pytest.raises(TypeError, match="ensemble: expected an RCVAEEnsemble, got Linear"):
        save_ensemble(torch.nn.Linear(2, 2), tmp_path / "m.pt")
    path = save_ensemble(small_ensemble(), tmp_path / "m.pt", extra={"data": "/data/x", "n": 3})
    assert torch.load(path, weights_only=True)["extra"] == {"data": "/data/x", "n": 3}


@pytest.mark.parametrize("path", [5, None])
def test_a_path_that_is_not_one_is_named(path):
    with pytest.raises(TypeError, match="path: expected a str or a path of checkpoint, got"):
        load_ensemble(path)


def test_a_training_checkpoint_is_not_loaded_as_a_model(tmp_path, linear_data, small_ensemble):
    """train_ensemble's checkpoint holds the last validation's weights (not the best ones
    training returns) and no self-checks: loading it as the model is refused, saying what to
    load instead."""
    train, val = linear_data
    budget = TrainConfig(max_steps=4, batch_windows=4, window=8, val_every=2, val_windows=4)
    resume_file = tmp_path / "model_train.pt"
    result = train_ensemble(
        small_ensemble(2),
        train,
        val,
        budget,
        progress=False,
        checks=False,
        checkpoint_path=resume_file,
    )
    model_file = save_ensemble(result.ensemble, tmp_path / "model.pt")
    with pytest.raises(CheckpointError) as refused:
        load_ensemble(resume_file)
    assert str(refused.value).startswith(
        f"checkpoint {str(resume_file)!r}: expected a model saved by save_ensemble, got a "
        "training checkpoint (train_ensemble's checkpoint_path"
    )
    assert "train_ensemble(..., checkpoint_path=it, resume=True)" in str(refused.value)
    assert load_ensemble(model_file).ensemble_size == 2


def test_a_path_that_is_no_file_path_is_named(tmp_path, small_ensemble):
    with pytest.raises(
        TypeError, match=r"^path: expected a file path \(a str or a Path\), got NoneType"
    ):
        save_ensemble(small_ensemble(), None)
    (tmp_path / "afile").write_text("mine")
    with pytest.raises(NotADirectoryError) as refused:
        save_ensemble(small_ensemble(), tmp_path / "afile" / "sub" / "m.pt")
    assert str(refused.value) == (
        f"path: expected a file path whose folders are folders, got "
        f"{str(tmp_path / 'afile' / 'sub' / 'm.pt')!r}, where {str(tmp_path / 'afile')!r} is a file"
    )
    assert (tmp_path / "afile").read_text() == "mine"


def test_a_model_that_would_not_load_back_is_not_saved(tmp_path):
    model = RCVAEEnsemble(RCVAEConfig(3, 2, hidden_dim=8, mlp_dim=8, latent_dim=2), 2, seed=0)
    with torch.no_grad():
        model.embed.weight.fill_(float("nan"))
    with pytest.raises(ValueError, match=r"ensemble: 'embed\.weight' holds NaN or infinite"):
        save_ensemble(model, tmp_path / "m.pt")
    assert not (tmp_path / "m.pt").exists()
    good = RCVAEEnsemble(RCVAEConfig(3, 2, hidden_dim=8, mlp_dim=8, latent_dim=2), 2, seed=0)
    save_ensemble(good, tmp_path / "g.pt")
    with pytest.raises(TypeError, match="expected_config: expected an RCVAEConfig or None, got"):
        load_ensemble(tmp_path / "g.pt", expected_config={"obs_dim": 3})
