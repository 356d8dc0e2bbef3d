"""Argument checks shared by every package of the library (one home for them).

Every check raises ``ValueError`` (``TypeError`` for a value of the wrong kind) whose message
names the argument, what was expected and what was given. Checks that only one package needs
live beside it (e.g. ``model_env/_checks.py``) and are built from these.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "ROUNDING",
    "as_tensor",
    "broadcasts_to",
    "check_batch_shapes",
    "check_bool",
    "check_choice",
    "check_dtype",
    "check_entries",
    "check_finite",
    "check_floating",
    "check_member",
    "check_min_rank",
    "check_non_negative",
    "check_positive",
    "check_positive_int",
    "check_positive_int_or_none",
    "check_rank",
    "check_same_shape",
    "check_same_starts",
    "check_shape",
    "check_tensor",
    "check_trailing",
    "check_unit_interval",
    "make_generator",
]


#: a float32 value copied through arithmetic stays within this of its source, relative above 1
#: (an error within ``ROUNDING * (1 + |x|)`` is no error)
ROUNDING = 1e-5


# ----------------------------------------------------------------------------- records
def check_entries(
    name: str,
    values: object,
    required: Sequence[str],
    what: str,
    optional: Sequence[str] | None = None,
) -> None:
    """Require a mapping holding every entry of ``required`` (a record read back, e.g. from
    JSON, for ``from_dict``), naming the missing ones and what the record should be.
    ``optional``: where given, the entries it may hold besides, and no other (a record of
    another kind, or one edited, is refused naming the entries it should not hold)."""
    if not isinstance(values, Mapping):
        raise TypeError(f"{name}: expected a mapping ({what}), got {type(values).__name__}")
    missing = [key for key in required if key not in values]
    if missing:
        raise ValueError(
            f"{name}: expected the entries {list(required)} ({what}), missing {missing}; "
            f"got {sorted(map(str, values))}"
        )
    if optional is not None:
        unknown = sorted(set(map(str, values)) - set(required) - set(optional))
        if unknown:
            raise ValueError(
                f"{name}: entries {unknown} are not those of {what}; expected only "
                f"{list(required) + list(optional)}"
            )


# ----------------------------------------------------------------------------- scalars
def is_integer(value: object) -> bool:
    """An integer: Python's or NumPy's (``numbers.Integral``), not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def broadcasts_to(shape: Sequence[int], target: Sequence[int]) -> bool:
    """Whether a tensor of ``shape`` broadcasts to ``target`` (torch's rule: trailing sizes
    equal or 1, no more dimensions than ``target``). Sizes only: nothing is read from a tensor,
    so it costs nothing on a device and adds no graph break under ``torch.compile``."""
    return len(shape) <= len(target) and all(
        s in (1, t) for s, t in zip(reversed(shape), reversed(target))
    )


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def check_positive_int(name: str, value: object) -> None:
    """Require a Python integer >= 1 (``bool`` is not an integer here)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}: expected a positive integer, got {value!r}")


def check_non_negative_int(name: str, value: object) -> None:
    """Require a Python integer >= 0 (``bool`` is not an integer here)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{name}: expected an integer >= 0, got {value!r}")


def check_positive_int_or_none(name: str, value: object) -> None:
    """Require ``None`` or a Python integer >= 1."""
    if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
        raise ValueError(f"{name}: expected a positive integer or None, got {value!r}")


def check_positive(name: str, value: object) -> None:
    """Require a finite number > 0."""
    if not _is_number(value) or not math.isfinite(value) or not value > 0:
        raise ValueError(f"{name}: expected a positive number, got {value!r}")


def check_non_negative(name: str, value: object) -> None:
    """Require a finite number >= 0."""
    if not _is_number(value) or not math.isfinite(value) or value < 0:
        raise ValueError(f"{name}: expected a finite number >= 0, got {value!r}")


def check_bool(name: str, value: object) -> None:
    """Require a Python bool (not a string or a number that happens to be truthy)."""
    if not isinstance(value, bool):
        raise TypeError(f"{name}: expected True or False, got {value!r}")


def check_unit_interval(name: str, value: object, *, include_zero: bool = True) -> None:
    """Require a number in [0, 1] (``include_zero``) or (0, 1]."""
    interval = "[0, 1]" if include_zero else "(0, 1]"
    if not _is_number(value):
        raise TypeError(f"{name}: expected a float in {interval}, got {value!r}")
    low_ok = value >= 0.0 if include_zero else value > 0.0
    if not (low_ok and value <= 1.0):
        raise ValueError(f"{name}: expected a float in {interval}, got {value!r}")


def check_open_unit_interval(
    name: str, value: object, what: str = "a number", why: str = ""
) -> None:
    """Require a number in (0, 1), neither end included (a share, a test's level, a held-out
    fraction); ``what`` and ``why`` word the message: ``"{name}: expected {what} in (0, 1){why},
    got ..."``."""
    if not (_is_number(value) and 0.0 < value < 1.0):
        raise ValueError(f"{name}: expected {what} in (0, 1){why}, got {value!r}")


def check_device(device: object, name: str = "device") -> None:
    """Require None or a device torch knows (``"cpu"``, ``"cuda:0"``, a ``torch.device``),
    naming ``name`` where torch's own message would not. Whether it is present on this
    machine is not judged."""
    if device is None or isinstance(device, torch.device):
        return
    try:
        torch.device(device)
    except (RuntimeError, TypeError, ValueError) as err:
        kind = TypeError if not isinstance(device, (str, int)) else ValueError
        raise kind(
            f"{name}: expected a torch device (e.g. 'cpu' or 'cuda:0') or None, got {device!r} "
            f"({err})"
        ) from None


def check_names(name: str, names: object, count: int | None = None) -> tuple[str, ...]:
    """Require distinct names (a sequence of str, not one str that would read letter by
    letter), ``count`` of them where given (one per dimension); returns them as a tuple."""
    if isinstance(names, (str, bytes)) or not isinstance(names, Sequence):
        raise TypeError(f"{name}: expected a sequence of names (str), got {names!r}")
    names = tuple(names)
    if not all(isinstance(n, str) for n in names):
        raise TypeError(f"{name}: expected a sequence of names (str), got {names!r}")
    if count is not None and len(names) != count:
        raise ValueError(
            f"{name}: expected {count} names (one per observation dimension), got {len(names)}"
        )
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(
            f"{name}: expected distinct names (results are kept by name), got {repeated} more "
            f"than once in {list(names)}"
        )
    return names


def check_seeds(name: str, seeds: object) -> list[int]:
    """Require a sequence of integer seeds (Python, NumPy or one-element integer tensors; a
    float would be truncated, so two seeds could give one episode twice); returns them as
    Python ints."""
    if isinstance(seeds, (Tensor, np.ndarray)) and seeds.ndim == 1:
        seeds = list(seeds)  # its elements are checked below
    if isinstance(seeds, (str, bytes)) or not isinstance(seeds, Sequence):
        raise TypeError(
            f"{name}: expected a sequence of integer seeds (one per episode, e.g. range(10)), "
            f"got {type(seeds).__name__} {seeds!r}"
        )
    out = []
    for seed in seeds:
        integer = isinstance(seed, numbers.Integral)  # Python's and NumPy's integers
        if isinstance(seed, Tensor):
            integer = seed.numel() == 1 and not seed.is_floating_point()
        if isinstance(seed, bool) or not integer:
            raise ValueError(f"{name}: expected integer seeds, got {seed!r}")
        out.append(int(seed))
    return out


def check_seed(name: str, seed: object) -> int:
    """Require one integer seed >= 0 (a Python or NumPy integer; a negative one would wrap to
    2**64 - 1 in ``torch.Generator.manual_seed``, a float be truncated); returns it as an int."""
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
        raise ValueError(f"{name}: expected an integer seed >= 0, got {seed!r}")
    return int(seed)


def check_choice(name: str, value: object, choices: Sequence[str]) -> None:
    """Require ``value`` to be one of ``choices``."""
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name}: expected one of {sorted(choices)}, got {value!r}")


# ----------------------------------------------------------------------------- tensors
def check_tensor(name: str, x: object) -> Tensor:
    """Require a ``torch.Tensor``; returns it."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    return x


def as_tensor(name: str, x: object) -> Tensor:
    """``x`` as a tensor (numbers and sequences are converted), or ``TypeError`` naming it."""
    if isinstance(x, Tensor):
        return x
    if isinstance(x, (int, float, bool, Sequence)) and not isinstance(x, str):
        return torch.as_tensor(x)
    raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")


def check_floating(name: str, x: Tensor) -> None:
    """Require a floating-point tensor."""
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")


def check_dtype(name: str, x: Tensor, dtype: torch.dtype, owner: str = "the model's") -> None:
    """Require ``x.dtype == dtype``; the message says where it comes from and how to convert."""
    if x.dtype != dtype:
        hint = ""
        if x.is_floating_point() and dtype.is_floating_point:
            wider = torch.finfo(x.dtype).bits > torch.finfo(dtype).bits
            hint = (
                f"; convert the inputs (x.to({dtype})), or for a TorchRL env append a "
                "DoubleToFloat transform"
                if wider
                else f"; convert the inputs (x.to({dtype})), or the model to theirs "
                f"(model.to({x.dtype}))"
            )
        elif "action" in name and not x.is_floating_point() and dtype.is_floating_point:
            hint = (
                "; integer or bool actions are discrete ones (a OneHot or Categorical action "
                "spec), which the world model does not take: relax them to a continuous action "
                "in [-1, 1] that a transform on the real env turns into the discrete one"
            )
        raise TypeError(f"{name}: expected dtype {dtype} ({owner}), got {x.dtype}{hint}")


def _all_finite(x: Tensor) -> bool:
    """True when no entry is NaN or ±inf; ``aminmax`` allocates nothing of the input's size."""
    if x.numel() == 0:
        return True
    low, high = torch.aminmax(x)
    return bool(torch.isfinite(low)) and bool(torch.isfinite(high))


def check_finite(name: str, x: Tensor) -> None:
    """Require every entry of a floating tensor to be finite (no NaN, no inf)."""
    if x.is_floating_point() and not _all_finite(x):
        n_nan = int(torch.isnan(x).sum())
        n_inf = int(torch.isinf(x).sum())
        raise ValueError(
            f"{name}: expected finite values, got {n_nan} NaN and {n_inf} inf "
            f"entries in a tensor of shape {tuple(x.shape)}"
        )


def check_bounds(name: str, low: object, high: object, *, finite: bool = False) -> None:
    """Require bounds with ``low <= high`` everywhere and no NaN (nor ±inf when ``finite``);
    ``low`` and ``high`` are numbers or tensors that broadcast together."""
    lo, hi = torch.as_tensor(low), torch.as_tensor(high)
    bad = torch.isnan(lo).any() | torch.isnan(hi).any() | (lo > hi).any()
    if finite:
        bad = bad | ~torch.isfinite(lo).all() | ~torch.isfinite(hi).all()
    if bool(bad):
        show = [v.tolist() if isinstance(v, Tensor) else v for v in (low, high)]
        want = "finite bounds with low <= high" if finite else "low <= high (and no NaN)"
        raise ValueError(f"{name}: expected {want}, got {show[0]} and {show[1]}")


def check_min_rank(name: str, x: Tensor, min_rank: int, layout: str) -> None:
    """Require ``x.ndim >= min_rank``; ``layout`` describes the expected shape."""
    check_tensor(name, x)
    if x.ndim < min_rank:
        raise ValueError(
            f"{name}: expected shape {layout} (at least {min_rank} dims), "
            f"got shape {tuple(x.shape)} ({x.ndim} dims)"
        )


def check_rank(name: str, x: Tensor, rank: int, layout: str) -> None:
    """Require ``x.ndim == rank``; ``layout`` describes the expected shape."""
    check_tensor(name, x)
    if x.ndim != rank:
        raise ValueError(
            f"{name}: expected shape {layout} ({rank} dims), "
            f"got shape {tuple(x.shape)} ({x.ndim} dims)"
        )


def check_shape(name: str, x: Tensor, expected: Sequence[int], layout: str) -> None:
    """Require ``x.shape == expected``; ``layout`` names the axes, e.g. ``"[*B, C, H, *A]"``."""
    check_tensor(name, x)
    if tuple(x.shape) != tuple(expected):
        raise ValueError(
            f"{name}: expected shape {layout} = {tuple(expected)}, got {tuple(x.shape)}"
        )


def check_trailing(name: str, x: Tensor, trailing: Sequence[int], layout: str) -> None:
    """Require ``x.shape`` to end with ``trailing``; ``layout`` describes it (``[*B, S=5]``)."""
    check_tensor(name, x)
    n = len(trailing)
    if x.dim() < n or tuple(x.shape[x.dim() - n :]) != tuple(trailing):
        raise ValueError(f"{name}: expected shape {layout}, got {tuple(x.shape)}")


def check_same_shape(name_a: str, a: Tensor, name_b: str, b: Tensor) -> None:
    """Require ``a`` and ``b`` to have the same shape."""
    if a.shape != b.shape:
        raise ValueError(
            f"{name_a} and {name_b}: expected the same shape, "
            f"got {tuple(a.shape)} and {tuple(b.shape)}"
        )


def check_same_starts(name: str, mine: Tensor | None, theirs: Tensor | None, what: str) -> None:
    """Refuse ``theirs`` (start states ``[B, S]`` of what ``name`` holds) where they are not
    ``mine`` (``[B', S]``, e.g. a report's), row for row: other start states, or the same in
    another order, judge other tasks. ``what`` says what ``name`` holds (e.g. "the real
    episodes"). Not compared where either is not known (``None``) or the dimensions differ."""
    if mine is None or theirs is None:
        return
    mine, theirs = mine.reshape(-1, mine.shape[-1]), theirs.reshape(-1, theirs.shape[-1])
    if mine.shape[-1] != theirs.shape[-1]:
        return
    if mine.shape[0] != theirs.shape[0]:
        raise ValueError(
            f"{name}: expected {what} of the forecast's {mine.shape[0]} start states, got "
            f"{theirs.shape[0]}"
        )
    differ = (mine.detach().cpu().double() - theirs.detach().cpu().double()).abs().amax(-1)
    other = (differ > 1e-5 * (1.0 + mine.detach().cpu().double().abs().amax(-1))).nonzero()
    if other.numel():
        raise ValueError(
            f"{name}: expected {what} from the forecast's start states, in its order, got "
            f"{other.numel()} of {mine.shape[0]} other ones (the first: start {int(other[0])}); "
            "other start states, or the same in another order, are other tasks"
        )


def check_batch_shapes(names: tuple[str, str], a: Sequence[int], b: Sequence[int]) -> None:
    """Require the batch shapes of two arguments to be equal."""
    if tuple(a) != tuple(b):
        raise ValueError(
            f"{names[1]}: expected batch shape {tuple(a)} (that of {names[0]}), got {tuple(b)}"
        )


def check_member(member: Tensor, ensemble_size: int, name: str = "member") -> None:
    """Require an integer tensor with values in ``[0, ensemble_size)``."""
    if member.dtype not in (torch.int64, torch.int32):
        raise TypeError(f"{name}: expected an int64 tensor, got dtype {member.dtype}")
    if member.numel() and (int(member.min()) < 0 or int(member.max()) >= ensemble_size):
        raise ValueError(
            f"{name}: expected values in [0, {ensemble_size}), got range "
            f"[{int(member.min())}, {int(member.max())}]"
        )


# ----------------------------------------------------------------------------- randomness
def make_generator(
    generator: torch.Generator | None,
    seed: int | None,
    device: torch.device | str | None = None,
) -> torch.Generator | None:
    """``generator``, or a new one on ``device`` seeded with ``seed`` (not both; neither: None).

    A seed must be an integer in ``[0, 2**63)``, the range torch's generators accept.
    """
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(
            f"generator: expected a torch.Generator or None, got {type(generator).__name__}"
        )
    if generator is not None and seed is not None:
        raise ValueError(f"seed: expected None when a generator is given, got {seed!r}")
    if seed is None:
        return generator
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
        raise ValueError(f"seed: expected an integer in [0, 2**63), got {seed!r}")
    return torch.Generator(device=device or "cpu").manual_seed(seed)
