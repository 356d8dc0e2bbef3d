"""The ahead-of-time compiled scoring rollout: equal to the eager reference, one build per key,
loaded from the cache without a build, retrained weights on the same package, corrupt packages
rebuilt with a warning.

The model, task and horizon are those of the model-env tests' compiled-scoring check (their
tiny Pusher-sized ensemble, the Pusher's reward and success, H = 2), so the session's cache
holds one build for both.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from filelock import FileLock

from rcvae_torchrl import processes
from rcvae_torchrl.envs import pusher_reward, pusher_success
from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
from rcvae_torchrl.rollout import (
    ActionBounds,
    AOTCacheWarning,
    AOTLoadError,
    Task,
    aot,
    default_cache_dir,
    evaluate_action_sequences,
    scoring_key,
)
from rcvae_torchrl.rollout.scoring import _score

ROOT = Path(__file__).resolve().parents[2]
E, H = 3, 2
CONFIG = RCVAEConfig(14, 2, hidden_dim=16, latent_dim=4, mlp_dim=16, passthrough_dims=(12, 13))
TASK = Task(pusher_reward, pusher_success)


def _model(seed: int = 0, config: RCVAEConfig = CONFIG, members: int = E) -> RCVAEEnsemble:
    """Untrained, with steps of about 0.01 (so the ball moves about as far as success needs)."""
    torch.manual_seed(seed)
    model = RCVAEEnsemble(config, ensemble_size=members).eval()
    obs, actions = torch.randn(200, config.obs_dim) * 0.1, torch.rand(200, 2) * 2 - 1
    model.fit_normalizer(obs, actions, next_observations=obs + 0.01 * torch.randn_like(obs))
    return model


def _plans(candidates: int, horizon: int = H) -> tuple[torch.Tensor, torch.Tensor]:
    """Start states with the ball 0 to 0.06 from the target (success: 0.03) and actions, some
    out of bounds."""
    g = torch.Generator().manual_seed(candidates)
    start = torch.randn(candidates, 14, generator=g) * 0.05
    start[:, 8] = start[:, 12] + torch.linspace(0.0, 0.06, candidates)
    start[:, 9] = start[:, 13]
    return start, torch.rand(candidates, horizon, 2, generator=g) * 3 - 1.5


def _scores(model, candidates, particles, compile, bounds=None, **kwargs):
    start, actions = _plans(candidates, kwargs.pop("horizon", H))
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        out = evaluate_action_sequences(
            model, start, actions, particles, task=kwargs.pop("task", TASK), bounds=bounds,
            generator=g, compile=compile, **kwargs,
        )  # fmt: skip
    return out, g.get_state()


def _assert_same(got, want) -> None:
    torch.testing.assert_close(got[0].returns, want[0].returns, rtol=1e-4, atol=1e-5)
    assert torch.equal(got[0].success, want[0].success)
    assert torch.equal(got[1], want[1]), "the generator advanced by other draws"


@pytest.fixture
def no_build(monkeypatch):
    """Fail on any build; the loaded packages of this process forgotten (as in a new one)."""

    def build(*args):
        raise AssertionError("built a package")

    monkeypatch.setattr(aot, "_build", build)
    monkeypatch.setattr(aot, "_LOADED", {})


@pytest.mark.parametrize(("candidates", "particles"), [(4, 2 * E), (7, 2 * E), (5, 1), (1, 1)])
@pytest.mark.parametrize("bounded", [False, True])
def test_aot_scoring_equals_the_eager_reference(candidates, particles, bounded):
    """One package for every number of candidates and particles (one particle per member up
    to many), with and without action bounds; the same noise draws as the eager rollout."""
    model = _model()
    bounds = ActionBounds(-torch.ones(2), torch.ones(2)) if bounded else None
    want = _scores(model, candidates, particles, False, bounds)
    got = _scores(model, candidates, particles, "aot", bounds)
    _assert_same(got, want)
    if candidates == 4:
        assert want[0].success.any() and not want[0].success.all()


def test_a_later_process_loads_the_package_without_building(no_build):
    model = _model()
    start = time.perf_counter()
    scoring = aot.aot_scoring(_score, model, TASK, H)
    assert time.perf_counter() - start < 5.0
    assert not scoring.built_here and scoring.build_s > 0
    _assert_same(_scores(model, 6, 2 * E, "aot"), _scores(model, 6, 2 * E, False))


def test_retrained_weights_use_the_same_package(no_build):
    """The weights are inputs of the graph: another model of the architecture, and weights
    changed in place (a training step), are scored by the cached package, correctly."""
    model = _model(seed=5)
    _assert_same(_scores(model, 6, 2 * E, "aot"), _scores(model, 6, 2 * E, False))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.3 * torch.randn_like(p))
        model.normalizer.state_std.mul_(2.0)
    _assert_same(_scores(model, 6, 2 * E, "aot"), _scores(model, 6, 2 * E, False))


class _Built(Exception):
    """A build was started (the spy stops it: the test is about the key, not the package)."""


@pytest.mark.parametrize(
    "change",
    ["horizon", "reward", "success", "terminate", "config", "members", "dtype", "threshold"],
)
def test_a_changed_key_builds_a_new_package(monkeypatch, change):
    model, task, horizon = _model(), TASK, H
    if change == "horizon":
        horizon = 3
    elif change in ("reward", "success", "terminate"):
        swap = {"reward": {"reward_fn": lambda observation, action: -observation[..., :1]},
                "success": {"success_fn": lambda observation: observation[..., 8] > 0.0},
                "terminate": {"terminate_on_success": True}}[change]  # fmt: skip
        task = dataclasses.replace(TASK, **swap)
    elif change == "config":
        model = _model(config=dataclasses.replace(CONFIG, hidden_dim=12))
    elif change == "members":
        model = _model(members=2)
    elif change == "dtype":
        model = _model().double()
    else:  # the same code reading another value from its closure
        task = Task(pusher_reward, _above(0.0))
        other = Task(pusher_reward, _above(0.1))
        assert aot._key(_score, model, task, H)[1] != aot._key(_score, model, other, H)[1]

    def build(*args):
        raise _Built

    monkeypatch.setattr(aot, "_build", build)
    with pytest.raises(_Built):
        aot.aot_scoring(_score, model, task, horizon)


def test_a_build_works_in_a_directory_of_its_own(monkeypatch, tmp_path):
    """Inductor's cache directory is shared by the user's processes, its files named by a hash
    of the code: two processes building one graph at once rewrote each other's files, and one
    packaged an empty metadata file that no process could load. A build writes into a
    directory of its own, removed afterwards; the process's cache directory is restored."""
    from torch._inductor.runtime.cache_dir_utils import cache_dir

    shared = tmp_path / "inductor"
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(shared))
    seen = []

    def package(exported, package_path):
        seen.append(Path(cache_dir()))
        raise _Built

    monkeypatch.setattr(torch._inductor, "aoti_compile_and_package", package)
    with pytest.raises(_Built):
        aot.aot_scoring(_score, _model(), TASK, H, cache_dir=tmp_path / "packages")
    assert len(seen) == 1 and not seen[0].is_relative_to(shared)
    assert not seen[0].exists()
    assert os.environ["TORCHINDUCTOR_CACHE_DIR"] == str(shared)


def _above(x: float):
    return lambda observation: observation[..., 8] > x


def test_the_key_ignores_weights_and_names():
    a, b = _model(seed=0), _model(seed=1)
    named = RCVAEEnsemble(dataclasses.replace(CONFIG, observation_names=tuple("abcdefghijklmn")), E)
    assert scoring_key(_score, a, TASK, H) == scoring_key(_score, b, TASK, H)
    assert scoring_key(_score, a, TASK, H) == scoring_key(_score, named, TASK, H)


def _cached_copy(tmp_path, aot_cache_dir):
    """A copy of the session's cache (building its package first if no test has yet), and
    the package's path in it."""
    aot.aot_scoring(_score, _model(), TASK, H)
    directory = tmp_path / "cache"
    shutil.copytree(aot_cache_dir, directory)
    name = aot._key(_score, _model(), TASK, H)[1]
    return directory, directory / f"{name}.pt2"


@pytest.mark.parametrize("damage", ["flipped bytes", "truncated", "no record", "bad record"])
def test_a_corrupt_package_is_rebuilt_with_a_warning(tmp_path, aot_cache_dir, monkeypatch, damage):
    """Flipped bytes load without an error (the zip's checksums are not read): the recorded
    SHA-256 catches them. The spy rebuild returns the good package's bytes (the build itself
    is tested above)."""
    directory, package = _cached_copy(tmp_path, aot_cache_dir)
    good, record = package.read_bytes(), package.with_suffix(".json")
    if damage == "flipped bytes":
        package.write_bytes(good[:1000] + bytes(100) + good[1100:])
    elif damage == "truncated":
        package.write_bytes(good[: len(good) // 2])
    elif damage == "no record":
        record.unlink()
    else:
        record.write_text("{")
    builds = []
    monkeypatch.setattr(aot, "_build", lambda *args: builds.append(args) or good)
    monkeypatch.setattr(aot, "_LOADED", {})
    model = _model()
    with pytest.warns(AOTCacheWarning, match="building it again"):
        got = _scores(model, 5, 2 * E, "aot", cache_dir=directory)
    assert len(builds) == 1
    assert package.read_bytes() == good
    assert json.loads(record.read_text())["bytes"] == len(good)
    _assert_same(got, _scores(model, 5, 2 * E, False))


def test_a_package_stored_while_waiting_for_the_lock_is_loaded_not_built(
    tmp_path, aot_cache_dir, monkeypatch
):
    """Processes sharing a cache build a package one at a time: one that waited while another
    built it loads what that one stored (before the lock, both built and each overwrote the
    other's package)."""
    directory, package = _cached_copy(tmp_path, aot_cache_dir)
    record = package.with_suffix(".json")
    stored = {path: path.read_bytes() for path in (package, record)}
    for path in stored:
        path.unlink()

    class Waited(FileLock):  # the other process stores its build while this one waits
        def acquire(self, *args, **kwargs):
            for path, data in stored.items():
                path.write_bytes(data)
            return super().acquire(*args, **kwargs)

    def build(*args):
        raise AssertionError("built a package")

    monkeypatch.setattr(aot, "FileLock", Waited, raising=False)
    monkeypatch.setattr(aot, "_build", build)
    monkeypatch.setattr(aot, "_LOADED", {})
    model = _model()
    assert not aot.aot_scoring(_score, model, TASK, H, cache_dir=directory).built_here
    _assert_same(
        _scores(model, 5, 2 * E, "aot", cache_dir=directory), _scores(model, 5, 2 * E, False)
    )


def _unchecked(record: Path) -> None:
    """The record as before a new process loaded its package."""
    meta = json.loads(record.read_text())
    del meta["loads"]
    record.write_text(json.dumps(meta))


def test_a_package_is_first_loaded_in_a_new_process_once(tmp_path, aot_cache_dir, monkeypatch):
    """A real child process loads it; the record keeps the verdict, so later processes load
    it without one."""
    directory, package = _cached_copy(tmp_path, aot_cache_dir)
    record = package.with_suffix(".json")
    assert json.loads(record.read_text())["loads"] is True, "the session's build was checked"
    _unchecked(record)
    children, real = [], aot._load_in_a_child
    monkeypatch.setattr(aot, "_load_in_a_child", lambda path: children.append(path) or real(path))
    model, want = _model(), _scores(_model(), 5, 2 * E, False)
    for _ in range(2):  # the second time as in a new process
        monkeypatch.setattr(aot, "_LOADED", {})
        _assert_same(_scores(model, 5, 2 * E, "aot", cache_dir=directory), want)
        assert children == [package] and json.loads(record.read_text())["loads"] is True


@pytest.mark.parametrize("cached", [True, False])
def test_a_package_that_crashes_its_loader_is_an_error_not_a_crash(
    tmp_path, aot_cache_dir, monkeypatch, cached
):
    """Some torch builds crash loading a package (every AOT test on a GPU machine's torch
    2.11 ended its process): the crash ends a child, this process gets an error, and a later
    process reads the verdict from the record without crashing a child again."""
    directory, package = _cached_copy(tmp_path, aot_cache_dir)
    record, good = package.with_suffix(".json"), package.read_bytes()
    if cached:
        _unchecked(record)
    else:  # built in this call
        package.unlink()
        record.unlink()
        monkeypatch.setattr(aot, "_build", lambda *args: good)
    monkeypatch.setattr(aot, "_LOAD_CHECK", "import os\nos.abort()")
    monkeypatch.setattr(aot, "_LOADED", {})
    crash = (
        r"loading it in a new process failed: its process was ended by SIGABRT; torch .* "
        r"compile=True \(torch.compile\)"
    )
    with pytest.raises(AOTLoadError, match=crash):
        _scores(_model(), 5, 2 * E, "aot", cache_dir=directory)
    assert json.loads(record.read_text())["loads"] is False

    def no_child(path):
        raise AssertionError("loaded it in a child again")

    monkeypatch.setattr(aot, "_load_in_a_child", no_child)
    monkeypatch.setattr(aot, "_LOADED", {})
    with pytest.raises(AOTLoadError, match=crash):
        _scores(_model(), 5, 2 * E, "aot", cache_dir=directory)


def test_without_a_new_process_the_package_is_loaded_here_unrecorded(
    tmp_path, aot_cache_dir, monkeypatch
):
    directory, package = _cached_copy(tmp_path, aot_cache_dir)
    record = package.with_suffix(".json")
    _unchecked(record)

    def no_process(*args, **kwargs):
        raise OSError("Resource temporarily unavailable")

    monkeypatch.setattr(processes.subprocess, "run", no_process)
    monkeypatch.setattr(aot, "_LOADED", {})
    model = _model()
    with pytest.warns(AOTCacheWarning, match="none could be started: Resource temporarily"):
        got = _scores(model, 5, 2 * E, "aot", cache_dir=directory)
    _assert_same(got, _scores(model, 5, 2 * E, False))
    assert "loads" not in json.loads(record.read_text())


def test_a_cached_package_a_new_process_cannot_load_is_rebuilt(
    tmp_path, aot_cache_dir, monkeypatch
):
    """An error (not a crash) loading a cached package: rebuilt with a warning; the rebuilt
    one failing too is an error."""
    directory, package = _cached_copy(tmp_path, aot_cache_dir)
    _unchecked(package.with_suffix(".json"))
    builds, good = [], package.read_bytes()
    monkeypatch.setattr(aot, "_build", lambda *args: builds.append(args) or good)
    monkeypatch.setattr(aot, "_LOAD_CHECK", "raise SystemExit('no runner for this package')")
    monkeypatch.setattr(aot, "_LOADED", {})
    with (
        pytest.warns(AOTCacheWarning, match="building it again: .*no runner for this package"),
        pytest.raises(AOTLoadError, match="in a new process failed: no runner for this package"),
    ):
        _scores(_model(), 5, 2 * E, "aot", cache_dir=directory)
    assert len(builds) == 1


def test_the_cache_directory(monkeypatch, tmp_path):
    monkeypatch.setenv("RCVAE_TORCHRL_CACHE", str(tmp_path / "mine"))
    assert default_cache_dir() == tmp_path / "mine"
    monkeypatch.delenv("RCVAE_TORCHRL_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "rcvae_torchrl" / "aot_scoring"


def test_inputs_the_package_was_not_compiled_for_are_an_error():
    """Its kernels would read another shape or dtype as garbage: checked before the call."""
    model = _model()
    scoring = aot.aot_scoring(_score, model, TASK, H)
    hidden, m = model.initial_hidden((2,), torch.zeros(())), 2
    noise = (torch.zeros(H, E, m, 4), torch.zeros(H, E, m, 12))
    obs, per_step = torch.zeros(E * m, 14), torch.zeros(H, E * m, 2)
    returns, success = scoring(model, hidden, obs, per_step, None, noise)
    assert returns.shape == success.shape == (E * m,)
    with pytest.raises(ValueError, match=r"s_0: expected shape \(6, 14\), torch.float32"):
        scoring(model, hidden, obs.double(), per_step, None, noise)
    with pytest.raises(ValueError, match=r"actions: expected shape \(2, 6, 2\)"):
        scoring(model, hidden, obs, torch.zeros(H + 1, E * m, 2), None, noise)
    with pytest.raises(ValueError, match="ε_s: expected shape"):
        scoring(model, hidden, obs, per_step, None, (noise[0], noise[0]))


@pytest.mark.parametrize("value", ["yes", 1, None, "AOT"])
def test_compile_must_be_false_true_or_aot(value):
    with pytest.raises(ValueError, match=r"compile: expected False .* or 'aot'"):
        _scores(_model(), 2, 1, value)


@pytest.mark.slow  # a new interpreter: imports torch and the library (seconds)
def test_a_new_process_reuses_the_package(aot_cache_dir):
    """The key is the same in another interpreter (no addresses, no hash-seed order)."""
    aot.aot_scoring(_score, _model(), TASK, H)
    code = (
        "import sys, time; sys.path[:0] = ['tests/rollout', '.']\n"
        "import test_aot as t; from rcvae_torchrl.rollout import aot\n"
        "aot._build = None; start = time.perf_counter()\n"
        "s = aot.aot_scoring(t._score, t._model(), t.TASK, t.H)\n"
        "print(s.built_here, time.perf_counter() - start)"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT,
        env={**os.environ, "PYTHONHASHSEED": "7"},
    )  # fmt: skip
    built, seconds = out.stdout.split()
    assert built == "False" and float(seconds) < 2.0, out.stdout


@pytest.mark.slow  # builds the study-sized package (about a minute on a CPU)
def test_the_study_model_at_the_planner_budget_equals_eager(tmp_path):
    """The study's ensemble (E = 5, the Pusher's state constraint and input features), the
    planner's budget (64 candidates x 5 particles x 12 steps), success ending episodes."""
    from recipes.pusher_competency.config import StudyConfig
    from recipes.pusher_competency.pusher import MODEL_FUNCTIONS, rcvae_config

    torch.manual_seed(0)
    model = RCVAEEnsemble(rcvae_config(StudyConfig().model), 5, functions=MODEL_FUNCTIONS).eval()
    obs, actions = torch.randn(500, 14) * 0.1, torch.rand(500, 2) * 2 - 1
    model.fit_normalizer(obs, actions, next_observations=obs + 0.01 * torch.randn_like(obs))
    task = Task(pusher_reward, pusher_success, terminate_on_success=True)
    bounds = ActionBounds(-torch.ones(2), torch.ones(2))
    for candidates, particles in ((64, 5), (13, 1)):
        kwargs = {"task": task, "horizon": 12, "cache_dir": tmp_path}
        want = _scores(model, candidates, particles, False, bounds, **kwargs)
        got = _scores(model, candidates, particles, "aot", bounds, **kwargs)
        _assert_same(got, want)


def test_aot_scoring_with_an_episode_latent_equals_the_eager_reference():
    """The episode latent rides in the carried state, an input of the package: drawn before
    the steps' noise, as the eager rollout draws it."""
    model = _model(config=dataclasses.replace(CONFIG, episode_latent_dim=2))
    with torch.no_grad():
        model.episode_prior_raw.normal_()
    want = _scores(model, 4, 2 * E, False)
    _assert_same(_scores(model, 4, 2 * E, "aot"), want)
