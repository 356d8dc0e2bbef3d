"""``RCVAEEnsembleEnv``: a TorchRL ``ModelBasedEnvBase`` over a trained :class:`RCVAEEnsemble`."""

from __future__ import annotations

import warnings
from typing import Literal

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.model_based import ModelBasedEnvBase

from rcvae_torchrl._checks import check_bool, check_bounds, make_generator
from rcvae_torchrl.data import control_step
from rcvae_torchrl.model_env import _checks
from rcvae_torchrl.model_env.specs import (
    ACTION_KEY,
    HIDDEN_KEY,
    LATENT_KEY,
    MEMBER_KEY,
    OBSERVATION_KEY,
    SUCCESS_KEY,
    ModelEnvSpecs,
    model_env_specs,
)
from rcvae_torchrl.models import RCVAEEnsemble
from rcvae_torchrl.rollout import (
    ActionBounds,
    Compile,
    ImaginePolicy,
    RewardFn,
    SuccessFn,
    Task,
    TrajectorySampling,
    check_compile,
    evaluate_action_sequences,
    imagine,
    init_model_state,
    make_transition_module,
    plan_actions,
)

__all__ = ["MemberAssignment", "RCVAEEnsembleEnv"]

MemberAssignment = Literal["round_robin", "random"]
_STATE_KEYS = (OBSERVATION_KEY, ACTION_KEY, HIDDEN_KEY, LATENT_KEY, MEMBER_KEY)


class RCVAEEnsembleEnv(ModelBasedEnvBase):
    """The RCVAE ensemble as a TorchRL environment (``batch_size=()``: any leading batch).

    A step samples s_{t+1} for every particle of the input (particles are batch elements),
    then scores it with the task functions (:class:`~rcvae_torchrl.rollout.Task`, called by
    keyword): ``"reward"`` = ``reward_fn(observation=s_{t+1}, action=a_t)``, ``"success"`` =
    ``success_fn(observation=s_{t+1})``; success sets ``"terminated"`` and ``"done"`` only when
    ``terminate_on_success`` (mirror the real env: most envs never end at success). Actions
    are clipped to the action spec's bounds, as a real env clips them. ``"truncated"`` is
    False in ``step``: the model has no clock (append a ``StepCounter(max_steps)`` transform
    for a time limit); :meth:`imagine` marks the horizon's last step ``truncated``.

    **Keys.** ``"observation"`` ``[*B, S]``, ``"action"`` ``[*B, A]``, ``"reward"`` ``[*B, 1]``,
    ``"success"`` / ``"done"`` / ``"terminated"`` / ``"truncated"`` bool ``[*B, 1]`` and the
    model state: ``("rcvae", "hidden")`` (``[*B, H]`` for TS-∞, every member's ``[*B, E, H]``
    for ``"ts1"`` and ``"mean"``), ``("rcvae", "latent")`` ``[*B, Z]`` (z of the last step, 0 at
    reset) and ``"member"`` int64 ``[*B]`` (the member a particle follows; for ``"ts1"`` the one
    drawn at the last step; absent for ``"mean"``).

    **Trajectory sampling** (Chua et al. 2018, PETS; see
    :mod:`rcvae_torchrl.rollout.sampling`): ``"ts_inf"`` (TS-∞, default) keeps the member
    assigned at reset, ``"ts1"`` redraws it every step, ``"mean"`` steps deterministically with
    the mean of the members' noise-free predictions.

    **Reset.** ``_reset`` returns a new tensordict. Start observations come from, in order:
    the input's ``"observation"`` (e.g. the real env's current state; the particle batch is
    the input's batch), else ``start_states`` ``[K, S]`` sampled uniformly with the env's
    generator, else (when ``real_env`` was given) one ``real_env.reset()`` per start state, so
    ``check_env_specs(model_env)`` works out of the box, else a ``ValueError``. Auto-resets of
    done particles inside ``rollout(..., break_when_any_done=False)`` (TorchRL's planners run
    it so) go through
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

    **Fast paths.** :meth:`imagine` (rollouts ``[E, N, *B, T]`` for the competency metrics),
    :meth:`plan_actions` (a policy's plan) and :meth:`evaluate_action_sequences` (the planner
    seam of :mod:`rcvae_torchrl.planners`) skip TensorDict and TorchRL bookkeeping: they call
    the rollout engine (:mod:`rcvae_torchrl.rollout`) on member-major tensors directly.

    Args:
        ensemble: the trained world model (its device is the env's).
        reward_fn: ``reward_fn(observation=s_{t+1} [..., S], action=a_t [..., A]) -> [..., 1]``
            (or ``[...]``).
        success_fn: ``success_fn(observation=s [..., S]) -> [...]`` bool.
        real_env: copy the task specs from it (:meth:`set_specs_from_env`) and draw start
            states from its ``reset()`` when no others are given (which ends the episode it is
            in); without it, default specs (actions bounded in [-1, 1]).
        trajectory_sampling: ``"ts_inf"``, ``"ts1"`` or ``"mean"``.
        member_assignment: ``"round_robin"`` or ``"random"`` members at reset.
        terminate_on_success: success ends an imagined episode (mirror the real env's setting;
            off by default, as in most envs).
        start_states: ``[K, S]`` start observations for resets without an ``"observation"``.
        generator: source of all randomness of the env (sampling noise, members, start
            states); or ``seed`` to make one. ``set_seed`` reseeds it. ``None``: global RNG.
        validate: check shapes, dtypes and finiteness of the inputs at every step.
        requires_grad: let ``step`` record the autograd graph (off: rollouts are for
            planning and evaluation, and a graph over a whole rollout costs memory).
        compile_scoring: :meth:`evaluate_action_sequences` runs the ``"ts_inf"`` rollout (all
            H steps: model, constraint, reward, success) compiled: ``True`` as one
            ``torch.compile``-d function (:func:`~rcvae_torchrl.rollout.compiled_scoring`;
            tens of seconds on a CPU in each process per new model, task or horizon),
            ``"aot"`` as a package compiled ahead of time (:mod:`~rcvae_torchrl.rollout.aot`:
            built once per architecture, task and horizon, cached across processes and
            loaded in a fraction of a second; retrained weights reuse it). One compile serves
            every number of candidates and particles; the same samples up to float rounding.
            Other modes and ``step`` are unaffected.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
        >>> model = RCVAEEnsemble(RCVAEConfig(4, 2, hidden_dim=16, mlp_dim=16), ensemble_size=5)
        >>> def reward(observation, action):
        ...     return -observation[..., :1].abs()
        >>> def success(observation):
        ...     return observation[..., 0].abs() < 0.01
        >>> starts = torch.rand(100, 4) * 0.2 - 0.1
        >>> env = RCVAEEnsembleEnv(model, reward, success, start_states=starts, seed=0)
        >>> td = env.reset(TensorDict(batch_size=[8]))
        >>> td["member"].tolist()
        [0, 1, 2, 3, 4, 0, 1, 2]
        >>> rollout = env.rollout(6, tensordict=td, auto_reset=False, break_when_any_done=False)
        >>> rollout["next", "observation"].shape
        torch.Size([8, 6, 4])
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
        trajectory_sampling: TrajectorySampling = "ts_inf",
        member_assignment: MemberAssignment = "round_robin",
        terminate_on_success: bool = False,
        start_states: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
        seed: int | None = None,
        validate: bool = True,
        requires_grad: bool = False,
        compile_scoring: Compile = False,
    ) -> None:
        _checks.check_arguments(ensemble, trajectory_sampling, member_assignment)
        for name, flag in (
            ("terminate_on_success", terminate_on_success),
            ("validate", validate),
            ("requires_grad", requires_grad),
        ):
            check_bool(name, flag)
        if real_env is not None and not isinstance(real_env, EnvBase):
            raise TypeError(
                f"real_env: expected a TorchRL EnvBase or None, got {type(real_env).__name__}"
            )
        task = Task(reward_fn, success_fn, terminate_on_success)
        device = ensemble.device
        cfg, like = ensemble.config, {"dtype": ensemble.dtype, "device": device}
        with torch.no_grad():  # two states: a function reducing over the batch shows
            task.check_batched(
                torch.zeros(2, cfg.obs_dim, **like), torch.zeros(2, cfg.action_dim, **like)
            )
        generator = make_generator(generator, seed, device)
        transition = make_transition_module(
            ensemble,
            trajectory_sampling=trajectory_sampling,
            generator=generator,
            validate=validate,
            out_prefix=(),
        )
        super().__init__(transition, device=device, batch_size=torch.Size([]))
        self.ensemble = ensemble
        self.task = task
        self.trajectory_sampling: TrajectorySampling = trajectory_sampling
        self.member_assignment: MemberAssignment = member_assignment
        self.requires_grad = bool(requires_grad)
        check_compile("compile_scoring", compile_scoring)
        self.compile_scoring: Compile = compile_scoring
        self.generator = generator
        self.start_states: torch.Tensor | None = None
        self.set_start_states(start_states)
        self._real_env = real_env
        if real_env is None:
            self._apply_specs(model_env_specs(ensemble, trajectory_sampling, device))
        else:
            self.set_specs_from_env(real_env)

    @property
    def real_control_step(self) -> tuple[float, str] | None:
        """Seconds per step of the real env whose specs this env copies, and how they were
        read (:func:`~rcvae_torchrl.data.control_step`); where they cannot be read or there is
        no real env, the ensemble's own (``RCVAEConfig.control_step``, the step of the episodes
        it was trained on); ``None`` where neither is known. An imagined step stands for one
        such step."""
        step = None if self._real_env is None else control_step(self._real_env)
        trained = self.ensemble.config.control_step
        if step is None and trained is not None:
            return trained, "the ensemble's control_step, the step of its training episodes"
        return step

    @property
    def made_from_observation(self) -> tuple[NestedKey, ...]:
        """The entries of its specs this env makes itself where a step's input has only the
        ``"observation"`` and the action (a real env's state): the model state and the success
        flag. A planner planning in it needs no more of the real env."""
        return (SUCCESS_KEY, HIDDEN_KEY, LATENT_KEY, MEMBER_KEY)

    @property
    def reward_fn(self) -> RewardFn:
        return self.task.reward_fn

    @property
    def success_fn(self) -> SuccessFn:
        return self.task.success_fn

    @property
    def terminate_on_success(self) -> bool:
        return self.task.terminate_on_success

    # ----------------------------------------------------------------- configuration
    def set_specs_from_env(self, env: EnvBase) -> None:
        """Copy the task specs (observation, success, action, reward, done) from ``env``.

        The model state is added; the real env's other observation entries are left out
        (see :mod:`rcvae_torchrl.model_env.specs`). Raises if the shapes do not match the
        ensemble.
        """
        if not isinstance(env, EnvBase):
            raise TypeError(f"env: expected a TorchRL EnvBase, got {type(env).__name__}")
        self._apply_specs(
            model_env_specs(self.ensemble, self.trajectory_sampling, self.device, env)
        )

    def _apply_specs(self, specs: ModelEnvSpecs) -> None:
        self.observation_spec = specs.observation
        self.action_spec = specs.action
        self.reward_spec = specs.reward
        self.full_done_spec = specs.done
        self.state_spec = specs.state
        space = getattr(specs.action, "space", None)
        low, high = getattr(space, "low", None), getattr(space, "high", None)
        self.action_bounds = None
        if low is not None and high is not None:
            check_bounds("action_spec (its low and high)", low, high)
            dtype = self.ensemble.dtype
            self.action_bounds = ActionBounds(
                low.to(self.device, dtype), high.to(self.device, dtype)
            )
            _warn_training_actions_outside(self.ensemble, self.action_bounds)

    def set_start_states(self, start_states: torch.Tensor | None) -> None:
        """Set (or clear, with ``None``) the start observations ``[K, S]`` sampled at reset."""
        if start_states is not None:
            _checks.check_start_states(self.ensemble, start_states)
            start_states = start_states.detach().to(self.device).clone()
        self.start_states = start_states

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            return
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
            raise ValueError(f"seed: expected an integer in [0, 2**63), got {seed!r}")
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
            partial = tensordict is not None and "_reset" in tensordict.keys()
            if partial and self.start_states is None and self._real_env is not None:
                self._warn_real_resets()
            observation = self._sample_start_states(batch)
        else:
            _checks.check_observation(self.ensemble, "tensordict['observation']", given)
            _checks.check_batch_observation("tensordict['observation']", given, batch)
            observation = given.clone()
        member = None if tensordict is None else tensordict.get(MEMBER_KEY, None)
        state = self._initial_state(observation, member)
        flag = torch.zeros(*batch, 1, dtype=torch.bool, device=self.device)
        state.set(SUCCESS_KEY, self.task.success(observation))
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
        for key in (OBSERVATION_KEY, ACTION_KEY):
            if key not in state.keys():
                raise KeyError(
                    f"RCVAEEnsembleEnv.step: the input has no {key!r} entry (got keys "
                    f"{sorted(map(str, tensordict.keys()))})"
                )
        validate = self.world_model.validate
        if self.action_bounds is not None:
            action, a = state.get(ACTION_KEY), self.ensemble.config.action_dim
            _checks.check_trailing(ACTION_KEY, action, (a,), f"[*B, A={a}]")
            if action.dtype != self.ensemble.dtype:  # before the clamp casts an int or bool one
                _checks.check_dtype(ACTION_KEY, action, self.ensemble.dtype)
            if validate:  # before the clamp makes an infinite action finite
                _checks.check_finite(ACTION_KEY, action)
            state.set(ACTION_KEY, torch.clamp(action, *self.action_bounds))
        if HIDDEN_KEY not in state.keys(include_nested=True):
            start = self._initial_state(state.get(OBSERVATION_KEY), state.get(MEMBER_KEY, None))
            state.update(start.exclude(OBSERVATION_KEY))
        with torch.set_grad_enabled(self.requires_grad and torch.is_grad_enabled()):
            out = self.world_model(state)
        result = out.select(OBSERVATION_KEY, "rcvae", MEMBER_KEY, strict=False)
        transitions = self.task.transitions(out.get(OBSERVATION_KEY), out.get(ACTION_KEY))
        if validate:
            _checks.check_finite("reward_fn's reward", transitions["reward"])
        result.update(transitions)
        return result

    def _initial_state(
        self, observation: torch.Tensor, member: torch.Tensor | None
    ) -> TensorDictBase:
        """Model state at h_0 for ``observation [*B, S]`` (with ``member [*B]`` if given)."""
        ts_inf = self.trajectory_sampling == "ts_inf"
        return init_model_state(
            self.ensemble,
            observation,
            trajectory_sampling=self.trajectory_sampling,
            member=member if (member is not None and ts_inf) else self.member_assignment,
            generator=self.generator,
        )

    def _sample_start_states(self, batch: torch.Size) -> torch.Tensor:
        if self.start_states is None and self._real_env is not None:
            return self._real_start_states(batch)
        if self.start_states is None:
            raise ValueError(
                "RCVAEEnsembleEnv.reset: no start observations. Pass a tensordict holding "
                f"{OBSERVATION_KEY!r} [*B, {self.ensemble.config.obs_dim}] (e.g. the real env's "
                "current state), give the env start_states [K, S] to sample from, or a "
                "real_env to reset (needed for resets that only hold '_reset', e.g. auto-resets "
                "inside rollouts)."
            )
        index = torch.randint(
            self.start_states.shape[0], batch, generator=self.generator, device=self.device
        )
        return self.start_states[index]

    def _warn_real_resets(self) -> None:
        """Once per env: an auto-reset of done particles that reached this env without their
        last observations (TorchRL's reset through a transform passes only ``"_reset"``) draws
        new start states by resetting ``real_env``, which ends the episode it is in."""
        if getattr(self, "_warned_real_resets", False):
            return
        self._warned_real_resets = True
        warnings.warn(
            "RCVAEEnsembleEnv: an auto-reset of done particles (TorchRL's reset through a "
            "transform, which passes only '_reset', not their last observations) resets real_env "
            "to draw new start states; if an agent acts in that env instance, its episode was "
            "just reset. Give the model env start_states=..., act in another instance of the "
            "real env, or keep imagined episodes from ending within a rollout "
            "(terminate_on_success off, no time limit such as a StepCounter's shorter than it)",
            UserWarning,
            stacklevel=2,
        )

    def _real_start_states(self, batch: torch.Size) -> torch.Tensor:
        """One ``real_env.reset()`` per start state needed (its observations, checked)."""
        n = max(batch.numel(), 1)
        states = []
        for _ in range(n):
            obs = self._real_env.reset().get(OBSERVATION_KEY)
            states.append(obs.reshape(-1, obs.shape[-1])[0])
        observation = torch.stack(states).to(self.device)
        _checks.check_observation(self.ensemble, "real_env.reset()['observation']", observation)
        return observation.reshape(*batch, -1)

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
        chunk_size: int | str | None = "auto",
    ) -> TensorDictBase:
        """Imagined rollouts ``[E, N, *B, T]`` from start states, open or closed loop, scored.

        Always TS-∞ (sample ``(m, n, b)`` follows member m), whatever ``trajectory_sampling``
        says: the per-member layout is what the uncertainty decomposition needs. Entries: see
        :func:`~rcvae_torchrl.rollout.imagine` (with this env's task and action bounds); entry
        t is the transition s_t -> s_{t+1}, the same numbers as ``env.rollout``'s
        ``("next", ·)`` (and ``"action"``), but flat: there is no ``"next"``, and
        ``"observation"`` at t is s_{t+1} (the start states are not in the rollout).

        **Equivalence with ``env.rollout``.** With the same generator state, a TS-∞ rollout of
        the tensordict ``[E, N, *B]`` whose ``"member"`` is e along dim 0 (flattened in that
        order, member-major) and whose observations are the start states broadcast over
        ``[E, N]``, gives the same trajectories when all ``N·|B|`` trajectories per member are
        rolled out in one chunk (``chunk_size=None`` or >= ``N·|B|``).

        Args:
            start: start states ``[*B, S]``, or a tensordict ``[*B]`` holding ``"observation"``.
            actions: a_0..a_{T-1} ``[*B, T, A]`` (open loop).
            policy: closed loop instead: a TensorDict module (``"observation"`` ->
                ``"action"``) or a callable on tensors ``[..., S] -> [..., A]``.
            horizon: T (closed loop).
            samples_per_member: N.
            generator: default: the env's.
            chunk_size: trajectories per member rolled out together (``"auto"``: by the
                device, see :func:`~rcvae_torchrl.rollout.chunk_size_for`); the noise drawn
                depends on it.
        """
        observation = start.get(OBSERVATION_KEY) if isinstance(start, TensorDictBase) else start
        with torch.no_grad():
            return imagine(
                self.ensemble,
                observation,
                actions,
                policy=policy,
                horizon=horizon,
                samples_per_member=samples_per_member,
                task=self.task,
                bounds=self.action_bounds,
                generator=self.generator if generator is None else generator,
                chunk_size=chunk_size,
            )

    def plan_actions(
        self,
        start: TensorDictBase | torch.Tensor,
        policy: ImaginePolicy,
        horizon: int,
        *,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """``policy``'s actions ``[*B, H, A]`` along one imagined rollout per start (member 0);
        see :func:`~rcvae_torchrl.rollout.plan_actions`."""
        observation = start.get(OBSERVATION_KEY) if isinstance(start, TensorDictBase) else start
        return plan_actions(
            self.ensemble,
            observation,
            policy,
            horizon,
            bounds=self.action_bounds,
            generator=self.generator if generator is None else generator,
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
        success when ``terminate_on_success`` (else over all H steps), as an episode of the
        real env would. P' = E·⌈P/E⌉ for TS-∞ (P rounded up so that every member scores every
        candidate equally often; particle p follows member p // ⌈P/E⌉), except P' = 1 for P = 1
        (the candidates are split over the members), else P' = P. A start state with a
        non-finite entry gets NaN returns (and no success) for all its candidates.

        Args:
            td_start: batch ``[*B]`` with ``"observation"`` ``[*B, S]``.
            actions: ``[*B, C, H, A]``.
            particles: P >= 1.
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
            scores = evaluate_action_sequences(
                self.ensemble,
                start.reshape(-1, start.shape[-1]),
                actions.reshape(-1, h, a),
                particles,
                task=self.task,
                trajectory_sampling=self.trajectory_sampling,
                bounds=self.action_bounds,
                generator=self.generator,
                compile=self.compile_scoring,
            )
        valid = finite.reshape(*batch, 1, 1)
        returns = scores.returns.reshape(*batch, c, -1)
        returns = torch.where(valid, returns, torch.full_like(returns, float("nan")))
        if not return_success:
            return returns
        return returns, scores.success.reshape(*batch, c, -1) & valid


def _warn_training_actions_outside(ensemble: RCVAEEnsemble, bounds: ActionBounds) -> None:
    """Warn when the world model's training actions, as its normaliser keeps them (mean and
    spread per dimension), cannot have lain inside the action spec's bounds: a mean outside
    them, or a spread above half their width (the most that actions inside them can have),
    each with 5 % of the width to spare. Actions recorded in other units than the env takes
    (0 to 50 units for an env of [0, 1]) were accepted, and the model was then fed actions
    it had never seen, silently."""
    normalizer = ensemble.normalizer
    if not normalizer.fitted:
        return
    mean = normalizer.action_mean.detach().to("cpu", torch.float64)
    # the bounds of each action dimension (over any batch dims of the spec)
    low, high = (b.detach().to("cpu", torch.float64).reshape(-1, mean.shape[0]) for b in bounds)
    low, high = low.amin(0), high.amax(0)
    std = normalizer.action_std.detach().to("cpu", torch.float64)
    width = high - low
    spare = 0.05 * width
    outside = torch.isfinite(width) & (
        (mean < low - spare) | (mean > high + spare) | (std > 0.5 * width + spare)
    )
    if not bool(outside.any()):
        return
    dims = outside.nonzero().flatten().tolist()

    def show(values: torch.Tensor) -> list[float]:
        return [round(float(v), 4) for v in values[dims]]

    warnings.warn(
        f"action_spec: the world model's training actions cannot have lain inside its bounds "
        f"at action dimension(s) {dims}: their mean {show(mean)} and spread {show(std)} (the "
        f"model's normaliser) against bounds {show(low)} to {show(high)} (actions inside them "
        f"spread by at most half the width); were they recorded in other units than the env "
        f"takes, or changed by a transform after collection? The model is fed the env's "
        f"actions, which it has not seen, and its forecasts extrapolate",
        UserWarning,
        stacklevel=3,
    )
