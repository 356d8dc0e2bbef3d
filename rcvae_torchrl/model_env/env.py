"""``RCVAEEnsembleEnv``: a TorchRL ``ModelBasedEnvBase`` over a trained :class:`RCVAEEnsemble`."""

from __future__ import annotations

from typing import Literal

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.model_based import ModelBasedEnvBase

from rcvae_torchrl.model_env import _checks
from rcvae_torchrl.model_env.imagine import ImaginePolicy, imagine_rollouts
from rcvae_torchrl.model_env.propagation import Propagation, make_step_module
from rcvae_torchrl.model_env.scoring import score_action_sequences
from rcvae_torchrl.model_env.specs import (
    ACTION_KEY,
    HIDDEN_KEY,
    LATENT_KEY,
    MEMBER_KEY,
    OBSERVATION_KEY,
    REWARD_KEY,
    SUCCESS_KEY,
    ModelEnvSpecs,
    model_env_specs,
)
from rcvae_torchrl.model_env.task import RewardFn, SuccessFn, task_reward, task_success
from rcvae_torchrl.models import RCVAEEnsemble, init_model_state

__all__ = ["MemberAssignment", "RCVAEEnsembleEnv"]

MemberAssignment = Literal["round_robin", "random"]
_STATE_KEYS = (OBSERVATION_KEY, ACTION_KEY, HIDDEN_KEY, LATENT_KEY, MEMBER_KEY)


class RCVAEEnsembleEnv(ModelBasedEnvBase):
    """The RCVAE ensemble as a TorchRL environment (``batch_size=()``: any leading batch).

    A step samples s_{t+1} for every particle of the input (particles are batch elements),
    then scores it with the task functions: ``"reward"`` = ``reward_fn(s_{t+1}, a_t)``,
    ``"success"`` = ``success_fn(s_{t+1})``; success sets ``"terminated"`` and ``"done"`` when
    ``terminate_on_success`` (default, as the real Pusher). ``"truncated"`` is always False: the
    model has no clock (append a ``StepCounter(max_steps)`` transform for a time limit).

    **Keys.** ``"observation"`` ``[*B, S]``, ``"action"`` ``[*B, A]``, ``"reward"`` ``[*B, 1]``,
    ``"success"`` / ``"done"`` / ``"terminated"`` / ``"truncated"`` bool ``[*B, 1]`` and the
    model state: ``("rcvae", "hidden")`` (``[*B, H]`` for TS-∞, every member's ``[*B, E, H]``
    for ``"ts1"`` and ``"mean"``), ``("rcvae", "latent")`` ``[*B, Z]`` (z of the last step, 0 at
    reset) and ``"member"`` int64 ``[*B]`` (the member a particle follows; for ``"ts1"`` the one
    drawn at the last step; absent for ``"mean"``).

    **Trajectory sampling** (Chua et al. 2018, PETS; see
    :mod:`rcvae_torchrl.model_env.propagation`): ``"ts_inf"`` (TS-∞, default) keeps the member
    assigned at reset, ``"ts1"`` redraws it every step, ``"mean"`` steps deterministically with
    the mean of the members' noise-free predictions.

    **Reset.** ``_reset`` returns a new tensordict. Start observations come from, in order:
    the input's ``"observation"`` (e.g. the real env's current state; the particle batch is
    the input's batch), else ``start_states`` ``[K, S]`` sampled uniformly with the env's
    generator, else a ``ValueError``. Auto-resets of done particles inside
    ``rollout(..., break_when_any_done=False)`` (TorchRL's planners run it so) go through
    :meth:`maybe_reset`: without ``start_states`` the particles restart from their own last
    observation. Through a ``TransformedEnv``, TorchRL strips such resets down to ``"_reset"``,
    so there they need ``start_states``. The model state restarts at h_0 = 0;
    members are taken from the input's ``"member"`` if given (TS-∞), else assigned round-robin
    over the flattened batch (balanced: no padding in the member-major layout) or at random
    (``member_assignment``). A step whose input has no model state (e.g. a tensordict from the
    real env, as TorchRL's planners pass it) starts it the same way: the planners plan from the
    real state with a fresh recurrent state, as the model was trained (windows start at h_0).
    TorchRL's ``rollout`` stops the whole batch at the first done unless
    ``break_when_any_done=False``; :meth:`imagine` has no such coupling.

    **Fast paths.** :meth:`imagine` (rollouts ``[E, N, *B, T]`` for the competency metrics) and
    :meth:`evaluate_action_sequences` (the planner seam of :mod:`rcvae_torchrl.planners`) skip
    TensorDict and TorchRL bookkeeping and step member-major tensors directly.

    Args:
        ensemble: the trained world model (its device is the env's).
        reward_fn: ``(observation_next [..., S], action [..., A]) -> [..., 1]``, e.g.
            :func:`rcvae_torchrl.envs.pusher_reward`.
        success_fn: ``observation [..., S] -> [...]`` bool, e.g.
            :func:`rcvae_torchrl.envs.pusher_success`.
        real_env: copy the task specs from it (:meth:`set_specs_from_env`); without it,
            defaults (actions bounded in [-1, 1]).
        trajectory_sampling: ``"ts_inf"``, ``"ts1"`` or ``"mean"``.
        member_assignment: ``"round_robin"`` or ``"random"`` members at reset.
        terminate_on_success: success ends an imagined episode (mirror the real env's setting).
        start_states: ``[K, S]`` start observations for resets without an ``"observation"``.
        generator: source of all randomness of the env (sampling noise, members, start
            states); or ``seed`` to make one. ``set_seed`` reseeds it. ``None``: global RNG.
        validate: check shapes, dtypes and finiteness of the inputs at every step.
        requires_grad: let ``step`` record the autograd graph (off: rollouts are for
            planning and evaluation, and a graph over a whole rollout costs memory).
        compile_scoring: :meth:`evaluate_action_sequences` runs the ``"ts_inf"`` rollout (all
            H steps: model, constraint, reward, success) as one ``torch.compile``-d function
            (:func:`~rcvae_torchrl.model_env.scoring.compiled_rollout`): faster once compiled,
            which takes tens of seconds to minutes on a CPU per new horizon or batch size; the
            same samples up to float rounding. Other modes and ``step`` are unaffected.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from rcvae_torchrl.envs import pusher_reward, pusher_success
        >>> from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
        >>> model = RCVAEEnsemble(RCVAEConfig(14, 2, hidden_dim=16, mlp_dim=16), ensemble_size=5)
        >>> starts = torch.rand(100, 14) * 0.2 - 0.1
        >>> env = RCVAEEnsembleEnv(
        ...     model, pusher_reward, pusher_success, start_states=starts, seed=0
        ... )
        >>> td = env.reset(TensorDict(batch_size=[8]))
        >>> td["member"].tolist()
        [0, 1, 2, 3, 4, 0, 1, 2]
        >>> rollout = env.rollout(6, tensordict=td, auto_reset=False, break_when_any_done=False)
        >>> rollout["next", "observation"].shape
        torch.Size([8, 6, 14])
        >>> env.imagine(starts[:3], torch.zeros(3, 6, 2), samples_per_member=4).batch_size
        torch.Size([5, 4, 3, 6])
        >>> env.evaluate_action_sequences(td, torch.zeros(8, 30, 15, 2), particles=10).shape
        torch.Size([8, 30, 10])
    """

    def __init__(
        self,
        ensemble: RCVAEEnsemble,
        reward_fn: RewardFn,
        success_fn: SuccessFn,
        *,
        real_env: EnvBase | None = None,
        trajectory_sampling: Propagation = "ts_inf",
        member_assignment: MemberAssignment = "round_robin",
        terminate_on_success: bool = True,
        start_states: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        seed: int | None = None,
        validate: bool = True,
        requires_grad: bool = False,
        compile_scoring: bool = False,
    ) -> None:
        _checks.check_arguments(
            ensemble, reward_fn, success_fn, trajectory_sampling, member_assignment
        )
        device = ensemble.device
        generator = _checks.make_generator(generator, seed, device)
        transition = make_step_module(
            ensemble, trajectory_sampling, generator=generator, validate=validate
        )
        super().__init__(transition, device=device, batch_size=torch.Size([]))
        self.ensemble = ensemble
        self.reward_fn, self.success_fn = reward_fn, success_fn
        self.trajectory_sampling: Propagation = trajectory_sampling
        self.member_assignment: MemberAssignment = member_assignment
        self.terminate_on_success = bool(terminate_on_success)
        self.requires_grad = bool(requires_grad)
        self.compile_scoring = bool(compile_scoring)
        self.generator = generator
        self.start_states: torch.Tensor | None = None
        self.set_start_states(start_states)
        if real_env is None:
            self._apply_specs(model_env_specs(ensemble, trajectory_sampling, device))
        else:
            self.set_specs_from_env(real_env)

    # ----------------------------------------------------------------- configuration
    def set_specs_from_env(self, env: EnvBase) -> None:
        """Copy the task specs (observation, success, action, reward, done) from ``env``.

        The model state is added; the real env's other observation entries are left out
        (see :mod:`rcvae_torchrl.model_env.specs`). Raises if the shapes do not match the
        ensemble.
        """
        self._apply_specs(
            model_env_specs(self.ensemble, self.trajectory_sampling, self.device, env)
        )

    def _apply_specs(self, specs: ModelEnvSpecs) -> None:
        self.observation_spec = specs.observation
        self.action_spec = specs.action
        self.reward_spec = specs.reward
        self.full_done_spec = specs.done
        self.state_spec = specs.state

    def set_start_states(self, start_states: torch.Tensor | None) -> None:
        """Set (or clear, with ``None``) the start observations ``[K, S]`` sampled at reset."""
        if start_states is not None:
            _checks.check_start_states(self.ensemble, start_states)
            start_states = start_states.detach().to(self.device).clone()
        self.start_states = start_states

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            return
        if self.generator is None:
            self.generator = torch.Generator(device=self.device)
            if hasattr(self.world_model, "generator"):
                self.world_model.generator = self.generator
        self.generator.manual_seed(int(seed))

    # ----------------------------------------------------------------- EnvBase
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        batch = self.batch_size if tensordict is None else tensordict.batch_size
        given = None if tensordict is None else tensordict.get(OBSERVATION_KEY, None)
        if given is None:
            observation = self._sample_start_states(batch)
        else:
            _checks.check_observation(self.ensemble, "tensordict['observation']", given)
            observation = given.clone()
        member = None if tensordict is None else tensordict.get(MEMBER_KEY, None)
        state = self._initial_state(observation, member)
        flag = torch.zeros(*batch, 1, dtype=torch.bool, device=self.device)
        state.set(SUCCESS_KEY, task_success(self.success_fn, observation))
        for key in self.done_keys:
            state.set(key, flag.clone())
        return state

    def maybe_reset(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Reset the done particles of ``tensordict`` (TorchRL's auto-reset inside rollouts).

        With ``start_states``, as any env: done particles restart from sampled start states.
        Without, they restart from their own last observation (fresh model state): the model
        has no initial-state distribution of its own, and TorchRL's planners mask the rewards
        after a done anyway, so their rollouts through an imagined success keep working.
        """
        if self.start_states is not None or not self.any_done(tensordict):
            return super().maybe_reset(tensordict)
        return self.reset(tensordict)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = _STATE_KEYS if self.trajectory_sampling != "mean" else _STATE_KEYS[:-1]
        state = tensordict.select(*keys, strict=False)
        if OBSERVATION_KEY not in state.keys():
            raise KeyError(f"RCVAEEnsembleEnv.step: the input has no {OBSERVATION_KEY!r} entry.")
        if HIDDEN_KEY not in state.keys(include_nested=True):
            start = self._initial_state(state.get(OBSERVATION_KEY), state.get(MEMBER_KEY, None))
            state.update(start.exclude(OBSERVATION_KEY))
        with torch.set_grad_enabled(self.requires_grad and torch.is_grad_enabled()):
            out = self.world_model(state)
        observation = out.get(OBSERVATION_KEY)
        success = task_success(self.success_fn, observation)
        terminated = success if self.terminate_on_success else torch.zeros_like(success)
        result = out.select(OBSERVATION_KEY, "rcvae", MEMBER_KEY, strict=False)
        result.update(
            {
                REWARD_KEY: task_reward(self.reward_fn, observation, out.get(ACTION_KEY)),
                SUCCESS_KEY: success,
                "terminated": terminated,
                "truncated": torch.zeros_like(terminated),
                "done": terminated.clone(),
            }
        )
        return result

    def _initial_state(
        self, observation: torch.Tensor, member: torch.Tensor | None
    ) -> TensorDictBase:
        """Model state at h_0 for ``observation [*B, S]`` (with ``member [*B]`` if given)."""
        ts_inf = self.trajectory_sampling == "ts_inf"
        state = init_model_state(
            self.ensemble,
            observation,
            trajectory_sampling="ts_inf" if ts_inf else "ts1",
            member=member if (member is not None and ts_inf) else self.member_assignment,
            generator=self.generator,
        )
        return state if self.trajectory_sampling != "mean" else state.exclude(MEMBER_KEY)

    def _sample_start_states(self, batch: torch.Size) -> torch.Tensor:
        if self.start_states is None:
            raise ValueError(
                "RCVAEEnsembleEnv.reset: no start observations. Pass a tensordict holding "
                f"{OBSERVATION_KEY!r} [*B, {self.ensemble.config.obs_dim}] (e.g. the real env's "
                "current state), or give the env start_states [K, S] to sample from (needed "
                "for resets that only hold '_reset', e.g. auto-resets inside rollouts)."
            )
        index = torch.randint(
            self.start_states.shape[0], batch, generator=self.generator, device=self.device
        )
        return self.start_states[index]

    # ----------------------------------------------------------------- fast paths
    def imagine(
        self,
        start: TensorDictBase | torch.Tensor,
        actions: torch.Tensor | None = None,
        *,
        policy: ImaginePolicy | None = None,
        horizon: int | None = None,
        samples_per_member: int = 1,
        generator: torch.Generator | None = None,
        chunk_size: int | None = 1024,
    ) -> TensorDictBase:
        """Imagined rollouts ``[E, N, *B, T]`` from start states, open or closed loop.

        Always TS-∞ (sample ``(m, n, b)`` follows member m), whatever ``trajectory_sampling``
        says: the per-member layout is what the uncertainty decomposition needs. Entries:
        see :func:`~rcvae_torchrl.model_env.imagine_rollouts`; entry t is the transition
        s_t → s_{t+1}, the same numbers as ``env.rollout``'s ``("next", ·)`` (and ``"action"``).

        **Equivalence with ``env.rollout``.** With the same generator state, a TS-∞ rollout of
        the tensordict ``[E, N, *B]`` whose ``"member"`` is e along dim 0 (flattened in that
        order, member-major) and whose observations are the start states broadcast over
        ``[E, N]``, gives the same trajectories when all ``N·|B|`` trajectories per member are
        rolled out in one chunk (``chunk_size=None`` or ≥ ``N·|B|``).

        Args:
            start: start states ``[*B, S]``, or a tensordict ``[*B]`` holding ``"observation"``.
            actions: a_0..a_{T−1} ``[*B, T, A]`` (open loop).
            policy: closed loop instead: a TensorDict module (``"observation"`` →
                ``"action"``) or a callable on tensors ``[..., S] -> [..., A]``.
            horizon: T (closed loop).
            samples_per_member: N.
            generator: default: the env's.
            chunk_size: trajectories per member rolled out together (see
                :func:`~rcvae_torchrl.models.generate`); the noise drawn depends on it.
        """
        observation = start.get(OBSERVATION_KEY) if isinstance(start, TensorDictBase) else start
        with torch.no_grad():
            return imagine_rollouts(
                self.ensemble,
                observation,
                actions,
                reward_fn=self.reward_fn,
                success_fn=self.success_fn,
                policy=policy,
                horizon=horizon,
                samples_per_member=samples_per_member,
                terminate_on_success=self.terminate_on_success,
                generator=self.generator if generator is None else generator,
                chunk_size=chunk_size,
            )

    def evaluate_action_sequences(
        self,
        td_start: TensorDictBase,
        actions: torch.Tensor,
        particles: int,
        *,
        return_success: bool = False,
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """Returns of C action sequences from each start state, P' particles each.

        The planner seam of :mod:`rcvae_torchrl.planners.evaluation`. Every particle starts
        from ``td_start["observation"]`` at h_0 = 0 (model state in ``td_start`` is ignored),
        follows ``trajectory_sampling``, and earns Σ_t r_t up to and including its first
        success (all H steps if not ``terminate_on_success``), as an episode of the real env
        would. P' = E·⌈P/E⌉ for TS-∞ (P rounded up so that every member scores every candidate
        equally often; particle p follows member p // ⌈P/E⌉), except P' = 1 for P = 1 (the
        candidates are split over the members), else P' = P. A start state with a
        non-finite entry gets NaN returns (and no success) for all its candidates.

        Args:
            td_start: batch ``[*B]`` with ``"observation"`` ``[*B, S]``.
            actions: ``[*B, C, H, A]``.
            particles: P ≥ 1.
            return_success: also return whether each particle succeeds within H steps.

        Returns:
            returns ``[*B, C, P']`` (and success, bool ``[*B, C, P']``).
        """
        observation = _checks.check_evaluation_inputs(self.ensemble, td_start, actions, particles)
        batch, (c, h, a) = td_start.batch_size, actions.shape[td_start.batch_dims :]
        finite = torch.isfinite(observation).all(-1)
        start = torch.where(finite.unsqueeze(-1), observation, torch.zeros_like(observation))
        start = start.unsqueeze(-2).expand(*batch, c, start.shape[-1])
        with torch.no_grad():
            scores = score_action_sequences(
                self.ensemble,
                start.reshape(-1, start.shape[-1]),
                actions.reshape(-1, h, a),
                particles,
                reward_fn=self.reward_fn,
                success_fn=self.success_fn,
                trajectory_sampling=self.trajectory_sampling,
                terminate_on_success=self.terminate_on_success,
                generator=self.generator,
                compile=self.compile_scoring,
            )
        valid = finite.reshape(*batch, 1, 1)
        returns = scores.returns.reshape(*batch, c, -1)
        returns = torch.where(valid, returns, torch.full_like(returns, float("nan")))
        if not return_success:
            return returns
        return returns, scores.success.reshape(*batch, c, -1) & valid
