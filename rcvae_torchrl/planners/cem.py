"""CEM model-predictive control as a TorchRL policy (an :class:`MPCPlannerBase` subclass)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import torch
from tensordict import NestedKey, TensorDictBase, unravel_key
from torch import Tensor
from torchrl.data import TensorSpec
from torchrl.envs import EnvBase
from torchrl.modules.planners.common import MPCPlannerBase

from rcvae_torchrl._checks import check_bounds, check_positive, make_generator
from rcvae_torchrl.planners import _checks
from rcvae_torchrl.planners.evaluation import (
    ParticleReturns,
    env_returns,
    has_fast_path,
    rollout_returns,
    supports_success,
)
from rcvae_torchrl.planners.functional import (
    _draw_candidates,
    action_prior,
    cem_update,
    shift_plan,
)
from rcvae_torchrl.planners.reductions import OBJECTIVES, reduce_particles

__all__ = ["CEMPlanner", "make_cem_planner"]

Objective = Literal["mean", "quantile", "cvar", "success"]
Evaluation = Literal["auto", "env", "rollout"]
_EVALUATIONS = ("auto", "env", "rollout")


class CEMPlanner(MPCPlannerBase):
    """Cross-entropy-method MPC: plan H steps ahead in ``env``, act with the first step.

    Each call plans for every start state of the input tensordict (batch ``[*B]``) at once:
    ``iterations`` rounds of (sample ``num_candidates`` action sequences from a Gaussian, clamp to
    the action bounds, score them, refit the Gaussian to the ``top_k`` best with ``momentum``).
    The action written under ``action_key`` is the first step of the final mean.

    **Scoring.** :meth:`evaluate` returns per-particle returns ``[*B, C, P]`` through one seam:
    ``env.evaluate_action_sequences(td_start, actions, particles)`` when the env's class defines
    it (the fast path, see :mod:`rcvae_torchrl.planners.evaluation`), otherwise a rollout with
    ``env.step`` for H steps from ``[*B, C, P]`` copies of the start states. ``objective`` reduces
    particles to one score per candidate (:mod:`rcvae_torchrl.planners.reductions`): expected
    return, a lower quantile, CVaR, or P(success) with ties broken by expected return. Candidates
    with NaN or infinite returns are never elites.

    **Warm start and episode resets.** After a call the planner keeps the final mean shifted
    by one step (the new last step is the prior's), keyed by the shape ``[*B, H, *A]``, and
    the next call searches around it with the prior std, as PETS does: a kept std shrinks at
    every call's iterations, and a pendulum's planner that kept it searched within 0.005 of its
    plan after 5-10 calls, never finding the swing-up again (upright 0-17 % of the time against
    10-74 % without). The kept plan is dropped, per batch element, where the
    input's ``init_key`` entry (``"is_init"``, written by TorchRL's ``InitTracker`` transform) is
    True; wholly when the batch shape changes, or when :meth:`reset` is called. Without an
    ``InitTracker`` on the acting env, call :meth:`reset` between episodes (inside a TorchRL
    collector, which resets the env by itself, append an ``InitTracker`` to the env it steps).

    **Devices.** Planning runs on ``env``'s device. An input on another device (a CPU simulator
    acting with a world model on a GPU) is copied there for the plan, and the action is written
    back on the input's own device.

    Args:
        env: a TorchRL env with ``batch_size=()`` and ``batch_locked=False`` (e.g. a
            ``ModelBasedEnvBase``), used only to score plans.
        horizon: H, planning horizon in steps.
        num_candidates: C, action sequences sampled per iteration and start state.
        top_k: elites per iteration, ``1 <= top_k <= num_candidates``.
        iterations: CEM iterations per call.
        particles: P, rollouts per candidate (stochastic or ensemble models).
        momentum: α in [0, 1): ``new = α·old + (1 − α)·elite_stat`` for mean and std.
        objective: ``"mean"``, ``"quantile"``, ``"cvar"`` or ``"success"``.
        risk_level: the quantile level, or the CVaR fraction of worst particles.
        init_std: prior std (scalar or ``[*A]``); default ``(high − low) / 4`` (1 if unbounded).
        warm_start: keep the shifted mean between calls (False: start every call from the
            prior).
        discount: γ for the rollout path (the fast path defines its own returns).
        evaluation: ``"auto"`` (fast path if the env's class has it), ``"env"`` or ``"rollout"``.
        action_key: default ``env.action_key`` (nested keys work).
        reward_key: default ``env.reward_key`` (rollout path).
        success_key: success flag under ``"next"`` for ``objective="success"`` on the rollout path.
        init_key: the episode-start flag read from the input (``InitTracker``'s ``"is_init"``).
        generator: random source of the candidates; or ``seed`` to make one.
        proposal: optional prior plan: a callable mapping the input tensordict ``[*B]`` to an
            action sequence ``[*B, H, *A]`` (e.g. a policy rolled out in the model). It joins
            every iteration's candidates (replacing one sample), so it is kept whenever it
            scores among the elites: policy-guided CEM, never worse than the prior under the
            model's own scores.
        proposal_std: with a proposal, start each call's search at the proposed plan with
            std ``proposal_std`` × the prior std (a local refinement of the policy's plan)
            instead of at the kept warm-start plan; ``None`` (default): the proposal only joins
            the candidates.

    Example:
        >>> from torchrl.envs import PendulumEnv
        >>> env = PendulumEnv()
        >>> planner = CEMPlanner(env, horizon=5, num_candidates=32, top_k=4, iterations=2, seed=0)
        >>> rollout = env.rollout(3, planner)
        >>> rollout["action"].shape, bool((rollout["action"].abs() <= 2.0).all())
        (torch.Size([3, 1]), True)
    """

    def __init__(
        self,
        env: EnvBase,
        horizon: int,
        *,
        num_candidates: int = 200,
        top_k: int = 20,
        iterations: int = 5,
        particles: int = 1,
        momentum: float = 0.1,
        objective: Objective = "mean",
        risk_level: float = 0.1,
        init_std: float | Tensor | None = None,
        warm_start: bool = True,
        discount: float = 1.0,
        evaluation: Evaluation = "auto",
        action_key: NestedKey | None = None,
        reward_key: NestedKey | None = None,
        success_key: NestedKey | None = None,
        init_key: NestedKey = "is_init",
        generator: torch.Generator | None = None,
        seed: int | None = None,
        proposal: Callable[[TensorDictBase], Tensor] | None = None,
        proposal_std: float | None = None,
    ) -> None:
        if not isinstance(env, EnvBase):
            raise TypeError(f"env: expected a TorchRL EnvBase, got {type(env).__name__}")
        if env.batch_locked:
            raise ValueError(
                f"env: expected an env that steps any batch of imagined states (a world model, "
                f"e.g. rcvae_torchrl.make_rcvae_env(ensemble, real_env, ...)), got "
                f"{type(env).__name__}, whose batch is locked (a real env: plan in its world "
                "model, act in the real env)"
            )
        _check_arguments(horizon, num_candidates, top_k, iterations, particles, momentum)
        _check_objective(objective, risk_level)
        _checks.check_unit_interval("discount", discount, include_zero=False)
        _checks.check_bool("warm_start", warm_start)
        action_key = unravel_key(env.action_key if action_key is None else action_key)
        actions = env.full_action_spec.keys(True, True)
        if action_key not in actions:
            raise ValueError(
                f"action_key: expected one of the env's action keys {sorted(map(str, actions))}, "
                f"got {action_key!r}"
            )
        super().__init__(env=env, action_key=action_key)
        self.action_spec = _continuous_action_spec(env, action_key)
        self.horizon, self.num_candidates, self.top_k = horizon, num_candidates, top_k
        self.iterations, self.particles, self.momentum = iterations, particles, momentum
        self.objective, self.risk_level, self.warm_start = objective, risk_level, warm_start
        self.action_key, self.init_key = action_key, unravel_key(init_key)
        self.evaluation = _resolve_evaluation(env, evaluation, discount, objective, success_key)
        if reward_key is None and self.evaluation == "rollout":
            reward_key = env.reward_key
        self.reward_key = None if reward_key is None else unravel_key(reward_key)
        self.success_key, self.discount = success_key, discount
        self.generator = make_generator(generator, seed, env.device)
        self._register_bounds(init_std)
        self._plan: tuple[Tensor, Tensor] | None = None
        if proposal is not None and not callable(proposal):
            raise TypeError(f"proposal: expected a callable or None, got {type(proposal).__name__}")
        if proposal_std is not None:
            check_positive("proposal_std", proposal_std)
        self.proposal, self.proposal_std = proposal, proposal_std

    def _register_bounds(self, init_std: float | Tensor | None) -> None:
        """Buffers ``low``, ``high`` (bounds), ``prior_mean``, ``prior_std``, all ``[*A]``."""
        low = self.action_spec.space.low.to(self.action_spec.dtype).clone()
        high = self.action_spec.space.high.to(self.action_spec.dtype).clone()
        check_bounds("action_spec (its low and high)", low, high)
        prior_mean, prior_std = action_prior(low, high, init_std)
        self.register_buffer("low", low, persistent=False)
        self.register_buffer("high", high, persistent=False)
        self.register_buffer("prior_mean", prior_mean, persistent=False)
        self.register_buffer("prior_std", prior_std, persistent=False)

    @property
    def action_shape(self) -> torch.Size:
        """A, the shape of one action."""
        return self.action_spec.shape

    @property
    def plan(self) -> tuple[Tensor, Tensor] | None:
        """The kept warm-start plan ``(mean, std)``, each ``[*B, H, *A]`` (copies; the std is
        the prior's), or ``None``."""
        if self._plan is None:
            return None
        return self._plan[0].clone(), self._plan[1].clone()

    def reset(self) -> None:
        """Forget the kept plan: the next call starts from the prior."""
        self._plan = None

    def initial_plan(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor]:
        """The plan a call on ``tensordict`` starts from: the kept one, or the prior.

        Returns ``(mean, std)``, each ``[*B, H, *A]``; elements flagged by ``init_key`` get the
        prior.
        """
        shape = (*tensordict.batch_size, self.horizon, *self.action_shape)
        prior = self.prior_mean.expand(shape), self.prior_std.expand(shape)
        kept = self._plan
        stale = kept is None or kept[0].shape != shape or kept[0].device != self.prior_mean.device
        if not self.warm_start or stale:
            return prior[0].clone(), prior[1].clone()
        is_init = tensordict.get(self.init_key, None)
        if is_init is None:
            return kept[0].clone(), kept[1].clone()
        fresh = is_init.reshape(*tensordict.batch_size, -1).any(-1)
        fresh = fresh.reshape(*fresh.shape, *([1] * (1 + len(self.action_shape))))
        return torch.where(fresh, prior[0], kept[0]), torch.where(fresh, prior[1], kept[1])

    def evaluate(self, td_start: TensorDictBase, actions: Tensor) -> ParticleReturns:
        """Per-particle returns of ``actions`` ``[*B, C, H, *A]`` from ``td_start`` ``[*B]``.

        Returns :class:`ParticleReturns` with ``returns`` ``[*B, C, P]`` (and ``success`` when
        ``objective="success"``).
        """
        self._check_actions(td_start, actions)
        want_success = self.objective == "success"
        if self.evaluation == "env":
            return env_returns(
                self.env, td_start, actions, self.particles, return_success=want_success
            )
        return rollout_returns(
            self.env,
            td_start,
            actions,
            self.particles,
            action_key=self.action_key,
            reward_key=self.reward_key,
            discount=self.discount,
            success_key=self.success_key if want_success else None,
        )

    def score(self, td_start: TensorDictBase, actions: Tensor) -> Tensor:
        """Objective value of each candidate: ``[*B, C]``, higher is better, NaN if non-finite."""
        out = self.evaluate(td_start, actions)
        return reduce_particles(out.returns, self.objective, self.risk_level, out.success)

    def optimize(
        self, tensordict: TensorDictBase, mean: Tensor, std: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Run the CEM iterations from ``(mean, std)`` ``[*B, H, *A]``; return the final plan."""
        self._check_plan(tensordict, mean, std)
        prior = self._proposed_plan(tensordict, mean.shape)
        if prior is not None and self.proposal_std is not None:
            mean, std = prior.clone(), (self.prior_std * self.proposal_std).expand_as(std).clone()
        scored = None  # [*B]: some candidate of the start state had a finite score
        for _ in range(self.iterations):
            candidates = _draw_candidates(
                mean, std, self.num_candidates, self.low, self.high, self.generator
            )
            if prior is not None:
                candidates.select(tensordict.batch_dims, -1).copy_(prior)
            scores = self.score(tensordict, candidates)
            finite = torch.isfinite(scores).any(dim=-1)
            scored = finite if scored is None else scored | finite
            mean, std = cem_update(mean, std, candidates, scores, self.top_k, self.momentum)
        _check_scored(scored)
        return mean, std

    def _proposed_plan(self, tensordict: TensorDictBase, shape: torch.Size) -> Tensor | None:
        """The proposal's plan ``[*B, H, *A]`` clamped to the bounds, or None."""
        if self.proposal is None:
            return None
        plan = self.proposal(tensordict)
        if not isinstance(plan, Tensor) or plan.shape != shape:
            got = tuple(plan.shape) if isinstance(plan, Tensor) else type(plan).__name__
            raise ValueError(f"proposal: expected a plan of shape {tuple(shape)}, got {got}")
        if not bool(torch.isfinite(plan).all()):
            raise ValueError(
                "proposal: expected a finite plan, got non-finite actions at "
                f"{torch.nonzero(~torch.isfinite(plan))[:3].tolist()} (first 3 indices)"
            )
        return torch.maximum(torch.minimum(plan, self.high), self.low)

    def planning(self, tensordict: TensorDictBase) -> Tensor:
        """Plan from each start state of ``tensordict`` ``[*B]``; return actions ``[*B, *A]``."""
        with torch.no_grad():
            self._check_state(tensordict)
            mean, std = self.optimize(tensordict, *self.initial_plan(tensordict))
            if self.warm_start:
                time_dim = tensordict.batch_dims
                self._plan = (
                    shift_plan(mean, self.prior_mean, time_dim),
                    self.prior_std.expand_as(std).clone(),
                )
        return mean.select(tensordict.batch_dims, 0)

    def forward(
        self,
        tensordict: TensorDictBase,
        tensordict_out: TensorDictBase | None = None,
        **kwargs,
    ) -> TensorDictBase:
        """Plan from ``tensordict`` (on any device) and write the action into it (or into
        ``tensordict_out``), on the input's device."""
        here, there = self.prior_mean.device, _device_of(tensordict)
        if there is None or there == here:
            return super().forward(tensordict, tensordict_out, **kwargs)
        if "params" in kwargs or "vmap" in kwargs:
            raise ValueError("CEMPlanner does not support functional calls (params, vmap)")
        action = self.action_spec.project(self.planning(tensordict.to(here)))
        return self._write_to_tensordict(tensordict, (action.to(there),), tensordict_out)

    def _check_actions(self, td_start: TensorDictBase, actions: Tensor) -> None:
        batch, action_shape = tuple(td_start.batch_size), tuple(self.action_shape)
        rank = len(batch) + 2 + len(action_shape)
        if (
            actions.ndim != rank
            or tuple(actions.shape[: len(batch)]) != batch
            or tuple(actions.shape[rank - len(action_shape) :]) != action_shape
        ):
            raise ValueError(
                f"actions: expected shape [*B, C, H, *A] with B = {batch} and "
                f"A = {action_shape}, got {tuple(actions.shape)}"
            )

    def _check_plan(self, tensordict: TensorDictBase, mean: Tensor, std: Tensor) -> None:
        """A plan to start from: ``[*B, H, *A]`` of this planner's H, a finite mean and a
        positive finite std (a NaN mean would otherwise be blamed on the model)."""
        shape = (*tensordict.batch_size, self.horizon, *self.action_shape)
        for name, value in (("mean", mean), ("std", std)):
            if not isinstance(value, Tensor) or tuple(value.shape) != shape:
                got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
                raise ValueError(
                    f"{name}: expected a plan [*B, H, *A] = {shape} (H: the planning horizon), "
                    f"got {got}"
                )
            _checks.check_finite(name, value)
        if not bool((std > 0).all()):
            raise ValueError(f"std: expected positive values, got a minimum of {std.min().item()}")

    def _check_state(self, tensordict: TensorDictBase) -> None:
        keys = {*self.in_keys, *self.env.state_spec.keys(True, True)}
        for key in keys:
            value = tensordict.get(key, None)
            if isinstance(value, Tensor):
                _checks.check_finite(f"tensordict[{key!r}]", value)


def _device_of(tensordict: TensorDictBase) -> torch.device | None:
    """The device of ``tensordict``, or of its first tensor when it has none."""
    if tensordict.device is not None:
        return tensordict.device
    first = next(iter(tensordict.values(True, True)), None)
    return first.device if isinstance(first, Tensor) else None


def _check_scored(scored: Tensor) -> None:
    """Refuse a plan that no finite score chose: it would be the prior's, returned silently."""
    if not bool(scored.all()):
        index = (~scored).nonzero().tolist()
        raise FloatingPointError(
            f"CEMPlanner: every candidate plan of {len(index)} of {scored.numel()} start "
            f"state(s) (batch indices {index[:5]}) scored NaN or ±inf in every iteration, so "
            f"no plan was chosen; the model (its weights or normaliser), the reward or the "
            f"discount gives non-finite returns"
        )


def _check_arguments(
    horizon: int, num_candidates: int, top_k: int, iterations: int, particles: int, momentum: float
) -> None:
    _checks.check_positive_int("horizon", horizon)
    _checks.check_positive_int("num_candidates", num_candidates)
    _checks.check_top_k(top_k, num_candidates)
    _checks.check_positive_int("iterations", iterations)
    _checks.check_positive_int("particles", particles)
    _checks.check_momentum(momentum)


def _check_objective(objective: str, risk_level: float) -> None:
    _checks.check_choice("objective", objective, OBJECTIVES)
    _checks.check_unit_interval("risk_level", risk_level, include_zero=objective != "cvar")


def _continuous_action_spec(env: EnvBase, action_key: NestedKey) -> TensorSpec:
    if tuple(env.batch_size) != ():
        raise ValueError(f"env.batch_size: expected (), got {tuple(env.batch_size)}")
    spec = env.full_action_spec[action_key]
    if not spec.dtype.is_floating_point or not hasattr(spec.space, "low"):
        raise TypeError(
            f"env.full_action_spec[{action_key!r}]: expected a continuous (Bounded or Unbounded) "
            f"spec, got {type(spec).__name__} of dtype {spec.dtype}"
        )
    return spec


def _resolve_evaluation(
    env: EnvBase, evaluation: str, discount: float, objective: str, success_key: NestedKey | None
) -> str:
    _checks.check_choice("evaluation", evaluation, _EVALUATIONS)
    if evaluation == "auto":
        evaluation = "env" if has_fast_path(env) else "rollout"
    if evaluation == "env" and not callable(getattr(env, "evaluate_action_sequences", None)):
        raise ValueError(
            f"evaluation: 'env' needs an env with evaluate_action_sequences, "
            f"got {type(env).__name__} without it"
        )
    if evaluation == "env" and discount != 1.0:
        raise ValueError(
            f"discount: expected 1.0 when the env scores plans itself (evaluation='env'), got "
            f"{discount}; pass evaluation='rollout' to discount"
        )
    if objective == "success":
        _check_success_source(env, evaluation, success_key)
    return evaluation


def _check_success_source(env: EnvBase, evaluation: str, success_key: NestedKey | None) -> None:
    if evaluation == "env" and not supports_success(env):
        raise ValueError(
            f"objective: 'success' needs {type(env).__name__}.evaluate_action_sequences to "
            f"accept return_success=True, got a method without it"
        )
    if evaluation == "rollout" and success_key is None:
        raise ValueError(
            "success_key: expected the key of a success flag (under 'next') for "
            "objective='success' on the rollout path, got None"
        )


def make_cem_planner(env: EnvBase, horizon: int, **kwargs) -> CEMPlanner:
    """Build a :class:`CEMPlanner` for ``env``, wiring the success flag when it can be found.

    For ``objective="success"`` on an env without a success-aware fast path and no
    ``success_key``, the env's observation or done entry whose key ends in ``"success"`` is used.
    Other keyword arguments go to :class:`CEMPlanner` unchanged.
    """
    evaluation = kwargs.get("evaluation", "auto")
    scores_itself = evaluation == "env" or (evaluation == "auto" and has_fast_path(env))
    wants_key = kwargs.get("objective") == "success" and kwargs.get("success_key") is None
    if wants_key and not (scores_itself and supports_success(env)):
        kwargs["success_key"] = _find_success_key(env)
    return CEMPlanner(env, horizon, **kwargs)


def _find_success_key(env: EnvBase) -> NestedKey | None:
    keys = [*env.observation_spec.keys(True, True), *env.done_keys]
    found = [key for key in keys if (key if isinstance(key, str) else key[-1]) == "success"]
    return found[0] if found else None
