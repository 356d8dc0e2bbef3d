"""Fingerprints of code and values: what a cached, compiled artefact was built from.

A compiled graph bakes in the code it was traced from and the values that code read (a
threshold in a closure, a module constant). To reuse such an artefact in a later process, the
cache key must change whenever any of them does; :func:`describe` gives a JSON description of a
value that does, and :func:`digest` hashes one.

- a function: its qualified name, its code and its module's source, the values of its closure
  and defaults, and, recursively, the module-level names its code reads (constants, helper
  functions and classes; modules themselves and torch's own functions are left out: the torch
  version stands for those);
- a class: its name and its module's source;
- a ``functools.partial`` or a callable object: the function and its bound arguments or state
  (its ``__dict__`` and the values it keeps in ``__slots__``);
- a tensor: dtype, shape and a hash of its values; numbers, strings, None: themselves;
- a NumPy array: its ``repr``, or, where that does not show every value exactly (more
  elements than NumPy's print threshold, or floats its 8 digits round), its dtype, shape and a
  hash of its values, as a tensor's.

What a function reads in other ways (an attribute of an imported module, a file, a global
changed at run time without its source changing) is not seen: give it a new name or clear the
cache when that changes.

``digest(value, sources=False)`` leaves the modules' sources out (a class is then its name and
its methods' code): what identifies a forecast's task, which an unrelated edit of the script
that defines its predicates must not change.
"""

from __future__ import annotations

import contextvars
import functools
import hashlib
import inspect
import json
import math
import numbers
import os
import sys
import types
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = [
    "SETTINGS",
    "agent_digest",
    "describe",
    "digest",
    "model_digest",
    "source_digest",
    "task_difference",
    "task_digest",
    "task_labels",
    "task_parts",
    "weights_digest",
]

#: The prefix of an :func:`agent_digest` made from a weightless module's settings (not weights)
SETTINGS = "settings:"
#: Packages whose module classes are containers or wrappers, not an agent's own code: their
#: settings (keys, hooks) say how a policy is wrapped, not which it is
_WRAPPERS = ("torch", "tensordict", "torchrl", "rcvae_torchrl")


#: Whether :func:`describe` holds the source of the modules that functions and classes are
#: defined in (:func:`digest`'s ``sources``)
_WITH_SOURCES: contextvars.ContextVar[bool] = contextvars.ContextVar("sources", default=True)


def digest(value: Any, *, sources: bool = True) -> str:
    """The SHA-256 hex digest of ``value``'s :func:`describe` (canonical JSON).

    ``sources``: whether a function or class is described with the source of the module it
    is defined in (whatever else that module holds: the key of a cached, compiled artefact,
    which any edit of that source must renew). Without, a function is its code, closure,
    defaults and the module-level names it reads, and a class its name and its methods' code:
    what identifies a task's boundary or model, which an unrelated edit of the script that
    defines them does not change."""
    token = _WITH_SOURCES.set(sources)
    try:
        text = json.dumps(describe(value), sort_keys=True, default=str)
    finally:
        _WITH_SOURCES.reset(token)
    return hashlib.sha256(text.encode()).hexdigest()


def weights_digest(module: Any) -> str | None:
    """Which agent a policy is, by its weights: the SHA-256 digest of the values of a module's
    parameters and buffers (each tensor's dtype, shape and values, as a sorted list: neither
    their names nor what wraps them count), so the same weights give the same digest in a
    ``TensorDictModule``, a planner or a wrapper of one's own, and other weights another.
    ``None`` for a callable that is not a ``torch.nn.Module``, or one without weights (a
    policy written as code): its identity is not known."""
    if not isinstance(module, torch.nn.Module):
        return None
    tensors = [*module.parameters(), *module.buffers()]
    if not tensors:
        return None
    return digest(sorted(json.dumps(_tensor(t), sort_keys=True) for t in tensors))


def agent_digest(policy: Any) -> str | None:
    """Which agent a policy is: its :func:`weights_digest` where it has weights. A module
    without weights (a controller written as code in an ``nn.Module``) is known by its code
    and settings instead: for each module of a class of the user's own inside it (not
    torch's, tensordict's, TorchRL's or this library's wrappers), its class name, the code of
    its methods, and its attributes that hold numbers, strings, ``None``, tensors, numpy
    arrays, or lists and dicts of them (a gain ``kp``, a target; private ones too), prefixed
    with :data:`SETTINGS`. Two controllers of one class with other gains, or of one name with
    other code, differ; the same code and gains give the same digest in any process, whatever
    wraps them and wherever the class is defined. ``None`` for a callable that is not a module
    (a function) or a module with neither: its identity is not known."""
    weights = weights_digest(policy)
    if weights is not None or not isinstance(policy, torch.nn.Module):
        return weights
    own = [
        json.dumps([_code_of(type(m)), _settings(m)], sort_keys=True, default=str)
        for m in policy.modules()
        if type(m).__module__.split(".")[0] not in _WRAPPERS
    ]
    return SETTINGS + digest(sorted(own)) if own else None


#: The parts of a :func:`task_digest`, in its order, and what another value of each means
_TASK_PARTS = {
    "boundary": "another boundary (its predicates' code or values)",
    "deadline": "another deadline",
    "dt": "another step (dt)",
    "model": "another world model (its weights, config or functions)",
}


def task_digest(predicates: str, time_limit: int, dt: float | None, model: Any) -> str:
    """What a forecast answers, part by part: ``"boundary <digest> deadline <steps> dt <dt>
    model <digest>"``, the boundary's predicates (their digest,
    :attr:`~rcvae_torchrl.competency.SuccessBoundary.predicates`), the deadline judged in
    steps (``none`` for a boundary without a time limit), the seconds per step, and the world
    model (what :func:`digest` takes, without sources: its weights, config and functions,
    :meth:`~rcvae_torchrl.models.RCVAEEnsemble.behaviour`). Two tasks are the same where the
    strings are equal; :func:`task_difference` names the parts that differ."""
    parts = {**task_labels(predicates, time_limit, dt), "model": model_digest(model)}
    return " ".join(f"{k} {parts[k]}" for k in _TASK_PARTS)


def model_digest(model: Any) -> str:
    """A world model's digest, as a task's ``model`` part holds it: :func:`digest` of what it
    forecasts from (:meth:`~rcvae_torchrl.models.RCVAEEnsemble.behaviour`) without sources."""
    return digest(model, sources=False)[:16]


def task_labels(predicates: str, time_limit: float, dt: float | None) -> dict[str, str]:
    """The parts of a :func:`task_digest` that a report's labels give (``"boundary"``,
    ``"deadline"``, ``"dt"``), as the digest writes them: a record's labels are checked
    against its task with them.

    ``time_limit``: the deadline in steps, a whole number >= 1, or ``None`` / ``inf`` for
    none; ``dt``: the seconds per step, a finite number > 0, or ``None`` where not known."""
    if time_limit is None or (_is_real(time_limit) and time_limit == math.inf):
        deadline = "none"
    elif (
        _is_real(time_limit)
        and math.isfinite(time_limit)
        and time_limit >= 1
        and time_limit == int(time_limit)
    ):
        deadline = str(int(time_limit))
    else:
        raise ValueError(
            f"time_limit: expected a whole number of steps (>= 1), or None or inf for no "
            f"deadline, got {time_limit!r}"
        )
    if dt is not None and not (_is_real(dt) and math.isfinite(dt) and dt > 0):
        raise ValueError(
            f"dt: expected the seconds per step (a finite number > 0) or None, got {dt!r}"
        )
    return {
        "boundary": digest(predicates)[:16],
        "deadline": deadline,
        "dt": repr(None if dt is None else float(dt)),
    }


def _is_real(value: object) -> bool:
    """A real number: Python's or NumPy's (not a bool)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _check_task(name: str, task: object) -> None:
    if not isinstance(task, str):
        raise TypeError(
            f"{name}: expected a task_digest string (or an older record's plain digest), got "
            f"{type(task).__name__} {task!r}"
        )


def task_parts(task: str) -> dict[str, str] | None:
    """The parts of a :func:`task_digest` string by name (``"boundary"``, ``"deadline"``,
    ``"dt"``, ``"model"``: the strings it holds); ``None`` where ``task`` is not one (a str
    of another form); a ``TypeError`` where it is not a str."""
    _check_task("task", task)
    words = task.split(" ")
    parts = dict(zip(words[::2], words[1::2], strict=False))
    return (
        parts if len(words) == 2 * len(_TASK_PARTS) and list(parts) == list(_TASK_PARTS) else None
    )


def task_difference(theirs: str, mine: str) -> str:
    """What makes task ``theirs`` another than ``mine`` (two :func:`task_digest` strings), in
    words: ``"another deadline (60 steps there, 100 steps here) and another world model (its
    weights, config or functions)"``; ``""`` where they are the same, ``"another task"``
    where either is not a :func:`task_digest` (an older record's plain digest)."""
    _check_task("theirs", theirs)
    _check_task("mine", mine)
    if theirs == mine:
        return ""
    a, b = task_parts(theirs), task_parts(mine)
    if a is None or b is None:
        return "another task"
    said = []
    for key, words in _TASK_PARTS.items():
        if a[key] == b[key]:
            continue
        if key not in ("deadline", "dt"):  # digests say nothing to a reader
            said.append(words)
            continue
        there, here = (
            f"{v} steps" if key == "deadline" and v.isdigit() else v for v in (a[key], b[key])
        )
        said.append(f"{words} ({there} there, {here} here)")
    return " and ".join(said)


#: The instance attributes every ``nn.Module`` has (its parameters, buffers, hooks, flags)
_MODULE_STATE = frozenset(vars(torch.nn.Module()))


def _code_of(cls: type) -> dict[str, Any]:
    """A class by its name and the code of the methods it defines (its own and its bases'
    below ``nn.Module``), not by where it is defined: the same code in another file or in
    ``__main__`` is the same controller, other code another."""
    methods = {}
    for klass in cls.__mro__:
        if klass.__module__.split(".")[0] in _WRAPPERS or klass is object:
            continue
        for name, value in sorted(vars(klass).items()):
            if isinstance(value, types.FunctionType) and name not in methods:
                methods[name] = _code(value.__code__)
    return {"class": cls.__qualname__, "methods": methods}


def _settings(module: torch.nn.Module) -> dict[str, Any]:
    """A module's own attributes holding plain values (numbers, strings, tensors or arrays,
    and lists or dicts of them; private ones too), as :func:`describe` gives them."""
    plain = {key: _plain(v) for key, v in sorted(vars(module).items()) if key not in _MODULE_STATE}
    return {key: describe(value) for key, value in plain.items() if value is not _NOT_PLAIN}


_NOT_PLAIN = object()


def _plain(value: Any) -> Any:
    """``value`` where it is plain (a numpy array as a tensor), else :data:`_NOT_PLAIN`."""
    if isinstance(value, (tuple, list)):
        items = [_plain(v) for v in value]
        return _NOT_PLAIN if any(v is _NOT_PLAIN for v in items) else items
    if isinstance(value, Mapping):
        items = {str(k): _plain(v) for k, v in value.items()}
        return _NOT_PLAIN if any(v is _NOT_PLAIN for v in items.values()) else items
    if value is None or isinstance(value, (bool, int, float, str, torch.Tensor)):
        return value
    if type(value).__module__ == "numpy" and hasattr(value, "dtype"):  # an array or scalar
        return torch.as_tensor(value)
    return _NOT_PLAIN


def source_digest(paths: Iterable[str | Path]) -> str:
    """SHA-256 hex digest of the named files' contents, in the given order."""
    if isinstance(paths, (str, bytes, os.PathLike)) or not isinstance(paths, Iterable):
        raise TypeError(
            "paths: expected an iterable of file paths (e.g. a list), not one path or another "
            f"object, got {type(paths).__name__} {paths!r}"
        )
    h = hashlib.sha256()
    for path in paths:
        h.update(Path(path).read_bytes())
    return h.hexdigest()


_MAX_DEPTH = 8  # objects nested deeper are described by their type only


def describe(value: Any, _seen: tuple[int, ...] = ()) -> Any:
    """A JSON-able description of ``value`` that changes when its behaviour can (see the module
    docstring for what is and is not covered)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, torch.Tensor):
        return _tensor(value)
    if isinstance(value, (torch.dtype, torch.device, types.ModuleType)):
        return repr(value)
    if isinstance(value, Mapping):
        return {str(k): describe(v, _seen) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [describe(v, _seen) for v in value]
    if id(value) in _seen:  # recursion: a function reading itself, or helpers reading each other
        return f"<recursion {_name(value)}>"
    if len(_seen) >= _MAX_DEPTH:
        return f"<{_name(type(value))}>"
    seen = (*_seen, id(value))
    if isinstance(value, functools.partial):
        return {"partial": describe(value.func, seen), "args": describe(value.args, seen),
                "keywords": describe(value.keywords, seen)}  # fmt: skip
    if isinstance(value, types.MethodType):
        return {"method": describe(value.__func__, seen), "self": describe(value.__self__, seen)}
    if isinstance(value, types.FunctionType):
        return _function(value, seen)
    if isinstance(value, type):
        if not _WITH_SOURCES.get():
            return _code_of(value)  # a library's own classes: its version stands for their code
        return {"class": _name(value), "module_source": _module_source(value)}
    slots = _slot_values(value)
    if callable(value) or hasattr(value, "__dict__") or slots:
        state = {**getattr(value, "__dict__", {}), **slots}
        return {"object": describe(type(value), seen), "state": describe(state, seen)}
    if isinstance(value, np.ndarray) and not _repr_is_exact(value):
        return _array(value, seen)
    return repr(value)


def _repr_is_exact(x: np.ndarray) -> bool:
    """Whether ``repr(x)`` shows every value of ``x`` exactly: not where it summarises a large
    array by its first and last values, nor where it rounds floats to NumPy's 8 digits (0.1 and
    0.1 + 1e-12 look alike) - those are described by a hash of their values instead."""
    if x.size > np.get_printoptions()["threshold"]:
        return False
    if x.dtype.kind not in "fc":
        return True
    with np.printoptions(floatmode="unique"):  # each value's shortest repr that reads back exactly
        exact = repr(x)
    return exact == repr(x)


def _slot_values(value: Any) -> dict[str, Any]:
    """The values an object keeps in ``__slots__`` (its classes' and their bases'), which it
    has no ``__dict__`` entry for (a ``dataclass(slots=True)``'s fields)."""
    found = {}
    for klass in type(value).__mro__:
        names = getattr(klass, "__slots__", ())
        for name in (names,) if isinstance(names, str) else names:
            if name not in ("__dict__", "__weakref__") and name not in found:
                try:
                    found[name] = getattr(value, name)
                except AttributeError:  # a slot never set
                    continue
    return found


def _name(value: Any) -> str:
    return f"{getattr(value, '__module__', '?')}.{getattr(value, '__qualname__', '?')}"


def _tensor(x: torch.Tensor) -> dict[str, Any]:
    data = x.detach().cpu().contiguous()
    raw = data.view(torch.uint8) if data.dim() else data.reshape(1).view(torch.uint8)
    return {"dtype": str(x.dtype), "shape": list(x.shape),
            "sha256": hashlib.sha256(raw.numpy().tobytes()).hexdigest()}  # fmt: skip


def _array(x: np.ndarray, seen: tuple[int, ...]) -> dict[str, Any]:
    """A NumPy array whose repr does not show every value exactly: dtype, shape and a hash of
    its values (as :func:`_tensor`), or of its elements' descriptions for an object array."""
    if x.dtype.hasobject:
        values = json.dumps(describe(x.ravel().tolist(), seen), sort_keys=True, default=str)
        raw = values.encode()
    else:
        raw = np.ascontiguousarray(x).tobytes()
    return {"dtype": str(x.dtype), "shape": list(x.shape),
            "sha256": hashlib.sha256(raw).hexdigest()}  # fmt: skip


@functools.cache
def _source_of_module(name: str) -> str | None:
    module = sys.modules.get(name)
    try:
        source = inspect.getsource(module) if module is not None else None
    except (OSError, TypeError):  # built in, or defined where no source is kept
        return None
    return hashlib.sha256(source.encode()).hexdigest() if source is not None else None


def _module_source(value: Any) -> str | None:
    """The digest of the source of the module ``value`` was defined in (None when unknown; the
    digest of ``__main__`` is not cached: its source can be another script's)."""
    name = getattr(value, "__module__", None)
    if name is None:
        return None
    return _source_of_module.__wrapped__(name) if name == "__main__" else _source_of_module(name)


def _function(fn: types.FunctionType, seen: tuple[int, ...]) -> dict[str, Any]:
    code = fn.__code__
    closure = [c.cell_contents for c in fn.__closure__ or () if _filled(c)]
    return {
        "function": _name(fn),
        "code": _code(code),
        "module_source": _module_source(fn) if _WITH_SOURCES.get() else None,
        "closure": describe(closure, seen),
        "defaults": describe(fn.__defaults__, seen),
        "kwdefaults": describe(fn.__kwdefaults__, seen),
        "globals": {
            name: describe(fn.__globals__[name], seen)
            for name in sorted(_global_names(code))
            if name in fn.__globals__ and _followed(fn.__globals__[name])
        },
    }


def _filled(cell: types.CellType) -> bool:
    try:
        cell.cell_contents  # noqa: B018
    except ValueError:  # an empty cell (a name not bound yet)
        return False
    return True


def _code(code: types.CodeType) -> str:
    """Digest of a code object's bytecode, constants and names (nested code included)."""
    h = hashlib.sha256(code.co_code)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            h.update(_code(const).encode())
        elif isinstance(const, frozenset):  # set literals: their order varies between runs
            h.update(repr(sorted(map(repr, const))).encode())
        else:
            h.update(repr(const).encode())
    h.update(repr((code.co_names, code.co_varnames)).encode())
    return h.hexdigest()


def _global_names(code: types.CodeType) -> set[str]:
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= _global_names(const)
    return names


_CONSTANTS = (bool, int, float, complex, str, bytes, tuple, frozenset, torch.Tensor, type(None))


def _followed(value: Any) -> bool:
    """Module-level names a function's behaviour depends on: constants, functions and classes.
    Not modules, mutable containers (caches, registries: state, not code) or other objects, and
    not torch's or Python's own functions and classes (the torch version stands for those)."""
    if isinstance(value, _CONSTANTS):
        return True
    if not isinstance(value, (types.FunctionType, type, functools.partial)):
        return False
    module = (getattr(value, "__module__", None) or "").split(".")[0]
    return module not in ("torch", "builtins", "typing", "collections", "abc")
