"""Any TorchRL env as the library expects it: one float32 ``"observation"`` vector, named.

The world model learns one state vector ``"observation"`` ``[S]`` of the model's dtype. Many
envs give several observation entries (dm_control: ``"position"``, ``"velocity"``, ...) in
float64. :func:`prepare_env` concatenates the entries you name (or all floating ones) into
``"observation"`` with TorchRL's own transforms (``DoubleToFloat``, ``CatTensors``) and returns
the :class:`ObservationLayout`: which dimensions came from which entry, with a name for each.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, Composite
from torchrl.envs import (
    CatTensors,
    Compose,
    DoubleToFloat,
    EnvBase,
    ExcludeTransform,
    FrameSkipTransform,
    PendulumEnv,
    Transform,
    TransformedEnv,
    UnsqueezeTransform,
)

from rcvae_torchrl._checks import check_bounds, check_non_negative_int, check_seed

__all__ = [
    "ActionNoise",
    "AngleAsCosSin",
    "ObservationLayout",
    "control_step",
    "observation_layout",
    "prepare_env",
    "seed_env",
]

OBSERVATION_KEY = "observation"
#: the suffix of the ``[1]`` copies of scalar entries that ``prepare_env`` concatenates
_UNSQUEEZED = "_unsqueezed"


@dataclass(frozen=True)
class ObservationLayout:
    """The dimensions of a concatenated observation: source entries and their sizes, in order.

    Example:
        >>> layout = ObservationLayout(("position", "velocity"), (2, 2))
        >>> layout.names
        ('position[0]', 'position[1]', 'velocity[0]', 'velocity[1]')
        >>> layout.indices("velocity")
        [2, 3]
    """

    keys: tuple[str, ...]
    sizes: tuple[int, ...]

    def __post_init__(self) -> None:
        for name in ("keys", "sizes"):
            if isinstance(getattr(self, name), (str, bytes)):
                raise TypeError(
                    f"{name}: expected a tuple (one per entry), got the string "
                    f"{getattr(self, name)!r}"
                )
        if len(self.keys) != len(self.sizes) or not self.keys:
            raise ValueError(
                f"keys, sizes: expected one size per key, got {self.keys} and {self.sizes}"
            )
        for key in self.keys:
            if not (isinstance(key, str) and key) and not (
                isinstance(key, tuple) and key and all(isinstance(k, str) for k in key)
            ):
                raise TypeError(f"keys: expected entry names (str), got {key!r} in {self.keys}")
        if len(set(self.keys)) != len(self.keys):
            raise ValueError(f"keys: expected distinct entries, got {self.keys}")
        for size in self.sizes:
            if isinstance(size, bool) or not isinstance(size, int) or size < 1:
                raise ValueError(
                    f"sizes: expected a positive integer per entry, got {size!r} in {self.sizes}"
                )

    @property
    def dim(self) -> int:
        """S, the size of the concatenated observation."""
        return sum(self.sizes)

    @property
    def names(self) -> tuple[str, ...]:
        """A name per dimension: ``key[i]`` (``key`` alone for an entry of size 1)."""
        return tuple(
            key if size == 1 else f"{key}[{i}]"
            for key, size in zip(self.keys, self.sizes)
            for i in range(size)
        )

    @classmethod
    def from_names(cls, names: Sequence[str]) -> ObservationLayout:
        """The layout whose :attr:`names` are ``names``, read back: consecutive ``key[0]``,
        ``key[1]``, ... form an entry ``key``; any other name is an entry of one dimension.

        Example:
            >>> ObservationLayout.from_names(("x[0]", "x[1]", "speed")).sizes
            (2, 1)
        """
        if isinstance(names, (str, bytes)) or not isinstance(names, Sequence) or not names:
            raise ValueError(
                f"names: expected a non-empty sequence of dimension names, got {names!r}"
            )
        keys: list[str] = []
        sizes: list[int] = []
        indexed: list[bool] = []
        for name in names:
            match = re.fullmatch(r"(.+)\[(\d+)\]", name)
            key, index = (match.group(1), int(match.group(2))) if match else (name, None)
            if keys and indexed[-1] and keys[-1] == key and index == sizes[-1]:
                sizes[-1] += 1  # the entry's next dimension
                continue
            keys.append(key if index == 0 else name)
            sizes.append(1)
            indexed.append(index == 0)
        # a lone "key[0]" is an entry of one dimension named so (a size-1 entry's name is its key)
        keys = [f"{k}[0]" if i and n == 1 else k for k, n, i in zip(keys, sizes, indexed)]
        return cls(tuple(keys), tuple(sizes))

    def indices(self, key: str) -> list[int]:
        """The dimensions that came from entry ``key``."""
        if key not in self.keys:
            raise KeyError(f"key: expected one of {list(self.keys)}, got {key!r}")
        start = sum(self.sizes[: self.keys.index(key)])
        return list(range(start, start + self.sizes[self.keys.index(key)]))


def check_env(env: object, name: str = "env") -> None:
    """Require a TorchRL env (an ``EnvBase``)."""
    if not isinstance(env, EnvBase):
        raise TypeError(f"{name}: expected a TorchRL env (an EnvBase), got {_type_name(env)}")


def _type_name(value: object) -> str:
    return f"the class {value.__name__}" if isinstance(value, type) else type(value).__name__


def _name(key: NestedKey) -> str:
    return key if isinstance(key, str) else ".".join(key)


def _floating_entries(env: EnvBase) -> list[NestedKey]:
    spec = env.observation_spec
    return [
        key
        for key in spec.keys(True, True)
        if _is_floating(spec[key]) and len(spec[key].shape) - len(env.batch_size) <= 1
    ]


def _is_floating(spec: object) -> bool:
    """A floating tensor entry (a non-tensor entry's spec has no dtype)."""
    dtype = getattr(spec, "dtype", None)
    return dtype is not None and dtype.is_floating_point


def prepare_env(
    env: EnvBase,
    observation_keys: Sequence[NestedKey] | None = None,
    *,
    keep_keys: bool = True,
) -> tuple[TransformedEnv, ObservationLayout]:
    """``env`` with one float32 ``"observation"`` entry the world model can learn.

    Args:
        env: any TorchRL env.
        observation_keys: the observation entries to model, concatenated in this order; default
            the env's ``"observation"`` if it has one, else every floating entry of at most one
            dimension (scalars count as one dimension), in the spec's order. Name them for an
            env that also carries constants among its observations (TorchRL's
            ``PendulumEnv`` carries its ``"params"``): a constant is no state to model.
        keep_keys: keep the source entries beside ``"observation"`` (for task functions or
            policies that read them, and for envs that read their state back from them, as
            TorchRL's stateless ``PendulumEnv`` does).

    Returns:
        ``(TransformedEnv, ObservationLayout)``: float64 entries (observations, action,
        reward) become float32 (``DoubleToFloat``), the named entries are concatenated
        (``CatTensors``) into ``"observation"``.

    Raises:
        KeyError: a named entry the env does not have.
        ValueError: an entry that is not floating point or has more than one dimension.
    """
    check_env(env)
    if isinstance(observation_keys, str) or (
        observation_keys is not None and not isinstance(observation_keys, (list, tuple))
    ):
        what = "the string" if isinstance(observation_keys, str) else _type_name(observation_keys)
        raise TypeError(
            f"observation_keys: expected a list of keys, e.g. [{observation_keys!r}], got "
            f"{what} {observation_keys!r}"
        )
    if not isinstance(keep_keys, bool):
        raise TypeError(f"keep_keys: expected True or False, got {keep_keys!r}")
    spec = env.observation_spec
    keys = list(observation_keys) if observation_keys is not None else None
    if keys is not None and not keys:
        raise ValueError("observation_keys: expected at least one key (or None), got []")
    if keys is not None and len(set(keys)) != len(keys):
        raise ValueError(f"observation_keys: expected each key once, got {keys}")
    if keys is None:
        keys = [OBSERVATION_KEY] if OBSERVATION_KEY in spec.keys() else _floating_entries(env)
    if not keys:
        raise ValueError(
            f"env: {type(env).__name__} has no floating observation entry to model; name the "
            "entries with observation_keys"
        )
    sizes, scalars = [], []
    for key in keys:
        if key not in spec.keys(True, True):
            raise KeyError(
                f"observation_keys: {type(env).__name__} has no observation {key!r} (it has "
                f"{sorted(map(_name, spec.keys(True, True)))})"
            )
        shape = spec[key].shape[len(env.batch_size) :]
        if not _is_floating(spec[key]) or len(shape) > 1:
            raise ValueError(
                f"observation_keys: {key!r} must be a floating vector or scalar, got dtype "
                f"{getattr(spec[key], 'dtype', None)} ({type(spec[key]).__name__}) and shape "
                f"{tuple(shape)}"
            )
        sizes.append(int(shape.numel()))
        if len(shape) == 0:
            scalars.append(key)
    transforms: list[Transform] = []
    if _has_double(env):
        transforms.append(DoubleToFloat())
    if keys != [OBSERVATION_KEY]:
        transforms += _concatenation(keys, scalars, keep_keys)
    # a transformed env keeps its own transforms, wrapped (not unwrapped into ours)
    prepared = TransformedEnv(env, Compose(*transforms), auto_unwrap=False)
    return prepared, ObservationLayout(tuple(_name(k) for k in keys), tuple(sizes))


def _concatenation(
    keys: list[NestedKey], scalars: list[NestedKey], keep_keys: bool
) -> list[Transform]:
    """The transforms that concatenate ``keys`` into ``"observation"``: scalar entries are first
    copied as ``[1]`` vectors (``CatTensors`` cannot start from a scalar), the copies then
    dropped; with ``keep_keys`` the source entries stay as they were."""
    vectors = {key: ("_" + _name(key) + _UNSQUEEZED if key in scalars else key) for key in keys}
    transforms: list[Transform] = []
    if scalars:
        copies = [vectors[key] for key in scalars]
        transforms.append(UnsqueezeTransform(-1, in_keys=scalars, out_keys=copies))
    transforms.append(
        CatTensors(list(vectors.values()), OBSERVATION_KEY, del_keys=not keep_keys, sort=False)
    )
    # the copies (deleted by CatTensors without keep_keys, where the scalar sources remain)
    drop = [vectors[key] for key in scalars] if keep_keys else scalars
    if drop:
        transforms.append(ExcludeTransform(*drop))
    return transforms


def _has_double(env: EnvBase) -> bool:
    specs = (env.observation_spec, env.full_action_spec, env.full_reward_spec)
    return any(s[key].dtype == torch.float64 for s in specs for key in s.keys(True, True))


class AngleAsCosSin(Transform):
    """Writes each angle entry's cosine and sine beside it (``"th"`` -> ``"th_cos"``,
    ``"th_sin"``), for :func:`prepare_env` to model instead of the angle.

    A wrapped angle jumps at ±π, which a smooth model blurs into states between the two ends;
    its cosine and sine move smoothly (keep them on the unit circle in imagination with a
    state constraint). The angle stays, for envs that read their state back from it.

    Example:
        >>> from torchrl.envs import PendulumEnv, TransformedEnv
        >>> env = TransformedEnv(PendulumEnv(), AngleAsCosSin(["th"]))
        >>> env, layout = prepare_env(env, ["th_cos", "th_sin", "thdot"])
        >>> layout.names
        ('th_cos', 'th_sin', 'thdot')
    """

    def __init__(self, in_keys: Sequence[NestedKey]) -> None:
        if isinstance(in_keys, str) or not isinstance(in_keys, Sequence) or not in_keys:
            raise TypeError(f"in_keys: expected a non-empty list of angle keys, got {in_keys!r}")
        for key in in_keys:
            if not (isinstance(key, str) and key) and not (
                isinstance(key, tuple) and key and all(isinstance(k, str) for k in key)
            ):
                raise TypeError(f"in_keys: expected keys (str or tuples of str), got {key!r}")
        names = [_name(key) for key in in_keys]
        out_keys = [f"{name}_{part}" for name in names for part in ("cos", "sin")]
        super().__init__(in_keys=list(in_keys), out_keys=out_keys)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        for key, cos, sin in zip(self.in_keys, self.out_keys[::2], self.out_keys[1::2]):
            angle = next_tensordict.get(key)
            next_tensordict.set(cos, angle.cos())
            next_tensordict.set(sin, angle.sin())
        return next_tensordict

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        for key, cos, sin in zip(self.in_keys, self.out_keys[::2], self.out_keys[1::2]):
            if key not in observation_spec.keys(True, True):
                raise KeyError(
                    f"in_keys: the env has no observation {key!r} (it has "
                    f"{sorted(map(_name, observation_spec.keys(True, True)))})"
                )
            angle = observation_spec[key]
            if not _is_floating(angle):
                raise TypeError(f"in_keys: {key!r} must be a floating angle, got {angle.dtype}")
            for out in (cos, sin):
                observation_spec[out] = Bounded(
                    -1.0, 1.0, angle.shape, dtype=angle.dtype, device=angle.device
                )
        return observation_spec


class ActionNoise(Transform):
    """A stochastic variant of any env: Gaussian noise on every action before it reaches the env.

    The env receives ``clip(a + std·ε, low, high)`` while the rollout records the commanded
    action ``a`` (the inverse transform of the ``"action"`` entry), as an actuator with noise
    would. The noise comes from the transform's own generator: seed it with :func:`seed_env`
    (TorchRL's ``set_seed`` seeds only the base env).

    Args:
        std: the noise's standard deviation (>= 0), scalar or ``[A]``.
        low, high: clip the noisy action to these bounds (default: the action spec's).
        seed: the generator's initial seed.
    """

    def __init__(
        self,
        std: float | torch.Tensor,
        *,
        low: float | torch.Tensor | None = None,
        high: float | torch.Tensor | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(in_keys_inv=["action"], out_keys_inv=["action"])
        if isinstance(std, (str, bytes, bool)) or std is None:
            raise TypeError(f"std: expected a number or a tensor, got {std!r}")
        std = torch.as_tensor(std, dtype=torch.float32)
        if not bool(torch.isfinite(std).all() and (std >= 0).all()):
            raise ValueError(f"std: expected a finite standard deviation >= 0, got {std}")
        self.register_buffer("std", std)
        for name, bound in (("low", low), ("high", high)):
            if bound is None:
                continue
            if isinstance(bound, (str, bytes, bool)):
                raise TypeError(f"{name}: expected a number, a tensor or None, got {bound!r}")
            check_bounds(name, bound, bound)  # no NaN
        if low is not None and high is not None:
            check_bounds("low, high", low, high)
        self._low, self._high = low, high
        self.generator = torch.Generator().manual_seed(check_seed("seed", seed))

    def reseed(self, seed: int) -> None:
        """Restart the noise stream (called by :func:`seed_env`)."""
        self.generator.manual_seed(check_seed("seed", seed))

    def _bounds(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        low, high = self._low, self._high
        if (low is None or high is None) and self.parent is not None:
            space = self.parent.full_action_spec["action"].space
            low = space.low if low is None else low
            high = space.high if high is None else high
        low = torch.as_tensor(-torch.inf if low is None else low).to(action)
        high = torch.as_tensor(torch.inf if high is None else high).to(action)
        return low, high

    def _inv_apply_transform(self, action: torch.Tensor) -> torch.Tensor:
        if self.std.ndim > 1 or (self.std.ndim == 1 and self.std.shape[0] != action.shape[-1]):
            raise ValueError(
                f"std: expected a scalar or one standard deviation per action dimension, "
                f"[A = {action.shape[-1]}] for this env's actions, got shape "
                f"{tuple(self.std.shape)}"
            )
        noise = torch.randn(action.shape, generator=self.generator).to(action)
        return torch.clamp(action + self.std.to(action) * noise, *self._bounds(action))


def seed_env(env: EnvBase, seed: int) -> None:
    """``env.set_seed(seed)``, and restart every transform that has its own random stream
    (those with a ``reseed`` method, e.g. :class:`ActionNoise`) from the same seed.

    The env gets ``seed mod 2**32`` (numpy-based envs such as dm_control's take no more), so
    seeds derived from any study seed are valid.
    """
    check_env(env)
    check_non_negative_int("seed", seed)
    env.set_seed(seed % 2**32)
    # the transforms of every TransformedEnv layer (an ActionNoise wrapped before prepare_env
    # is inside its layer); a ParallelEnv would send the lookup to its workers (and fail
    # there): transforms inside a batched env's sub-envs are not reached
    for part in _transforms(env)[0]:
        if callable(getattr(part, "reseed", None)):
            part.reseed(seed)


def control_step(env: EnvBase) -> tuple[float, str] | None:
    """The seconds of simulated time one step of ``env`` takes, where it can be read, and how
    it was read; ``None`` where it cannot (e.g. gymnasium's ``MountainCarContinuous``, which
    keeps no ``dt``: ``control_step(env)[0]`` fails there, so test for ``None``).

    Read from the base env's simulator (dm_control's ``control_timestep()``; gym and
    gymnasium's ``unwrapped.dt``; an env of one's own with a number ``dt`` among its
    attributes; TorchRL's ``PendulumEnv``, the ``("params", "dt")`` of its ``gen_params()``,
    which its resets use), times the frame
    skip of a wrapper that skips frames itself (``DMControlEnv(..., frame_skip=k)``) and every
    ``FrameSkipTransform``'s around it. A batched env (its sub-envs are not reached) and other
    envs give ``None``.

    Example:
        >>> from torchrl.envs import DMControlEnv, FrameSkipTransform
        >>> env = DMControlEnv("cartpole", "swingup").append_transform(FrameSkipTransform(5))
        >>> control_step(env)
        (0.05, "DMControlEnv's control timestep 0.01 s x FrameSkipTransform(5)")
    """
    check_env(env)
    transforms, base = _transforms(env)
    skips = [p.frame_skip for p in transforms if isinstance(p, FrameSkipTransform)]
    inner = base.__dict__.get("_env")  # not getattr: a batched env would ask its workers
    timestep = getattr(inner, "control_timestep", None)
    if callable(timestep):
        dt, what = float(timestep()), "control timestep"
    elif isinstance(getattr(getattr(inner, "unwrapped", None), "dt", None), (int, float)):
        dt, what = float(inner.unwrapped.dt), "dt"
    elif _is_seconds(own := base.__dict__.get("dt")):  # an env of one's own keeping its dt
        dt, what = float(own), "dt"
    elif (declared := _declared_dt(base)) is not None:
        dt, what = declared, "default params' dt"
    else:
        return None
    text = f"{type(base).__name__}'s {what} {dt:g} s"
    # a wrapper that skips frames itself (TorchRL's DMControlEnv(..., frame_skip=k), GymEnv);
    # read from __dict__ as TorchRL does (a batched env would start its workers to answer)
    native = base.__dict__.get("frame_skip", 1) if getattr(type(base), "_has_frame_skip", 0) else 1
    if isinstance(native, int) and native > 1:
        dt, text = dt * native, text + f" x frame_skip={native}"
    for skip in skips:
        dt, text = dt * skip, text + f" x FrameSkipTransform({skip})"
    return round(dt, 12), text


def _is_seconds(value: object) -> bool:
    """A positive finite number (not a bool)."""
    return (
        isinstance(value, (int, float))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value > 0
    )


def _declared_dt(base: EnvBase) -> float | None:
    """The ``("params", "dt")`` of ``gen_params()`` for TorchRL's ``PendulumEnv`` (and its
    subclasses), whose resets take their parameters from it; else ``None`` (another env's
    ``gen_params`` defaults need not be the instance's)."""
    if not isinstance(base, PendulumEnv):
        return None
    params = getattr(type(base), "gen_params", None)
    try:
        found = params() if callable(params) else None
    except TypeError:  # a gen_params of another kind, which needs arguments
        return None
    if isinstance(found, TensorDictBase) and ("params", "dt") in found.keys(True):
        return float(f"{float(found['params', 'dt']):.7g}")  # float32's digits
    return None


def _transforms(env: EnvBase) -> tuple[list[Transform], EnvBase]:
    """Every transform around ``env``'s base env, in the order they apply to an observation
    (the innermost env's first), and the base env. Transforms inside a batched env's sub-envs
    are not reached (their workers are not asked)."""
    layers = []
    base = env
    while isinstance(base, TransformedEnv):
        transform = base.transform
        layers.append(list(transform) if isinstance(transform, Compose) else [transform])
        base = base.base_env
    return [t for layer in reversed(layers) for t in layer], base


def observation_layout(env: EnvBase) -> ObservationLayout | None:
    """The layout of ``env``'s ``"observation"`` as a :func:`prepare_env`'d env builds it: the
    entries its last ``CatTensors`` into ``"observation"`` concatenates, in order, and their
    sizes; ``None`` where no transform of ``env`` builds it (the env gives it itself, or a
    batched env's sub-envs do)."""
    check_env(env)
    transforms, _ = _transforms(env)
    cats = [
        t for t in transforms if isinstance(t, CatTensors) and list(t.out_keys) == [OBSERVATION_KEY]
    ]
    if not cats or cats[-1].parent is None:
        return None
    cat = cats[-1]
    parent = cat.parent
    spec = parent.full_observation_spec
    keys, sizes = [], []
    for key in cat.in_keys:
        if key not in spec.keys(True, True):
            return None
        name = _name(key)
        scalar = name.startswith("_") and name.endswith(_UNSQUEEZED)  # prepare_env's copies
        keys.append(name[1 : -len(_UNSQUEEZED)] if scalar else name)
        sizes.append(int(spec[key].shape[len(parent.batch_size) :].numel()))
    return ObservationLayout(tuple(keys), tuple(sizes))
