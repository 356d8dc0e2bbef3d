"""Exploration policies for data collection: a base policy plus Gaussian noise, or uniform noise;
and how a stochastic TorchRL policy acts in the library's runs (:func:`acting`).

Actions stay inside the action bounds ``[low, high]`` (scalars or ``[A]``); take them from
your env's action spec with :func:`action_bounds`.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Iterator, Sequence

import torch
from tensordict.nn import ProbabilisticTensorDictModule, TensorDictModule
from torch import nn
from torchrl import modules as torchrl_modules
from torchrl.envs.utils import ExplorationType, exploration_type, set_exploration_type
from torchrl.modules.planners import MPCPlannerBase

from rcvae_torchrl import distributed
from rcvae_torchrl._checks import broadcasts_to, check_bounds, check_positive_int, check_seed
from rcvae_torchrl.fingerprint import SETTINGS

from .prepare import check_env

__all__ = [
    "GaussianExploration",
    "UniformRandomPolicy",
    "acting",
    "acting_record",
    "action_bounds",
    "check_same_acting",
    "check_same_agent",
    "exploration_mode",
    "held_generators",
    "planner_generators",
    "make_policy_module",
]


def exploration_mode(mode: ExplorationType | str | None = None) -> ExplorationType:
    """How a stochastic TorchRL policy (a ``ProbabilisticActor``) chooses its actions in the
    library's runs: ``mode`` where given (an ``ExplorationType`` or its name: ``"random"``,
    ``"deterministic"``, ``"mode"``, ``"mean"``, ``"median"``); else the caller's own, inside
    TorchRL's ``set_exploration_type(...)``; else ``RANDOM``, its samples, as TorchRL's
    collectors run it (and so as :func:`~rcvae_torchrl.data.collect_episodes` records the
    episodes a world model learns from). Outside any such setting a ``ProbabilisticActor``
    would act by its mean (a cheetah's gait: real success 0.85 by its mean, 0.39 sampled), so
    the library sets the mode wherever it runs a policy: collecting, imagining, real episodes.
    A policy that draws nothing (a planner, a deterministic network) acts the same in every
    mode."""
    if mode is None:
        mode = exploration_type() or ExplorationType.RANDOM
    if isinstance(mode, str) and not isinstance(mode, ExplorationType):
        names = [m.value for m in ExplorationType]
        if mode.lower() not in names:
            raise ValueError(f"exploration_type: expected one of {names}, got {mode!r}")
        mode = ExplorationType(mode.lower())
    if not isinstance(mode, ExplorationType):
        raise TypeError(
            "exploration_type: expected a torchrl ExplorationType, its name or None, got "
            f"{type(mode).__name__}"
        )
    return mode


@contextlib.contextmanager
def acting(
    mode: ExplorationType | str | None = None,
    seed: int | None = None,
    generators: Sequence[torch.Generator] = (),
) -> Iterator[str]:
    """Run a policy in :func:`exploration_mode` ``mode`` (yields its name, e.g. ``"random"``,
    for a record of how the agent acted). With a ``seed``, torch's global random stream, from
    which a ``ProbabilisticActor`` samples its actions, is seeded by it for the block and
    restored afterwards (those of CUDA devices already in use too), so that the same seed gives
    the same draws; and so are ``generators`` (e.g. a planner's, :func:`planner_generators`),
    each on a stream of its own."""
    resolved = exploration_mode(mode)
    with set_exploration_type(resolved):
        if seed is None:
            yield resolved.value
            return
        held = list(generators)
        for i, g in enumerate(held):
            if not isinstance(g, torch.Generator):
                raise TypeError(f"generators[{i}]: expected a torch.Generator, got {g!r}")
        states = [g.get_state() for g in held]
        in_use = torch.cuda.device_count() if torch.cuda.is_initialized() else 0
        with torch.random.fork_rng(devices=list(range(in_use))):
            torch.default_generator.manual_seed(seed)
            if in_use:  # not torch.manual_seed: it would also seed CUDA when first used
                torch.cuda.manual_seed_all(seed)
            for stream, g in enumerate(held, start=1):
                g.manual_seed(distributed.work_generator(abs(seed), stream).initial_seed())
            try:
                yield resolved.value
            finally:
                for g, state in zip(held, states, strict=True):
                    g.set_state(state)


def planner_generators(policy: object) -> list[torch.Generator]:
    """The generators a planner draws from (:func:`held_generators`) where ``policy`` is one
    (a TorchRL ``MPCPlannerBase``: the library's ``CEMPlanner``, TorchRL's ``CEMPlanner`` and
    ``MPPIPlanner``), else none: an exploration policy's own generator
    (``GaussianExploration``, ``UniformRandomPolicy``) runs on from where it was seeded, as in
    :func:`collect_episodes`."""
    return held_generators(policy) if isinstance(policy, MPCPlannerBase) else []


def held_generators(*owners: object) -> list[torch.Generator]:
    """The distinct torch generators a policy draws from: each owner's ``generator``
    attribute (the library's planners hold their candidates' there) and, for a planner that
    holds the env it plans in as ``env`` (TorchRL's ``MPCPlannerBase``), that env's (the
    library's model env draws its imagined steps from it)."""
    found: list[torch.Generator] = []
    for owner in owners:
        for holder in (owner, getattr(owner, "env", None)):
            g = getattr(holder, "generator", None) if holder is not None else None
            if isinstance(g, torch.Generator) and all(g is not h for h in found):
                found.append(g)
    return found


Bound = float | torch.Tensor


def action_bounds(env) -> tuple[torch.Tensor, torch.Tensor]:
    """``(low, high)`` ``[A]`` of a TorchRL env's bounded action spec."""
    check_env(env)
    space = getattr(env.action_spec, "space", None)
    low, high = getattr(space, "low", None), getattr(space, "high", None)
    if low is None or high is None:
        raise ValueError(
            f"env: expected a bounded continuous action spec, got {type(env.action_spec).__name__}"
        )
    shape = env.action_spec.shape[len(env.batch_size) :]
    return low.reshape(-1, *shape)[0].float(), high.reshape(-1, *shape)[0].float()


def check_same_acting(forecast: str | None, real: str | None, name: str = "outcomes") -> None:
    """Refuse to judge a forecast against real episodes whose policy acted otherwise: its
    imagined episodes with the policy in exploration mode ``forecast`` (a report's
    ``acting``), the real ones in ``real`` (the outcomes', or a forecast check's: ``name``
    says which argument). ``None`` on either side (not known, or an open-loop forecast) is not
    compared."""
    if forecast is None or real is None or forecast == real:
        return
    raise ValueError(
        f"{name}: the real episodes' policy acted {real!r} (its exploration type), the "
        f"forecast's imagined one {forecast!r}: a stochastic policy is another agent in each "
        "mode, and one is judged against the other; give CompetencyAssessor.assess and "
        f"real_outcomes the same exploration_type (e.g. exploration_type={forecast!r}), or "
        "run both inside one torchrl set_exploration_type(...)"
    )


#: TorchRL modules whose actions depend on the exploration type: a stochastic policy's
#: sampling module (inside a ``ProbabilisticActor``) and the exploration noise modules
_BY_MODE = (
    ProbabilisticTensorDictModule,
    *(
        getattr(torchrl_modules, f"{noise}{kind}")
        for noise in ("AdditiveGaussian", "EGreedy", "OrnsteinUhlenbeckProcess")
        for kind in ("Module", "Wrapper")
    ),
)


def acting_record(policy: object, mode: ExplorationType) -> str | None:
    """What a run records of how ``policy`` acted in exploration mode ``mode``: the mode's
    name where the policy's actions can depend on it (a module holding a TorchRL
    ``ProbabilisticActor`` or exploration-noise module, or a callable that is not a module,
    which may hold one), ``None`` for a module that holds none (a deterministic network, a
    planner): it acts the same in every mode, and its runs in two modes judge one agent."""
    mode = exploration_mode(mode)
    if not isinstance(policy, nn.Module):
        return mode.value
    return mode.value if any(isinstance(m, _BY_MODE) for m in policy.modules()) else None


def check_same_agent(forecast: object, real: object, name: str = "outcomes") -> None:
    """Refuse to judge a forecast against real episodes of another agent: ``forecast`` a
    report (or a forecast check), ``real`` the real outcomes (or a check) compared with it,
    each with its ``acting`` (:func:`check_same_acting`) and ``agent``
    (:func:`~rcvae_torchrl.fingerprint.agent_digest`); ``name`` is the argument ``real``
    came as. What either side does not know (``None``, or not there) is not compared. Two
    agents known by their weights that differ are refused; where either is known by its
    settings only (a module without weights), a difference is warned of, since a controller
    whose public attributes change as it acts (a step count) differs from itself."""
    check_same_acting(getattr(forecast, "acting", None), getattr(real, "acting", None), name)
    mine, theirs = getattr(forecast, "agent", None), getattr(real, "agent", None)
    if mine is None or theirs is None or mine == theirs:
        return
    if mine.startswith(SETTINGS) or theirs.startswith(SETTINGS):
        warnings.warn(
            f"{name}: the real episodes may be of another agent than the forecast's: "
            f"{_agent_words(theirs)} (digest {_short(theirs)}) against the forecast's "
            f"{_agent_words(mine)} (digest {_short(mine)}). A controller without weights is "
            "known by its class name and public attributes (its gains, say): if they changed "
            "on purpose, run real_outcomes with the policy given to CompetencyAssessor.assess; "
            "if they change as it acts, this is the same agent",
            UserWarning,
            stacklevel=3,
        )
        return
    raise ValueError(
        f"{name}: the real episodes are of another agent than the forecast's: their policy's "
        f"weights (digest {theirs[:12]}) are not those of the policy the forecast imagined "
        f"(digest {mine[:12]}); a forecast is judged against real episodes of the agent it "
        "forecast: run real_outcomes with the policy given to CompetencyAssessor.assess (or "
        "assess the agent whose episodes these are)"
    )


def _agent_words(agent: str) -> str:
    return "settings" if agent.startswith(SETTINGS) else "weights"


def _short(agent: str) -> str:
    return agent.removeprefix(SETTINGS)[:12]


def _is_std(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and 0 <= value < math.inf


def _bounds(low: Bound, high: Bound) -> tuple[torch.Tensor, torch.Tensor]:
    low, high = (
        torch.as_tensor(low, dtype=torch.float32),
        torch.as_tensor(high, dtype=torch.float32),
    )
    check_bounds("low, high", low, high, finite=True)
    return low, high


class GaussianExploration(nn.Module):
    """``clip(policy(obs) + noise_std * eps, low, high)``, with noise from its own generator.

    Args:
        policy: a module mapping observations ``[..., S]`` to actions ``[..., A]``.
        noise_std: std of the added Gaussian noise (>= 0).
        seed: seed of the noise generator (reproducible collection).
        low, high: the action bounds (default [-1, 1]; see :func:`action_bounds`).
    """

    def __init__(
        self,
        policy: nn.Module,
        noise_std: float,
        seed: int = 0,
        *,
        low: Bound = -1.0,
        high: Bound = 1.0,
    ) -> None:
        super().__init__()
        if not callable(policy):
            raise TypeError(
                f"policy: expected a module mapping observations to actions, got "
                f"{type(policy).__name__}"
            )
        if not _is_std(noise_std):
            raise ValueError(f"noise_std: expected a finite std >= 0, got {noise_std!r}")
        self.policy, self.noise_std = policy, float(noise_std)
        self.low, self.high = _bounds(low, high)
        self.generator = torch.Generator().manual_seed(check_seed("seed", seed))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        action = self.policy(observation)
        for name, bound in (("low", self.low), ("high", self.high)):  # the actions' width now
            if not broadcasts_to(bound.shape, action.shape):
                raise ValueError(
                    f"{name}: expected a bound that broadcasts to the policy's actions "
                    f"{tuple(action.shape)}, got shape {tuple(bound.shape)}"
                )
        noisy = action
        if self.noise_std > 0:  # no noise: no draw (the generator's stream is left as it is)
            noise = torch.randn(action.shape, generator=self.generator, dtype=action.dtype)
            noisy = action + self.noise_std * noise.to(action.device)
        return torch.clamp(noisy, self.low.to(noisy), self.high.to(noisy))


class UniformRandomPolicy(nn.Module):
    """Actions uniform in ``[low, high]`` (default ``[-1, 1]^A``), held for ``hold`` consecutive
    calls (smoother exploration).

    Holding an action for a few steps moves a system further than white noise does, so random
    episodes cover more of its state space.
    """

    def __init__(
        self,
        action_dim: int,
        hold: int = 5,
        seed: int = 0,
        *,
        low: Bound = -1.0,
        high: Bound = 1.0,
    ) -> None:
        super().__init__()
        check_positive_int("action_dim", action_dim)
        check_positive_int("hold", hold)
        self.action_dim, self.hold = action_dim, hold
        self.low, self.high = _bounds(low, high)
        self.generator = torch.Generator().manual_seed(check_seed("seed", seed))
        self._calls, self._action = 0, None

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        shape = (*observation.shape[:-1], self.action_dim)
        if self._action is None or self._action.shape != shape or self._calls % self.hold == 0:
            unit = torch.rand(shape, generator=self.generator)
            self._action = self.low + unit * (self.high - self.low)
        self._calls += 1
        return self._action.to(observation.device, observation.dtype)


def make_policy_module(policy: nn.Module) -> TensorDictModule:
    """Wire a tensor policy (``observation -> action``, an exploration policy, an agent) to
    TorchRL keys: reads ``"observation"``, writes ``"action"``."""
    return TensorDictModule(policy, in_keys=["observation"], out_keys=["action"])
