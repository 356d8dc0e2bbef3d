"""The scoring rollout compiled ahead of time: one package per graph, cached across processes.

``torch.export`` traces the scoring rollout (all H steps of the ensemble, the state constraint,
the input features, reward and success) with the number of particles per member as a symbolic
size, and AOTInductor compiles the graph into a ``.pt2`` package: fused C++ kernels in a shared
library. The package is stored in a cache directory and loaded by later processes in a fraction
of a second instead of being compiled again (tens of seconds on a CPU).

What the package serves, and what it does not:

- every number of candidates and particles (the particle count per member is dynamic);
- every set of weights of the same architecture: the ensemble's parameters and buffers are
  inputs of the graph, read at each call, so a retrained or updated model uses the same
  package (no gradients flow through it);
- a new architecture, ensemble size, horizon, dtype, device, task function, model function
  (state constraint, input features), library source (``rcvae_torchrl/models`` and
  ``rcvae_torchrl/rollout``), torch version or CPU instruction set is another graph: its key
  (:func:`scoring_key`) differs and a new package is built. Functions are keyed by their code,
  their module's source and the values they read (:mod:`rcvae_torchrl.fingerprint`).

Cache layout: ``<cache_dir>/<key digest>.pt2`` (written atomically) and ``<key digest>.json``
(the key itself, the package's SHA-256, how long the build took and whether a new process
loaded it). A package whose bytes do not match the recorded digest, or which fails to load, is
reported with an :class:`AOTCacheWarning` and built again. The directory is ``cache_dir`` when
given, else the environment variable ``RCVAE_TORCHRL_CACHE``, else
``$XDG_CACHE_HOME/rcvae_torchrl/aot_scoring`` (``~/.cache/...``). Deleting it is always safe.
One process builds a package at a time (a lock file, ``<key digest>.lock``): the others wait
and load what it stored. Inductor builds each package in a temporary directory of its own, not
in its cache shared by the user's processes, so builds of the same graph for two cache
directories cannot package each other's half-written files.

A package is first loaded in a child process, once per package: some torch builds crash
(a segmentation fault or an abort, which no ``except`` catches) rather than raise when loading
one, and the crash then ends only the child. Such a torch gets an :class:`AOTLoadError`, in
every later process too (the record keeps the verdict), and ``compile=True`` or eager scoring
still serve.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import io
import logging
import os
import platform
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from filelock import FileLock
from torch import nn

from rcvae_torchrl.fingerprint import describe, digest, source_digest
from rcvae_torchrl.io import StoredFileError, atomic_write, read_json, write_json
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.processes import try_in_a_child
from rcvae_torchrl.rollout.loop import ActionBounds
from rcvae_torchrl.rollout.task import Task

__all__ = [
    "AOTCacheWarning",
    "AOTLoadError",
    "AOTScoring",
    "SCORING_CACHE_ENV",
    "aot_scoring",
    "default_cache_dir",
    "scoring_key",
]

log = logging.getLogger(__name__)

#: The environment variable naming the package cache directory.
SCORING_CACHE_ENV = "RCVAE_TORCHRL_CACHE"

#: ``fn(ensemble, mode, task, hidden, obs, per_step, bounds, generator, noise)`` ->
#: ``(returns [n], success [n])``: the eager scoring rollout that is compiled.
ScoringFn = Callable[..., tuple[torch.Tensor, torch.Tensor]]

_FORMAT = 1  # the layout of the package's inputs; bump it when it changes


class AOTCacheWarning(UserWarning):
    """A cached package could not be used (corrupt, truncated, unloadable) and is rebuilt."""


class AOTLoadError(RuntimeError):
    """This torch cannot load the package here: loading it crashed a new process, or a
    package just built would not load."""


def default_cache_dir() -> Path:
    """``$RCVAE_TORCHRL_CACHE``, else ``$XDG_CACHE_HOME/rcvae_torchrl/aot_scoring`` (XDG's
    default: ``~/.cache``)."""
    if os.environ.get(SCORING_CACHE_ENV):
        return Path(os.environ[SCORING_CACHE_ENV]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "rcvae_torchrl" / "aot_scoring"


@functools.cache
def _library_source() -> str:
    """Digest of the library code the graph is traced from (models and rollout)."""
    root = Path(__file__).resolve().parents[1]
    files = sorted([*(root / "models").glob("*.py"), *(root / "rollout").glob("*.py")])
    return source_digest(files)


@functools.cache
def _cpu() -> dict[str, str]:
    """The CPU the kernels are compiled for: ATen's capability and, on Linux, a digest of the
    instruction-set flags (a cache shared by machines of different CPUs keeps one package
    for each)."""
    flags = ""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line for line in f if line.startswith("flags")), "")
    except OSError:
        pass
    return {
        "machine": platform.machine(),
        "capability": torch.backends.cpu.get_cpu_capability(),
        "flags": hashlib.sha256(" ".join(sorted(flags.split())).encode()).hexdigest(),
    }


def _weights(ensemble: RCVAEEnsemble) -> dict[str, torch.Tensor]:
    """Parameters and buffers by name, sorted: the package's first inputs."""
    state = dict(ensemble.named_parameters()) | dict(ensemble.named_buffers())
    return {name: state[name] for name in sorted(state)}


def scoring_key(fn: ScoringFn, ensemble: RCVAEEnsemble, task: Task, horizon: int) -> dict[str, Any]:
    """Everything the compiled graph depends on (a JSON-able description; its digest names the
    package). The weights' values are not in it: they are inputs of the graph."""
    config = dataclasses.asdict(ensemble.config)
    for key in ("observation_names", "control_step"):  # records only: no part of the graph
        config.pop(key)
    state = _weights(ensemble)
    return {
        "format": _FORMAT,
        "function": describe(fn),
        "library_source": _library_source(),
        "model": {
            "class": describe(type(ensemble)),
            "config": config,
            "ensemble_size": ensemble.ensemble_size,
            "functions": describe(ensemble.functions),
            "weights": [[n, list(x.shape), str(x.dtype)] for n, x in state.items()],
        },
        "task": describe({f.name: getattr(task, f.name) for f in dataclasses.fields(task)}),
        "horizon": horizon,
        "trajectory_sampling": "ts_inf",
        "dtype": str(ensemble.dtype),
        "device": str(ensemble.device),
        "torch": torch.__version__,
        "cpu": _cpu(),
    }


class _Rollout(nn.Module):
    """``fn`` over the ensemble (a registered submodule, so its weights can be swapped)."""

    def __init__(self, fn: ScoringFn, ensemble: RCVAEEnsemble, task: Task) -> None:
        super().__init__()
        self.fn, self.ensemble, self.task = fn, ensemble, task

    def forward(self, hidden, obs, per_step, noise_z, noise_s, low, high):
        bounds = ActionBounds(low, high)
        args = (self.ensemble, "ts_inf", self.task, hidden, obs, per_step, bounds)
        return self.fn(*args, None, (noise_z, noise_s))


class _Program(nn.Module):
    """The exported signature: ``(weights, h_0, s_0, a, ε_z, ε_s, low, high)``, the weights a
    tuple in :func:`_weights` order, so that they are graph inputs, not baked-in constants."""

    def __init__(self, rollout: _Rollout, names: list[str]) -> None:
        super().__init__()
        self.held = (rollout,)  # a tuple: not registered, so its weights are not lifted
        self.names = ["ensemble." + n for n in names]

    def forward(self, weights, hidden, obs, per_step, noise_z, noise_s, low, high):
        inputs = (hidden, obs, per_step, noise_z, noise_s, low, high)
        return torch.func.functional_call(self.held[0], dict(zip(self.names, weights)), inputs)


def _inputs(ensemble, hidden, obs, per_step, bounds, noise) -> tuple:
    """The package's inputs, contiguous (the compiled kernels assume the exported strides)."""
    a = ensemble.config.action_dim
    if bounds is None:
        inf = obs.new_full((a,), torch.inf)
        bounds = ActionBounds(-inf, inf)  # clamping to ±inf leaves every action as it is
    low, high = (torch.as_tensor(b, dtype=obs.dtype, device=obs.device).expand(a) for b in bounds)
    tensors = (hidden, obs, per_step, *noise, low, high)
    return (tuple(_weights(ensemble).values()), *(t.contiguous() for t in tensors))


def _check_inputs(ensemble: RCVAEEnsemble, horizon: int, tensors: tuple) -> None:
    """The shapes, dtype and device the package was compiled for (its kernels do not check
    them: another shape or dtype would be read as garbage, not raise)."""
    cfg, e, m = ensemble.config, ensemble.ensemble_size, tensors[0].shape[-2]
    want = {
        "h_0": (e, m, ensemble.carry_dim),
        "s_0": (e * m, cfg.obs_dim),
        "actions": (horizon, e * m, cfg.action_dim),
        "ε_z": (horizon, e, m, cfg.latent_dim),
        "ε_s": (horizon, e, m, cfg.predicted_dim),
        "low": (cfg.action_dim,),
        "high": (cfg.action_dim,),
    }
    for (name, shape), x in zip(want.items(), tensors):
        if tuple(x.shape) != shape or x.dtype != ensemble.dtype or x.device != ensemble.device:
            raise ValueError(
                f"AOT scoring input {name}: expected shape {shape}, {ensemble.dtype} on "
                f"{ensemble.device} (the package's), got {tuple(x.shape)}, {x.dtype} on {x.device}"
            )


def _example(ensemble: RCVAEEnsemble, horizon: int) -> tuple:
    """Inputs with 2 particles per member (sizes 0 and 1 would be specialised by export)."""
    cfg, e, m = ensemble.config, ensemble.ensemble_size, 2
    like = torch.zeros((), dtype=ensemble.dtype, device=ensemble.device)
    hidden = ensemble.initial_hidden((m,), like)
    obs = like.new_zeros(e * m, cfg.obs_dim)
    per_step = like.new_zeros(horizon, e * m, cfg.action_dim)
    noise = (
        like.new_zeros(horizon, e, m, cfg.latent_dim),
        like.new_zeros(horizon, e, m, cfg.predicted_dim),
    )
    return _inputs(ensemble, hidden, obs, per_step, None, noise)


def _build(fn: ScoringFn, ensemble: RCVAEEnsemble, task: Task, horizon: int) -> bytes:
    """Export the rollout with a dynamic particle count and compile it: the package's bytes."""
    names = list(_weights(ensemble))
    program = _Program(_Rollout(fn, ensemble, task), names)
    m = torch.export.Dim("particles_per_member", min=1)
    n = ensemble.ensemble_size * m
    shapes = ((None,) * len(names), {1: m}, {0: n}, {1: n}, {2: m}, {2: m}, None, None)
    with torch.no_grad(), warnings.catch_warnings(), _own_build_dir():
        # torch's own, raised inside the build by modules it imports: nothing a caller can do
        warnings.filterwarnings("ignore", ".*LeafSpec", FutureWarning)
        warnings.filterwarnings("ignore", ".*torch.jit.script_method", DeprecationWarning)
        exported = torch.export.export(program, _example(ensemble, horizon), dynamic_shapes=shapes)
        buffer = io.BytesIO()
        torch._inductor.aoti_compile_and_package(exported, package_path=buffer)
    return buffer.getvalue()


@contextlib.contextmanager
def _own_build_dir():
    """Inductor's working directory for one build, of its own, removed afterwards.

    Inductor writes a build's generated sources, metadata and libraries into its cache
    directory, which every process of the user shares, under names that hash the code. Two
    processes building the same graph at once (ranks, test workers, two studies) write the same
    files, and one can package a file while the other rewrites it: a package holding an empty
    metadata file, which no process can load. A build in a directory of its own packages only
    what it wrote."""
    try:
        from torch._inductor.runtime.cache_dir_utils import temporary_cache_dir
    except ImportError:  # an older torch: its cache is the environment variable alone
        temporary_cache_dir = None
    with tempfile.TemporaryDirectory(prefix="rcvae_torchrl_aot_") as path:
        if temporary_cache_dir is not None:
            with temporary_cache_dir(path):
                yield path
            return
        previous = os.environ.get("TORCHINDUCTOR_CACHE_DIR")
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = path
        try:
            yield path
        finally:
            if previous is None:
                del os.environ["TORCHINDUCTOR_CACHE_DIR"]
            else:
                os.environ["TORCHINDUCTOR_CACHE_DIR"] = previous


def _open(package: Path) -> Any:
    """AOTInductor's runner of a package, from its C++ loader: torch's Python loader first
    probes the CPU's instruction sets by compiling and running test programs (about a second in
    each process), which the key's CPU fields already stand for."""
    loader = getattr(getattr(torch._C, "_aoti", None), "AOTIModelPackageLoader", None)
    if loader is None:  # another torch build: the public loader
        return torch._inductor.aoti_load_package(str(package))
    from torch.export.pt2_archive._package import AOTICompiledModel

    return AOTICompiledModel(loader(str(package), "model", False, 1, -1))


#: What the child process runs to load a package (its path is the argument).
_LOAD_CHECK = "import sys\nfrom rcvae_torchrl.rollout.aot import _open\n_open(sys.argv[1])"
_LOAD_CHECK_S = 600


def _load_in_a_child(package: Path) -> tuple[bool, str | None]:
    """``(crashed, problem)`` of loading ``package`` in a new interpreter: ``(False, None)``
    when it loads; ``crashed`` when a signal ended the child (or it hung); ``(False, "")``,
    with a warning, when no child could be started."""
    try:
        outcome = try_in_a_child(_LOAD_CHECK, str(package), timeout=_LOAD_CHECK_S)
    except OSError as err:  # nothing learnt about the package: loaded here, unrecorded
        warnings.warn(
            f"AOT scoring package {str(package)!r} not first loaded in a new process (none "
            f"could be started: {err}); loading it in this one",
            AOTCacheWarning,
            stacklevel=5,
        )
        return False, ""
    if outcome.problem is None:
        return False, None
    return outcome.crashed, f"loading it in a new process failed: {outcome.problem}"


def _load_error(package: Path, problem: str) -> AOTLoadError:
    return AOTLoadError(
        f"AOT scoring package {str(package)!r}: {problem}; torch {torch.__version__} cannot "
        f"run ahead-of-time compiled packages here: score with compile=True (torch.compile) "
        f"or compile=False (eager) instead"
    )


def _open_checked(package: Path, record: Path, meta: dict[str, Any], built: bool) -> Any:
    """:func:`_open`, once a new process has loaded the package (``"loads"`` in its record):
    a crash there is an :class:`AOTLoadError` (recorded, so later processes need not crash to
    learn it), as is any failure of a package just ``built``; another failure of a cached one
    is an error for :func:`_load` to rebuild it."""
    if meta.get("loads") is False:
        raise _load_error(package, meta.get("load_problem", "it would not load"))
    if meta.get("loads") is not True:
        crashed, problem = _load_in_a_child(package)
        if problem == "":  # not checked
            return _open(package)
        if problem is None:
            write_json(record, {**meta, "loads": True})
        elif crashed:
            write_json(record, {**meta, "loads": False, "load_problem": problem})
        if problem is not None and (crashed or built):
            raise _load_error(package, problem)
        if problem is not None:
            raise StoredFileError(f"AOT scoring package {str(package)!r}: {problem}", package)
    return _open(package)


class AOTScoring:
    """A loaded package: ``scoring(ensemble, hidden, obs, per_step, bounds, noise)`` ->
    ``(returns [n], success [n])``, the arguments as the eager rollout takes them (TS-∞
    layout, ``noise`` pre-drawn), the weights read from ``ensemble`` at each call.

    ``horizon``: H; ``path``: the package file; ``build_s``: seconds its build took (in
    whichever process built it); ``built_here``: whether this process built it.
    """

    def __init__(self, runner: Any, horizon: int, path: Path, build_s: float, built_here: bool):
        self.runner, self.horizon, self.path = runner, horizon, path
        self.build_s, self.built_here = build_s, built_here

    def __call__(self, ensemble, hidden, obs, per_step, bounds, noise):
        inputs = _inputs(ensemble, hidden, obs, per_step, bounds, noise)
        _check_inputs(ensemble, self.horizon, inputs[1:])
        return tuple(self.runner(*inputs))


def _load(package: Path, record: Path) -> tuple[Any, dict] | None:
    """The runner and the record of a cached package; None when there is none; a warning and
    None when the cached one cannot be used."""
    if not package.is_file() and not record.is_file():
        return None
    try:
        meta = read_json(record, "AOT scoring package record")
        if not package.is_file():
            raise StoredFileError(f"AOT scoring package {str(package)!r}: missing", package)
        data = package.read_bytes()
        if hashlib.sha256(data).hexdigest() != meta.get("sha256"):
            raise StoredFileError(
                f"AOT scoring package {str(package)!r} ({len(data)} bytes) does not match the "
                f"SHA-256 recorded in {str(record)!r}: corrupt or truncated",
                package,
            )
        return _open_checked(package, record, meta, built=False), meta
    except AOTLoadError:
        raise
    except Exception as err:  # a damaged archive raises several kinds of error
        warnings.warn(
            f"cached AOT scoring package cannot be used, building it again: {err}",
            AOTCacheWarning,
            stacklevel=4,
        )
        return None


_LOADED: dict[tuple[Path, str], AOTScoring] = {}
_KEYS: dict[tuple, tuple[dict[str, Any], str]] = {}


def _key(fn, ensemble, task, horizon) -> tuple[dict[str, Any], str]:
    """:func:`scoring_key` and its digest, remembered by the objects it is made of (describing
    functions reads their modules' sources; a call of the planner should not)."""
    shapes = tuple((n, tuple(x.shape), x.dtype) for n, x in _weights(ensemble).items())
    features = ensemble.functions.features(ensemble.config.input_features)
    memo = (fn, type(ensemble), ensemble.config, ensemble.ensemble_size,
            ensemble.state_constraint, features, task, horizon, ensemble.dtype,
            ensemble.device, shapes)  # fmt: skip
    try:
        hash(memo)
    except TypeError:  # an unhashable task or model function: described at every call
        key = scoring_key(fn, ensemble, task, horizon)
        return key, digest(key)
    if memo not in _KEYS:
        key = scoring_key(fn, ensemble, task, horizon)
        _KEYS[memo] = (key, digest(key))
    return _KEYS[memo]


def aot_scoring(
    fn: ScoringFn,
    ensemble: RCVAEEnsemble,
    task: Task,
    horizon: int,
    *,
    cache_dir: str | Path | None = None,
) -> AOTScoring:
    """The compiled scoring rollout ``fn`` for this model architecture, task and horizon: from
    this process's memory, else from the cache (``cache_dir``, see the module docstring), else
    built (tens of seconds on a CPU) and stored there.

    Args:
        fn: the eager rollout (:data:`ScoringFn`), e.g. the one
            :func:`~rcvae_torchrl.rollout.evaluate_action_sequences` runs.
        ensemble: the world model (its weights are read at each call, not here).
        task: reward, success and episode ends.
        horizon: H steps.
        cache_dir: where packages are kept (default :func:`default_cache_dir`).
    """
    directory = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    key, name = _key(fn, ensemble, task, horizon)
    if (directory, name) in _LOADED:
        return _LOADED[(directory, name)]
    package, record = directory / f"{name}.pt2", directory / f"{name}.json"
    start = time.perf_counter()
    seen = _stat(record)
    loaded = _load(package, record)
    if loaded is None:  # one build per package at a time, over every process using the cache
        directory.mkdir(parents=True, exist_ok=True)
        with FileLock(directory / f"{name}.lock"):
            if _stat(record) != seen:  # another process stored it while this one waited
                loaded = _load(package, record)
            if loaded is None:
                return _built(fn, ensemble, task, horizon, directory, name, key, start)
    runner, meta = loaded
    build_s = float(meta.get("build_s", float("nan")))
    scoring = AOTScoring(runner, horizon, package, build_s, False)
    log.info("loaded AOT scoring package %s in %.2f s", package, time.perf_counter() - start)
    _LOADED[(directory, name)] = scoring
    return scoring


def _stat(path: Path) -> tuple[int, int] | None:
    """A file's modification time and size (None when there is none): whether it changed."""
    try:
        info = path.stat()
    except FileNotFoundError:
        return None
    return info.st_mtime_ns, info.st_size


def _built(fn, ensemble, task, horizon, directory: Path, name: str, key, start: float):
    """:func:`aot_scoring`'s build: the package built, stored, loaded and remembered."""
    package, record = directory / f"{name}.pt2", directory / f"{name}.json"
    log.info("building AOT scoring package %s (horizon %d)", package, horizon)
    data = _build(fn, ensemble, task, horizon)
    build_s = time.perf_counter() - start
    atomic_write(package, lambda f: f.write(data))
    sha = hashlib.sha256(data).hexdigest()
    meta = {"sha256": sha, "bytes": len(data), "build_s": build_s, "key": key}
    write_json(record, meta)
    runner = _open_checked(package, record, meta, built=True)
    scoring = AOTScoring(runner, horizon, package, build_s, True)
    log.info("built AOT scoring package %s in %.1f s", package, build_s)
    _LOADED[(directory, name)] = scoring
    return scoring
