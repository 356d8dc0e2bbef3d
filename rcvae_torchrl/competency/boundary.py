"""User-specified success / failure boundary of a task, evaluated on observation trajectories.

The paper forecasts "the probability of success ... based on a user specified success-failure
boundary" (Acharya, Russell & Ahmed, 2022, Sec. IV): here a success region (any predicate over
observations, or a ball around a target), a time limit, and an optional failure predicate; or,
for tasks of staying inside rather than reaching (a pole upright, a cart on its track), a
failure predicate alone that must not hold before the time limit (:meth:`SuccessBoundary.survival`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from rcvae_torchrl import fingerprint
from rcvae_torchrl.competency import _checks

__all__ = ["Predicate", "SuccessBoundary", "check_same_predicates", "hold_last_state"]

#: ``obs [..., D] -> bool [...]``, a function of each state alone: a forecast calls it on
#: whole trajectories ``[..., T, D]`` and the model env on one step's states ``[..., D]``, so
#: it must not combine states along an axis (a sum over time would sum over the batch there).
Predicate = Callable[[Tensor], Tensor]


class SuccessBoundary:
    """Success region + time limit (+ failure region) over trajectories ``[..., T, D]``.

    A trajectory succeeds when it is inside the success region at some step ``t`` with
    ``t < time_limit`` (step indices along the time axis of the observations) and no failure
    occurred at or before ``t``. It fails when a failure occurs within the time limit before any
    success (a failure and a success at the same step count as a failure); otherwise it times out.
    A survival boundary (:meth:`survival`, ``success is None``) has no success region: a
    trajectory succeeds by reaching its time limit without a failure.

    Args:
        success: predicate ``obs [..., D] -> bool [...]`` for the success region; ``None`` for
            a survival boundary (needs ``failure`` and a time limit).
        time_limit: number of steps that count; ``None`` for the whole horizon.
        time_limit_s: alternatively the limit in time (seconds, or ``time_unit``), with
            ``dt`` (steps = ``floor(time_limit_s / dt)``).
        dt: the duration of one step in seconds (or ``time_unit``); needed by
            ``time_limit_s`` and for times in the reports.
        failure: optional predicate for the failure region.
        time_unit: the unit of ``dt`` and of every time the reports write (``"s"``; e.g.
            ``"days"`` for an env whose step is a day, with ``dt=1``). With another unit than
            seconds, ``dt`` is not compared with a simulator's control step.

    Example:
        >>> boundary = SuccessBoundary.ball(position=[0, 1], target=[2, 3], radius=0.03,
        ...                                 time_limit_s=30.0, dt=0.05)
        >>> boundary.time_limit
        600
        >>> obs = torch.tensor([[[0.0, 0.0, 0.5, 0.5], [0.5, 0.49, 0.5, 0.5]]])  # [1, T=2, D=4]
        >>> boundary.success_over_time(obs).tolist()
        [[False, True]]
    """

    def __init__(
        self,
        success: Predicate | None,
        *,
        time_limit: int | None = None,
        time_limit_s: float | None = None,
        dt: float | None = None,
        failure: Predicate | None = None,
        time_unit: str = "s",
    ) -> None:
        if not isinstance(time_unit, str) or not time_unit.strip():
            raise TypeError(
                f"time_unit: expected the name of dt's unit (e.g. 's', 'days'), got {time_unit!r}"
            )
        if success is not None and not callable(success):
            raise TypeError(
                f"success: expected a callable predicate (or None: a survival boundary), got "
                f"{type(success).__name__}"
            )
        if failure is not None and not callable(failure):
            raise TypeError(f"failure: expected a callable predicate, got {type(failure).__name__}")
        self.success = success
        self.failure = failure
        self.dt = dt
        self.time_unit = time_unit
        self.time_limit = _time_limit_steps(time_limit, time_limit_s, dt)
        if success is None and failure is None:
            raise TypeError(
                "success, failure: expected a success predicate, or (a survival boundary) a "
                "failure predicate, got neither"
            )
        if success is None and math.isinf(self.time_limit):
            raise ValueError(
                "time_limit, time_limit_s: expected how long to last (a survival boundary, "
                "success=None, is decided at its time limit), got neither"
            )

    @classmethod
    def survival(cls, failure: Predicate, **kwargs: object) -> SuccessBoundary:
        """Success when a trajectory reaches the time limit without a failure: a task of
        staying inside a region (a pole upright, a vehicle in its lane) rather than reaching one
        (the same as ``SuccessBoundary(None, failure=failure, ...)``).

        A trajectory succeeds at step ``time_limit - 1``, the last that counts, when no failure
        occurred at or before it, and fails at its first failure within the limit. One shorter
        than the limit without a failure times out: it has not lasted the limit yet (the
        :class:`~rcvae_torchrl.competency.CompetencyAssessor` refuses such a horizon).

        Args:
            failure: predicate ``obs [..., D] -> bool [...]`` of the states to avoid.
            **kwargs: ``time_limit`` (how long to last, in steps; required, or
                ``time_limit_s`` with ``dt``), ``time_limit_s``, ``dt`` as in the constructor.

        Example:
            >>> fallen = lambda obs: obs[..., 0].abs() > 0.5  # e.g. a pole's angle (rad)
            >>> boundary = SuccessBoundary.survival(fallen, time_limit=3)
            >>> obs = torch.tensor([[0.1, 0.2, 0.3, 0.4], [0.1, 0.6, 0.0, 0.0]]).unsqueeze(-1)
            >>> _, success, failure = boundary.outcome(obs)  # [2, T=4, D=1]
            >>> success.tolist(), failure.tolist()
            ([True, False], [False, True])
        """
        return cls(None, failure=failure, **kwargs)  # type: ignore[arg-type]

    @property
    def predicates(self) -> str:
        """What judges a trajectory here, as a digest of the success and failure predicates
        (their code and the values they read, not the rest of the file that defines them:
        :func:`rcvae_torchrl.fingerprint.digest` without sources): a
        report keeps it in its task, real outcomes judged by this boundary keep it too, and
        a forecast is not scored against outcomes judged by other predicates (another radius).
        Predicates the digest cannot walk are named by their identity in this process."""
        try:
            return fingerprint.digest([self.success, self.failure], sources=False)
        except Exception:  # an object describe() cannot walk: this process's own objects
            return f"objects {id(self.success)} {id(self.failure)}"

    @property
    def is_survival(self) -> bool:
        """Whether a trajectory succeeds by lasting the time limit (:meth:`survival`)."""
        return self.success is None

    @classmethod
    def ball(
        cls,
        position: Sequence[int],
        radius: float,
        *,
        target: Sequence[int] | Tensor,
        obs_dim: int | None = None,
        **kwargs: object,
    ) -> SuccessBoundary:
        """Success when ``‖obs[..., position] - target‖ <= radius`` (Euclidean).

        Args:
            position: observation indices of the controlled position (e.g. an end effector's x, y).
            radius: positive, finite radius, in the observation's units.
            target: observation indices holding the target (a sequence of ints), or a fixed
                target position (a float tensor of ``len(position)`` entries).
            obs_dim: the observation size D, when known: indices are then checked against it
                here (else at the first evaluation, against the observations' D).
            **kwargs: ``time_limit``, ``time_limit_s``, ``dt``, ``failure`` as in the constructor.
        """
        _checks.check_positive("radius", radius)
        if obs_dim is not None:
            _checks.check_positive_int("obs_dim", obs_dim)
        position = _indices("position", position, obs_dim)
        same = isinstance(target, Sequence) and not isinstance(target, (str, bytes))
        if same and sorted(target) == sorted(position):
            raise ValueError(
                f"target: expected other indices than position's {list(position)} (the "
                f"distance would always be 0, every state a success), got {list(target)}"
            )
        target_fn = _target_getter(target, len(position), obs_dim)

        def distance(obs: Tensor) -> Tensor:
            _check_indices("position", position, obs.shape[-1])
            return torch.linalg.vector_norm(obs[..., position] - target_fn(obs), dim=-1)

        return cls.within_distance(distance, radius, **kwargs)

    @classmethod
    def within_distance(
        cls, distance: Callable[[Tensor], Tensor], radius: float, **kwargs: object
    ) -> SuccessBoundary:
        """Success when ``distance(obs) <= radius``; ``distance``: ``[..., D] -> [...]``.

        A NaN distance (of finite observations: a bug in ``distance``) is a ``ValueError``,
        not a failure.
        """
        _checks.check_positive("radius", radius)
        if not callable(distance):
            raise TypeError(f"distance: expected a callable, got {type(distance).__name__}")

        def inside(obs: Tensor) -> Tensor:
            d = distance(obs)
            if isinstance(d, Tensor) and d.is_floating_point() and bool(torch.isnan(d).any()):
                raise ValueError(
                    f"distance: expected no NaN for finite observations, got "
                    f"{int(torch.isnan(d).sum())} NaN of {d.numel()}"
                )
            return d <= radius

        return cls(inside, **kwargs)  # type: ignore[arg-type]

    def success_over_time(self, observation: Tensor) -> Tensor:
        """Bool ``[..., T]``: in the success region at step ``t``, within the limit, not failed
        (for a survival boundary: ``t`` is the limit's last step, not failed)."""
        if self.is_survival:
            failed = self._failed_by_step(observation)
            steps = torch.arange(failed.shape[-1], device=failed.device)
            return (steps == self.time_limit - 1) & ~failed
        inside = self._evaluate(self.success, "success", observation)
        steps = torch.arange(inside.shape[-1], device=inside.device)
        inside = inside & (steps < self.time_limit)
        if self.failure is None:
            return inside
        return inside & ~self._failed_by_step(observation)

    def outcome(self, observation: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(success_over_time [..., T], success [...], failure [...])`` for ``[..., T, D]``."""
        success_over_time = self.success_over_time(observation)
        success = success_over_time.any(dim=-1)
        if self.failure is None:
            return success_over_time, success, torch.zeros_like(success)
        return success_over_time, success, self._failed_by_step(observation)[..., -1] & ~success

    def ended_over_time(self, observation: Tensor) -> Tensor:
        """Bool ``[..., T]``: the episode has ended before step ``t``.

        An episode ends at its first success or failure (the step after it is the first one
        marked) and at the time limit (steps ``t >= time_limit`` are marked), as a TorchRL
        ``done`` ends a rollout. Pass it as ``ended`` to
        :func:`~rcvae_torchrl.competency.decompose_uncertainty` (or as the ``"ended"`` entry of
        :class:`~rcvae_torchrl.competency.UncertaintyMetric`'s input) to measure the uncertainty
        of the episode, which has none left once it is over.
        """
        decided = self.success_over_time(observation)
        if self.failure is not None:
            decided = decided | self._failed_by_step(observation)
        over = decided.cummax(dim=-1).values
        ended = torch.zeros_like(over)
        ended[..., 1:] = over[..., :-1]
        steps = torch.arange(ended.shape[-1], device=ended.device)
        return ended | (steps >= self.time_limit)

    def _failed_by_step(self, observation: Tensor) -> Tensor:
        """Bool ``[..., T]``: a failure occurred at or before step ``t`` within the limit."""
        failed = self._evaluate(self.failure, "failure", observation)
        steps = torch.arange(failed.shape[-1], device=failed.device)
        failed = failed & (steps < self.time_limit)
        return failed.cummax(dim=-1).values

    @staticmethod
    def _evaluate(predicate: Predicate | None, name: str, observation: Tensor) -> Tensor:
        """The predicate's bool ``[..., T]`` on finite observations ``[..., T, D]`` (a NaN
        observation is a ``ValueError``, as in the uncertainty metric: it is neither in nor
        out of a region)."""
        _checks.check_tensor("observation", observation)
        _checks.check_min_rank("observation", observation, 2, "[..., T, D]")
        _checks.check_floating("observation", observation)
        _checks.check_finite("observation", observation)
        result = _called(
            predicate,
            name,
            observation,
            f"[..., T, D]: the model's state vector, its D = {observation.shape[-1]} dimensions "
            "read as observation[..., i], not the env's entries by name",
        )
        if not isinstance(result, Tensor) or result.shape != observation.shape[:-1]:
            got = tuple(result.shape) if isinstance(result, Tensor) else type(result).__name__
            raise ValueError(
                f"{name}: expected the predicate to map observations {tuple(observation.shape)} "
                f"to a bool tensor of shape {tuple(observation.shape[:-1])}, got {got}"
            )
        if result.dtype != torch.bool:
            raise TypeError(
                f"{name}: expected the predicate to return a bool tensor (e.g. distance <= r), "
                f"got dtype {result.dtype}"
            )
        if observation.shape[-2] > 1:
            _check_each_state_alone(predicate, name, observation, result)
        return result

    def __repr__(self) -> str:
        kind = ", survival" if self.is_survival else ""
        unit = "" if self.time_unit == "s" else f", time_unit={self.time_unit!r}"
        return f"{type(self).__name__}(time_limit={self.time_limit}, dt={self.dt}{unit}{kind})"


def _called(predicate: Predicate, name: str, observation: Tensor, reading: str) -> object:
    """``predicate(observation)``; its failure a ``ValueError`` naming the shape it failed on
    and how that shape is read (``reading``)."""
    try:
        return predicate(observation)
    except (AttributeError, IndexError, KeyError, TypeError, RuntimeError) as error:
        raise ValueError(
            f"{name}: the predicate failed on observations of shape {tuple(observation.shape)} "
            f"({reading}), with {type(error).__name__}: {error}"
        ) from error


def _check_each_state_alone(
    predicate: Predicate, name: str, observation: Tensor, result: Tensor
) -> None:
    """A predicate must judge each state alone (:data:`Predicate`): its results for the first
    trajectory of ``observation`` ``[..., T, D]`` must be those for the same states one at a
    time, ``[T, 1, D]``. One that combines states along the steps (a cumulative sum, a count)
    would judge the start states of a batch, or the training states the boundary is probed
    on, as one sequence, silently."""
    trajectories = observation.reshape(-1, *observation.shape[-2:])
    if not trajectories.shape[0]:  # an empty batch: nothing to judge
        return
    first = trajectories[0]
    steps = first.shape[0]
    alone = _called(
        predicate,
        name,
        first[:, None, :],
        "the states of one trajectory, each alone: it must take any batch shape [..., D], and "
        "a threshold per start state broadcast against the batch fails here",
    )
    along = result.reshape(-1, steps)[0]
    if isinstance(alone, Tensor) and alone.shape == (steps, 1) and torch.equal(alone[:, 0], along):
        return
    if isinstance(alone, Tensor) and alone.shape == (steps, 1):
        detail = f"{int((alone[:, 0] != along).sum())} of the {steps} states judged otherwise"
    else:
        shape = tuple(alone.shape) if isinstance(alone, Tensor) else type(alone).__name__
        detail = f"a result of shape {shape} for them, expected {(steps, 1)}"
    raise ValueError(
        f"{name}: expected a predicate of each state alone (obs [..., D] -> bool [...]), got "
        f"other results for the states of one trajectory judged one at a time "
        f"([{steps}, 1, D]) than along its steps ([..., {steps}, D]): {detail}. A predicate "
        "that combines states along an axis (a cumulative sum or a count over the steps), or "
        "reads a state's place in the batch (a threshold per start state), would judge a "
        "batch of start states, or the training states the boundary is checked on, as one "
        "sequence; put what it counts in the state (a transform on the env, such as TorchRL's "
        "RewardSum for the return or StepCounter for the steps) and judge that, and assess "
        "starts that need a threshold of their own one at a time, each with its boundary"
    )


def _time_limit_steps(steps: int | None, seconds: float | None, dt: float | None) -> int | float:
    """Resolve the time limit to a number of steps (``inf`` when none is given)."""
    if dt is not None:
        _checks.check_positive("dt", dt)
    if steps is not None and seconds is not None:
        raise ValueError("time_limit, time_limit_s: expected at most one of them, got both")
    if steps is not None:
        _checks.check_positive_int("time_limit", steps)
        return steps
    if seconds is None:
        return math.inf
    _checks.check_positive("time_limit_s", seconds)
    if dt is None:
        raise ValueError("dt: expected the step duration in seconds with time_limit_s, got None")
    steps = math.floor(seconds / dt + 1e-9)
    if steps < 1:
        raise ValueError(
            f"time_limit_s: expected at least one step of dt = {dt:g} s, got {seconds:g} s "
            "(no step would end within it)"
        )
    if seconds / dt - steps > 1e-6:
        warnings.warn(
            f"time_limit_s: {seconds:g} s is not a whole number of steps of dt = {dt:g} s; "
            f"the deadline is the end of step {steps} ({steps * dt:g} s). Give time_limit "
            "in steps, or a multiple of dt, to say which",
            UserWarning,
            stacklevel=3,
        )
    return steps


def _indices(name: str, indices: object, obs_dim: int | None) -> list[int]:
    """Observation indices: a non-empty sequence of distinct ints >= 0 (and < ``obs_dim``)."""
    if isinstance(indices, Tensor):
        if indices.is_floating_point() or indices.dtype == torch.bool or indices.ndim != 1:
            raise TypeError(f"{name}: expected a sequence of int indices, got {indices!r}")
        indices = indices.tolist()
    if isinstance(indices, (str, bytes)) or not isinstance(indices, Sequence):
        raise TypeError(f"{name}: expected a sequence of int indices, got {indices!r}")
    values = list(indices)
    if not values or not all(isinstance(i, int) and not isinstance(i, bool) for i in values):
        raise TypeError(f"{name}: expected a non-empty sequence of int indices, got {values!r}")
    if min(values) < 0 or len(set(values)) != len(values):
        raise ValueError(f"{name}: expected distinct indices >= 0, got {values}")
    if obs_dim is not None:
        _check_indices(name, values, obs_dim)
    return values


def _check_indices(name: str, indices: list[int], obs_dim: int) -> None:
    if max(indices) >= obs_dim:
        raise ValueError(
            f"{name}: expected observation indices in [0, {obs_dim}) (D = {obs_dim}), got {indices}"
        )


def _target_getter(
    target: Sequence[int] | Tensor, size: int, obs_dim: int | None
) -> Callable[[Tensor], Tensor]:
    """Target position from observation indices or a fixed tensor."""
    if isinstance(target, Tensor) and target.is_floating_point():
        if target.shape != (size,):
            raise ValueError(
                f"target: expected a fixed position of shape ({size},), got {tuple(target.shape)}"
            )
        _checks.check_finite("target", target)
        return lambda obs: target.to(obs)
    indices = _indices("target", target, obs_dim)
    if len(indices) != size:
        raise ValueError(f"target: expected {size} observation indices, got {indices}")

    def get(obs: Tensor) -> Tensor:
        _check_indices("target", indices, obs.shape[-1])
        return obs[..., indices]

    return get


def check_same_predicates(forecast: object, real: object, name: str = "outcomes") -> None:
    """Refuse to score a forecast against real episodes judged by other predicates:
    ``forecast`` a report, ``real`` the real outcomes, each with the ``predicates`` of the
    boundary that judged it (:attr:`SuccessBoundary.predicates`); ``name`` is the argument
    ``real`` came as. Not compared where either does not know them (``None``: outcomes judged
    by an env's flag or a function of one's own). Outcomes judged by a survival forecast's own
    predicates that do not say the survival's time limit (``survival_limit``, a record older
    than it) are refused too: their successes may have lasted another deadline."""
    mine, theirs = getattr(forecast, "predicates", None), getattr(real, "predicates", None)
    if mine is not None and mine == theirs and getattr(forecast, "survival", False):
        if getattr(real, "survival_limit", 0) is None:  # judged by it, its deadline not kept
            raise ValueError(
                f"{name}: the real episodes were judged by the forecast's survival boundary, but "
                "their record does not say for how long (written before RealOutcomes kept "
                "survival_limit), so whether they lasted the forecast's deadline is not known; "
                "judge kept episodes again with outcomes.judged_by(boundary), or run them again"
            )
    if mine is None or theirs is None or mine == theirs:
        return
    raise ValueError(
        f"{name}: the real episodes were judged by another boundary than the forecast's: its "
        f"predicates' code or values differ (digest {theirs[:12]}, the forecast's "
        f"{mine[:12]}; e.g. another radius), so the two answer different tasks; judge kept "
        "episodes again with outcomes.judged_by(boundary), or run real_outcomes with "
        "success=boundary.success_over_time, of the assessor's boundary"
    )


def hold_last_state(observation: Tensor) -> tuple[Tensor, Tensor]:
    """Episodes of several lengths, ``[..., T, S]`` padded with NaN after each one's last step
    (real episodes kept by ``real_outcomes``): ``(held, ran)``, each step after an episode's
    end holding its last state (a boundary's predicates see states, never NaN), and bool
    ``[..., T]`` of the steps it ran. Every episode must have run at least its first step."""
    ran = ~observation.isnan().any(-1)
    if not bool(ran[..., 0].all()):
        raise ValueError(
            "observation: expected every episode to have run at least one step (a finite "
            "first observation), got one that is NaN from its first step"
        )
    steps = torch.arange(observation.shape[-2], device=observation.device)
    last = torch.where(ran, steps, 0).cummax(-1).values
    held = observation.gather(-2, last.unsqueeze(-1).expand_as(observation))
    return held, ran
