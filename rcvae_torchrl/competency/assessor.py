"""One call from start states to a competency report: forecast, uncertainty, plain words.

:class:`CompetencyAssessor` imagines ``E·N`` TS-∞ rollouts per start state with any world model
that can imagine rollouts (:class:`ImaginesRollouts`, e.g. an
:class:`~rcvae_torchrl.model_env.RCVAEEnsembleEnv`), either closed loop (a policy acts on the
imagined states, e.g. the MPC planner) or open loop (an action sequence: the paper's
p(s_1:T | s_0, a_0:T−1)), measures them with :class:`~rcvae_torchrl.competency.UncertaintyMetric`
and :class:`~rcvae_torchrl.competency.SuccessMetric`, and returns a
:class:`~rcvae_torchrl.competency.CompetencyReport`: one TensorDict with the start states as its
batch, and a plain-language summary of it (Acharya, Russell & Ahmed, 2022: Table 1 per start
state, Figure 1 per dimension and time).
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import inspect
import math
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol, runtime_checkable

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType

from rcvae_torchrl import distributed, fingerprint
from rcvae_torchrl.competency import _checks
from rcvae_torchrl.competency._keys import KeyedModule
from rcvae_torchrl.competency.boundary import SuccessBoundary, hold_last_state
from rcvae_torchrl.competency.decomposition import check_shuffle_samples, estimator_arg_names
from rcvae_torchrl.competency.entropy import BinWidth
from rcvae_torchrl.competency.metrics import SuccessMetric, UncertaintyMetric
from rcvae_torchrl.competency.report import SPREAD_MEASURE, CompetencyReport, RealSpread
from rcvae_torchrl.data import acting, acting_record, exploration_mode, held_generators
from rcvae_torchrl.fingerprint import agent_digest
from rcvae_torchrl.rollout import as_tensor_policy, policy_reset

__all__ = ["CompetencyAssessor", "ImaginesRollouts", "PerSample", "Policy"]

_MEMBER_FIRST = ("success", "failure", ("time_to_success", "first_step"))  # [E, N, b] entries

#: ``observation [E, N, b, T, S] -> [E, N, b, T, ...]``: a per-sample output the report keeps.
PerSample = Callable[[Tensor], Tensor]
#: A closed-loop policy: a TensorDict module (``"observation"`` -> ``"action"``) or a tensor
#: callable ``[..., S] -> [..., A]``; passed on to the world model's ``imagine``.
Policy = Any


@runtime_checkable
class ImaginesRollouts(Protocol):
    """What the assessor needs of a world model: its ensemble, and imagined rollouts.

    ``ensemble`` has ``ensemble_size`` (E) and ``config.obs_dim`` / ``config.action_dim``;
    ``imagine(start [b, S], actions [b, T, A] | None, *, policy, horizon, samples_per_member,
    generator)`` returns a TensorDict ``[E, N, b, T]`` holding ``"observation"`` ``[..., S]``
    (sample ``(m, n, b)`` following member m). :class:`~rcvae_torchrl.model_env.RCVAEEnsembleEnv`
    is one.
    """

    ensemble: Any

    def imagine(self, start: Any, actions: Any = None, **kwargs: Any) -> TensorDictBase: ...


class CompetencyAssessor(KeyedModule):
    """Forecast success and its uncertainty for start states, closed or open loop.

    Each start state gets ``samples_per_member`` TS-∞ rollouts from every member of the world
    model's ensemble (its ``imagine``, see :class:`ImaginesRollouts`) over
    ``horizon`` steps, measured by :class:`~rcvae_torchrl.competency.UncertaintyMetric` (bits
    per dimension and time, the paper's equations 2 and 3) and
    :class:`~rcvae_torchrl.competency.SuccessMetric` (P(success) against ``boundary``), in
    chunks of ``start_chunk`` start states so that memory stays bounded (the noise a generator
    gives each start state depends on the chunking). Rollouts run the whole horizon; success is
    reaching the boundary at any step within its time limit.

    Use :meth:`assess` (start states as a tensor or a tensordict, policy or actions as
    arguments) or ``forward(td)`` (a TensorDict module: start states under ``"observation"``
    ``[*B, S]``, an optional open-loop plan under ``"actions"`` ``[*B, T, A]``, else the
    ``policy`` given here; keys renamed with ``set_keys``).

    Args:
        model_env: the world model (:class:`ImaginesRollouts`, ``E >= 2`` members), e.g. an
            :class:`~rcvae_torchrl.model_env.RCVAEEnsembleEnv`.
        boundary: the task's success / failure boundary.
        bin_width: histogram bin width, scalar or ``[S]`` (the smallest difference that
            matters in each dimension, in its own units); see
            :class:`~rcvae_torchrl.competency.UncertaintyMetric`.
        dim_names: names of the ``S`` observation dimensions (default: the model config's
            ``observation_names``, else ``obs[i]``).
        samples_per_member: N.
        horizon: T, steps imagined; default the boundary's time limit. Open-loop action
            sequences must have T steps (without a horizon, their length is T).
        estimator: ``"histogram"`` (default), ``"gaussian"``, ``"knn"`` or ``"mixture"``.
        dt: seconds per step for the summary's times (in the boundary's ``time_unit``);
            default the boundary's.
        policy: default closed-loop policy (a TensorDict module ``"observation"`` →
            ``"action"`` or a tensor callable ``[..., S] -> [..., A]``, e.g. the MPC planner).
        confidence: coverage of the P(success) interval.
        interval: ``"jeffreys"`` or ``"wilson"``.
        top_k: dimensions named in the summary.
        start_chunk: start states imagined together.
        episode_end: measure the uncertainty of the episode, which ends when ``boundary``
            decides the outcome (:meth:`SuccessBoundary.ended_over_time`; histogram only).
        per_sample: extra outputs kept per imagined sample: name -> function of the imagined
            observations ``[E, N, b, T, S] -> [E, N, b, T, ...]`` (e.g. a distance to a goal
            for forecast bands); the report holds them under ``("per_sample", name)`` with the
            start state first, ``[*B, E, N, T, ...]``. A NaN value is refused.
        **estimator_args: other estimator arguments (e.g. ``k``, ``joint``). The histogram's
            ``bias_correction`` defaults to ``"shuffle"`` here (one sample per member is
            refused: a member's spread from one sample is 0): its plug-in epistemic part
            reads the members' undersampling as their disagreement, bits of it per dimension
            (a 78-dimensional quadruped read 80 epistemic bits, 2.7 corrected).
            ``bias_correction="none"`` gives the plug-in split (faster: the correction splits
            the samples again a few times).

    Example:
        >>> from rcvae_torchrl.model_env import RCVAEEnsembleEnv
        >>> from rcvae_torchrl.models import RCVAEConfig, RCVAEEnsemble
        >>> model = RCVAEEnsemble(RCVAEConfig(3, 1, hidden_dim=8, mlp_dim=8), ensemble_size=3)
        >>> env = RCVAEEnsembleEnv(
        ...     model,
        ...     lambda observation, action: -observation[..., :1],
        ...     lambda observation: observation[..., 0] > 1,
        ... )
        >>> boundary = SuccessBoundary(lambda s: s[..., 0] > 1.0, time_limit_s=1.0, dt=0.1)
        >>> assessor = CompetencyAssessor(env, boundary, bin_width=0.5, dim_names=["x", "y", "v"])
        >>> report = assessor.assess(torch.zeros(2, 3), actions=torch.zeros(10, 1))
        >>> report.data["competency", "p_success"].shape, report.data["uncertainty", "total"].shape
        (torch.Size([2]), torch.Size([2, 10, 3]))
        >>> # an untrained model has no self-checks: its summary opens with a warning
        >>> print(report.summary(index=0))  # doctest: +ELLIPSIS
        Warning: the world model has no self-checks ... P(success within 1 s) = ... (95% ...
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable keys: ``observation``, ``actions`` (inputs); ``uncertainty``,
        ``competency`` (output roots)."""

        observation: NestedKey = "observation"
        actions: NestedKey = "actions"
        uncertainty: NestedKey = "uncertainty"
        competency: NestedKey = "competency"

    _inputs = ("observation",)
    _outputs = ("uncertainty", "competency")
    tensor_keys: _AcceptedKeys

    def __init__(
        self,
        model_env: ImaginesRollouts,
        boundary: SuccessBoundary,
        *,
        bin_width: BinWidth | None = None,
        dim_names: Sequence[str] | None = None,
        samples_per_member: int = 20,
        horizon: int | None = None,
        estimator: str = "histogram",
        dt: float | None = None,
        policy: Policy | None = None,
        confidence: float = 0.95,
        interval: Literal["jeffreys", "wilson"] = "jeffreys",
        top_k: int = 2,
        start_chunk: int = 16,
        episode_end: bool = False,
        per_sample: Mapping[str, PerSample] | None = None,
        **estimator_args: Any,
    ) -> None:
        super().__init__()
        obs_dim = _check_model_env(model_env)
        for name, value in (
            ("samples_per_member", samples_per_member),
            ("top_k", top_k),
            ("start_chunk", start_chunk),
        ):
            _checks.check_positive_int(name, value)
        if samples_per_member < 2:
            raise ValueError(
                f"samples_per_member: expected at least 2 imagined episodes per member (the "
                f"aleatoric part is each member's own spread: from one sample it is 0, and "
                f"every bit would be called epistemic), got {samples_per_member}; for bits you "
                f"read, take 40 or more"
            )
        if bin_width is not None:
            _checks.bin_width_tensor(bin_width, obs_dim, torch.empty(0))
        _check_keywords(estimator, estimator_args)
        if estimator == "histogram" and "bias_correction" not in estimator_args:
            # the plug-in split reads the members' undersampling as their disagreement: a
            # quadruped's 78 dimensions read 80 epistemic bits of it, 2.7 corrected
            estimator_args["bias_correction"] = "shuffle"
        self.model_env = model_env
        self.success_metric = SuccessMetric(boundary, confidence, interval)
        self.success_metric.warn_short = False  # a short horizon is warned of below, once
        self.dim_names = _dim_names(dim_names, model_env.ensemble.config)
        # the model's names when none are given: the metric's per-dimension entries and its
        # warnings name the dimensions as the report does
        self.uncertainty_metric = UncertaintyMetric(
            bin_width, estimator, self.dim_names, episode_end=episode_end, **estimator_args
        )
        self.horizon = _horizon(horizon, boundary)
        if boundary.is_survival and self.horizon < boundary.time_limit:
            raise ValueError(
                f"horizon: a survival boundary is decided at its time limit "
                f"({boundary.time_limit} steps), so the imagined episodes must last that long; "
                f"expected a horizon of at least {boundary.time_limit}, got {self.horizon}"
            )
        self.dt = _dt(dt, boundary)
        if boundary.time_unit == "s":  # a simulator's control step is in seconds
            _check_dt_against_real_env(self.dt, model_env)
        short = self.horizon is not None and self.horizon < boundary.time_limit < math.inf
        if short and not boundary.is_survival:
            # the report answers the shorter deadline, which only its wording would show
            unit = boundary.time_unit
            seconds = "" if self.dt is None else f" = {self.horizon * self.dt:g} {unit}"
            limit = "" if self.dt is None else f" = {boundary.time_limit * self.dt:g} {unit}"
            warnings.warn(
                f"horizon: {self.horizon} steps{seconds}, shorter than the boundary's time limit "
                f"of {boundary.time_limit} steps{limit}: the forecast answers P(success within "
                f"{self.horizon} steps{seconds}); give a horizon of at least "
                f"{boundary.time_limit} for the boundary's deadline",
                stacklevel=2,
            )
        _warn_success_unseen(
            boundary, getattr(getattr(model_env, "ensemble", None), "novelty", None)
        )
        self.policy = policy
        check_shuffle_samples(estimator_args.get("bias_correction", "none"), samples_per_member)
        self.samples_per_member = samples_per_member
        self.top_k, self.start_chunk = top_k, start_chunk
        self.per_sample = _per_sample(per_sample)

    @property
    def boundary(self) -> SuccessBoundary:
        return self.success_metric.boundary

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The report's ``data`` for ``tensordict[observation]`` (see the class docstring)."""
        actions = tensordict.get(self.tensor_keys.actions, None)
        return self.assess(tensordict, actions=actions).data

    def assess(
        self,
        start: Tensor | TensorDictBase,
        *,
        policy: Policy | None = None,
        actions: Tensor | None = None,
        generator: torch.Generator | None = None,
        seed: int | None = None,
        return_rollouts: bool = False,
        exploration_type: ExplorationType | str | None = None,
        first_chunk: int = 0,
    ) -> CompetencyReport:
        """Imagine, measure and report; see :class:`CompetencyReport` for what it holds.

        Args:
            start: start states ``[*B, S]``, or a tensordict holding them under the
                ``observation`` key.
            policy: closed loop (default: the assessor's ``policy``), ``horizon`` steps. A
                policy whose class has ``reset()`` (a planner's warm start) is reset before
                each chunk: its imagined episodes are new ones.
            actions: open loop instead: ``[T, A]`` (the same for every start state) or
                ``[*B, T, A]``, inside the action spec's bounds (as a closed-loop policy's
                must be: the real episodes refuse actions outside them).
            generator: source of all sampling noise (default: the model env's), drawn chunk
                after chunk. The model env's generator is its own, seeded when the env is
                made and advanced by every call: two calls without ``seed`` give two reports
                that differ by the imagined samples' chance, whatever ``torch.manual_seed``
                says. Pass ``seed`` for the same report.
            seed: instead of ``generator``: chunk ``k`` of ``start_chunk`` start states draws
                its noise (imagination, the estimator's shuffles, and with a closed-loop policy
                the generator it holds as ``policy.generator`` and the model env's own, as a
                planner draws and scores its candidates) from generators seeded by
                ``(seed, k)`` alone; the policy's and the env's generators are left as they
                were. Under ``torch.distributed`` (:mod:`rcvae_torchrl.distributed`) the
                chunks are shared out over the ranks and the report gathered on every rank;
                it equals the single-process report under the same seed. A sharded assessment
                needs a seed.
            return_rollouts: also keep the rollouts, ``data["rollout"]`` ``[*B, E, N, T]``
                (``E·N·T`` states per start state: memory).
            exploration_type: how a stochastic closed-loop policy (a TorchRL
                ``ProbabilisticActor``) acts in the imagined episodes
                (:func:`~rcvae_torchrl.data.exploration_mode`: by default the caller's
                ``set_exploration_type``, else sampled, as TorchRL's collectors and
                :func:`~rcvae_torchrl.data.collect_episodes` run it). The report keeps it
                (:attr:`CompetencyReport.acting`): real episodes of the policy acting
                otherwise do not check it. With a ``seed``, the samples it draws from torch's
                global random stream are seeded by ``(seed, k)`` too (the stream restored
                afterwards): the same seed gives the same report.
            first_chunk: with ``seed``: these start states are a part of a larger set, cut
                at chunk ``first_chunk`` of it (a multiple of ``start_chunk`` start states
                in), and chunk ``k`` here draws as chunk ``first_chunk + k`` of the whole.
                The reports of consecutive parts then hold the whole's rows: the unit of
                work to share over processes, e.g. worker processes that each assess a
                part.
        """
        observation = self._start_states(start)
        batch = observation.shape[:-1]
        policy, plan = self._controls(policy, actions, batch)
        mode = exploration_mode(exploration_type)
        _check_seed(seed, generator)
        _checks.check_non_negative_int("first_chunk", first_chunk)
        if first_chunk and seed is None:
            raise ValueError(
                f"first_chunk: expected a seed with it (chunk k of the whole draws from "
                f"generators seeded by (seed, k)), got first_chunk={first_chunk} and no seed"
            )
        _checks.check_bool("return_rollouts", return_rollouts)
        flat = observation.reshape(-1, observation.shape[-1])
        chunks = range(0, flat.shape[0], self.start_chunk)
        if distributed.is_active() and len(chunks) < distributed.world_size():
            _warn_idle_ranks(flat.shape[0], self.start_chunk, distributed.world_size())
        mine = distributed.shard(len(chunks)) if distributed.is_active() else range(len(chunks))
        parts = []
        for k in mine:
            i = chunks[k]
            reset = policy_reset(policy)
            if reset is not None:
                reset()  # e.g. a planner's warm start: each chunk's episodes are new
            whole = first_chunk + k  # the chunk's index in the whole set of start states
            draws = None if seed is None else distributed.work_generator(seed, whole, 5)
            with (
                self._chunk_noise(seed, whole, generator, policy) as noise,
                acting(mode, None if draws is None else draws.initial_seed()),
            ):
                parts.append(
                    self._assess_chunk(
                        flat[i : i + self.start_chunk],
                        None if plan is None else plan[i : i + self.start_chunk],
                        policy,
                        noise,
                        return_rollouts,
                    )
                )
        steps = self.horizon if plan is None else plan.shape[-2]
        report = self.report(_gathered(parts, flat.device).reshape(batch), steps)
        if plan is not None:
            return report
        return dataclasses.replace(
            report, acting=acting_record(policy, mode), agent=agent_digest(policy)
        )

    @contextlib.contextmanager
    def _chunk_noise(
        self,
        seed: int | None,
        chunk: int,
        generator: torch.Generator | None,
        policy: Policy | None = None,
    ) -> Iterator[torch.Generator | None]:
        """The imagination generator of chunk ``chunk``; with a seed, the estimator's
        shuffles also draw from a generator of the chunk while it is assessed, and so do the
        generators a policy draws from (its ``generator`` attribute, as a planner's candidates,
        and the model env's own, which scores them), their states restored afterwards."""
        if seed is None:
            args = self.uncertainty_metric.estimator_args
            source = (
                generator if generator is not None else getattr(self.model_env, "generator", None)
            )
            if args.get("bias_correction") != "shuffle" or "generator" in args or source is None:
                yield generator
                return
            # the shuffles from a generator seeded by the noise source's state, which they
            # leave as it is: the same generator gives the same report
            args["generator"] = _derived_generator(source)
            try:
                yield generator
            finally:
                del args["generator"]
            return
        device = next(self.model_env.ensemble.parameters()).device
        args = self.uncertainty_metric.estimator_args
        saved = dict(args)
        if args.get("bias_correction") == "shuffle":
            args["generator"] = distributed.work_generator(seed, chunk, 1)
        held = held_generators(self.model_env, policy) if policy is not None else []
        states = [g.get_state() for g in held]
        for stream, g in enumerate(held, start=2):
            g.manual_seed(distributed.work_generator(seed, chunk, stream).initial_seed())
        try:
            yield distributed.work_generator(seed, chunk, 0, device=device)
        finally:
            args.clear()
            args.update(saved)
            for g, state in zip(held, states, strict=True):
                g.set_state(state)

    def report(self, data: TensorDictBase, steps: int | None = None) -> CompetencyReport:
        """A :class:`CompetencyReport` of ``data`` (the TensorDict :meth:`assess` returns as
        ``report.data``, e.g. read back from a file) with this assessor's settings: names,
        time limit (``steps`` imagined, default the horizon), dt, confidence, keys and the
        world model's self-check warning.

        ``steps`` must be the steps ``data`` imagined, where it holds its bits per step (its
        default then): its P(success) was judged at the time limit or at the end of those
        steps, whichever came first, and other steps would change only the words (a 3-s
        report read "within 1 s" with its 3-s P). For another deadline, judge the rollouts
        again (:func:`~rcvae_torchrl.competency.success_on_grid`, ``per_sample``) or assess
        anew.

        The report is labelled with this assessor's task (boundary, deadline, world model) and
        knows no agent: ``data`` does not say what it answered. To keep a report and read it
        back with its own task, agent and checks, save :meth:`CompetencyReport.as_dict`
        (:meth:`CompetencyReport.from_dict` reads it)."""
        total = data.get((self.tensor_keys.uncertainty, "total"), None)
        imagined = None if total is None else int(total.shape[data.batch_dims])
        if steps is not None and imagined is not None and steps != imagined:
            raise ValueError(
                f"steps: expected the {imagined} steps data imagined (its bits are per step of "
                f"them), got {steps}: the report's P(success) was judged over those steps, and "
                "other steps would change only the words; for another deadline judge the "
                "rollouts again (success_on_grid, per_sample) or assess anew"
            )
        steps = steps if steps is not None else imagined if imagined is not None else self.horizon
        limit = self.boundary.time_limit if steps is None else min(self.boundary.time_limit, steps)
        return CompetencyReport(
            data,
            self.dim_names,
            int(limit),
            self.dt,
            self.success_metric.confidence,
            self.top_k,
            self.tensor_keys.uncertainty,
            self.tensor_keys.competency,
            self.tensor_keys.observation,
            model_warning=self.model_warning,
            model_caution=self.model_caution,
            survival=self.boundary.is_survival,
            novelty=self.novelty,
            measure=self.measure,
            task=self.task(int(limit)),
            predicates=self.boundary.predicates,
            time_unit=self.boundary.time_unit,
        )

    def task(self, time_limit: int | None = None) -> str:
        """What this assessor's forecasts answer, part by part
        (:func:`rcvae_torchrl.fingerprint.task_digest`; a report keeps it as its ``task``, and
        a forecast check made from that report too): the boundary's predicates (a digest of
        their code and the values they read, as :func:`rcvae_torchrl.fingerprint.digest`
        describes a function), the deadline judged (``time_limit`` steps, default the
        boundary's), dt, and a digest of the world model (its weights, config and the
        functions it calls: :meth:`~rcvae_torchrl.models.RCVAEEnsemble.behaviour`). Two
        reports share it only where both judge the same task with the same model, and a
        refusal names the parts that differ
        (:func:`~rcvae_torchrl.fingerprint.task_difference`). The agent is not in it: a report
        keeps it on its own (:attr:`CompetencyReport.agent`)."""
        boundary = self.boundary
        limit = boundary.time_limit if time_limit is None else time_limit
        ensemble = getattr(self.model_env, "ensemble", None)
        if ensemble is None:
            model = {}
        elif callable(getattr(ensemble, "behaviour", None)):
            model = ensemble.behaviour()  # weights, config and the functions it calls
        else:
            model = dict(ensemble.state_dict())
        return fingerprint.task_digest(boundary.predicates, limit, self.dt, model)

    def real_spread(self, outcomes: Any) -> RealSpread:
        """The agent's real episodes' spread, in bits, measured as this assessor measures the
        imagined episodes' (its bin widths, the boundary's episode end, its horizon): the
        ``R`` real episodes from each start (``outcomes``, the
        :class:`~rcvae_torchrl.agent.RealOutcomes` of ``real_outcomes(...,
        keep_observations=True)``, run for at least the horizon) as the samples of one
        member, whose entropy is all aleatoric: a :class:`RealSpread`, whose ``bits`` are a
        report's ``"uncertainty"`` entries (``"total"`` = ``"aleatoric"`` ``[B, T, D]``,
        ``"epistemic"`` 0, ``"time_mean"``, ``"summary"``, ``"by_dim"``, and with an episode end
        ``"live"`` and ``"per_live_step"``), batch ``[B]``, with how they were measured and the
        outcomes' agent and start states.

        A world model that learned the env's noise imagines about as many aleatoric bits from
        the same starts (:meth:`CompetencyReport.with_real_spread` compares them); far more
        are its own error, which its members share and so do not call epistemic (a
        deterministic env and agent repeat their episodes: 0 bits). The histogram estimator
        only (its bins do not mind repeated samples); the plug-in entropy of ``R`` samples
        that spread over many bins reads low, as a member's ``N`` samples' do: compare with
        ``R`` near ``samples_per_member``."""
        metric = self.uncertainty_metric
        if metric.estimator != "histogram":
            raise ValueError(
                f"estimator: the real spread is measured with the histogram estimator, this "
                f"assessor's is {metric.estimator!r}"
            )
        observation = getattr(outcomes, "observation", None)
        if observation is None:
            raise ValueError(
                "outcomes: expected real outcomes with their observations, got "
                f"{type(outcomes).__name__} without; run real_outcomes(..., "
                "keep_observations=True)"
            )
        b, r, steps = observation.shape[:3]
        if r < 2:
            raise ValueError(
                f"outcomes: expected at least 2 real episodes per start state to measure their "
                f"spread, got {r}"
            )
        if self.horizon is None or steps < self.horizon:
            raise ValueError(
                f"outcomes: expected real episodes of at least the horizon "
                f"({self.horizon} steps), got {steps} steps"
            )
        held, ran = hold_last_state(observation[:, :, : self.horizon])
        ended = self.boundary.ended_over_time(held) | ~ran
        samples = held.transpose(0, 1).unsqueeze(0).expand(2, -1, -1, -1, -1)  # [2, R, B, T, D]
        observed = TensorDict({"observation": samples}, batch_size=samples.shape[:-1])
        if metric.episode_end:
            observed.set("ended", ended.transpose(0, 1).unsqueeze(0).expand(samples.shape[:-1]))
        skip = ("bias_correction", "shuffles", "generator")  # one member: nothing to correct
        args = {k: v for k, v in metric.estimator_args.items() if k not in skip}
        spread = UncertaintyMetric(
            metric.bin_width,
            "histogram",
            metric.dim_names,
            metric.dim_reduction,
            metric.episode_end,
            **args,
        )
        out = spread(observed).get("uncertainty")
        out.batch_size = torch.Size([b])
        return RealSpread(
            bits=out,
            measure={k: self.measure[k] for k in SPREAD_MEASURE},
            predicates=self.boundary.predicates,
            steps=int(self.horizon),
            agent=getattr(outcomes, "agent", None),
            acting=getattr(outcomes, "acting", None),
            starts=getattr(outcomes, "starts", None),
            runs=int(r),
        )

    @property
    def measure(self) -> dict[str, Any]:
        """How this assessor measures bits: its estimator, the estimator's settings (bin
        widths, bias correction, ...) and the samples per member; a report keeps it, and a
        reference measured otherwise is refused (:meth:`CompetencyReport.with_reference`)."""
        metric = self.uncertainty_metric
        width = metric.bin_width
        return {
            "estimator": metric.estimator,
            "bin_width": None if width is None else tuple(width.reshape(-1).tolist()),
            **{k: v for k, v in sorted(metric.estimator_args.items()) if k != "generator"},
            "episode_end": metric.episode_end,
            "samples_per_member": self.samples_per_member,
        }

    @property
    def model_warning(self) -> str:
        """Why the world model is not trustworthy: the message of its failed self-checks
        (``ensemble.checks``, set by training), or that it has none; '' when it passed them."""
        checks = getattr(self.model_env.ensemble, "checks", None)
        if checks is None:
            return (
                "the world model has no self-checks (trained with checks=False, or not trained "
                "here), so nothing shows it learned what this forecast needs; check it on "
                "held-out episodes: ensemble.checks = "
                "rcvae_torchrl.training.check_model(ensemble, held_out_episodes)"
            )
        return "" if checks.passed else checks.message()

    @property
    def model_caution(self) -> str:
        """What the world model's self-checks found that does not fail them: a spread wider
        than its errors (:attr:`~rcvae_torchrl.training.ModelChecks.underconfident`), whose
        aleatoric bits overstate the env's noise; '' where they found none."""
        checks = getattr(self.model_env.ensemble, "checks", None)
        wide = getattr(checks, "wide_sentence", None)
        return wide() if callable(wide) else ""

    # ----------------------------------------------------------------- one chunk
    def _assess_chunk(
        self,
        starts: Tensor,
        plan: Tensor | None,
        policy: Policy | None,
        generator: torch.Generator | None,
        keep_rollouts: bool,
    ) -> TensorDictBase:
        """Report entries ``[b]`` for start states ``[b, S]``."""
        bounds = getattr(self.model_env, "action_bounds", None)
        checked = None if policy is None or bounds is None else _InBounds(policy, *bounds)
        rollout = self.model_env.imagine(
            starts,
            plan,
            policy=policy if checked is None else checked,
            horizon=self.horizon if plan is None else None,
            samples_per_member=self.samples_per_member,
            generator=generator,
        )
        if checked is not None:
            checked.check()
        imagined = rollout.get("observation")
        observed = TensorDict({"observation": imagined}, batch_size=rollout.batch_size)
        novelty = self.novelty
        episode_end = self.uncertainty_metric.episode_end
        ended = (
            self.boundary.ended_over_time(imagined) if episode_end or novelty is not None else None
        )
        if episode_end:
            observed.set(self.uncertainty_metric.tensor_keys.ended, ended)
        out = TensorDict(batch_size=starts.shape[:1])
        out.set(self.tensor_keys.observation, starts)
        out.set(self.tensor_keys.uncertainty, self._uncertainty(observed, starts.shape[0]))
        out.set(self.tensor_keys.competency, self._competency(observed, starts.shape[0]))
        for name, fn in self.per_sample.items():
            out.set(("per_sample", name), _per_sample_value(name, fn, observed, starts.shape[0]))
        out.set("start_state", self._start_regions(starts))
        if novelty is not None:
            actions = rollout.get("action", None)
            out.set("novelty", _novelty_entries(novelty, starts, imagined, ended, actions))
        if keep_rollouts:
            out.set("rollout", rollout.permute(2, 0, 1, 3))
        return out

    def _start_regions(self, starts: Tensor) -> TensorDict:
        """``"in_success"`` and ``"in_failure"`` ``[b]``: whether a start state already lies in
        the boundary's success or failure region (the forecast looks from ``s_1`` on, so such
        a start's outcome is mostly settled before the agent acts; ``False`` without the
        region)."""
        regions = {}
        for name in ("success", "failure"):
            predicate = getattr(self.boundary, name)
            inside = torch.zeros(starts.shape[0], dtype=torch.bool, device=starts.device)
            if predicate is not None:
                inside = self.boundary._evaluate(predicate, name, starts[:, None, :])[:, 0]
            regions[f"in_{name}"] = inside
        return TensorDict(regions, batch_size=starts.shape[:1])

    @property
    def novelty(self) -> Any:
        """The world model's check of how unlike its training states a state is
        (``ensemble.novelty``, a :class:`~rcvae_torchrl.training.StateNovelty` fitted by
        training), or ``None``."""
        return getattr(self.model_env.ensemble, "novelty", None)

    def _uncertainty(self, observed: TensorDictBase, b: int) -> TensorDictBase:
        """``UncertaintyMetric`` entries with batch ``[b]``, plus the peak time per dimension."""
        out = self.uncertainty_metric(observed).get(self.uncertainty_metric.tensor_keys.uncertainty)
        out.batch_size = torch.Size([b])
        total = out.get("total")
        if total.ndim == 3:  # [b, T, D]: per dimension
            peak = total.argmax(dim=1)
            out.set("peak_step", peak)
            if self.dt is not None:
                out.set("peak_time_s", (peak + 1).to(total.dtype) * self.dt)
        return out

    def _competency(self, observed: TensorDictBase, b: int) -> TensorDictBase:
        """``SuccessMetric`` entries with the start state first, batch ``[b]``."""
        out = self.success_metric(observed).get(self.success_metric.tensor_keys.competency)
        for key in _MEMBER_FIRST:
            out.set(key, out.get(key).movedim(2, 0))
        out.set("p_success_member", out.get("p_success_member").movedim(1, 0))
        stats = out.get("time_to_success")
        if self.dt is not None and "mean_s" not in stats.keys():
            stats.set("mean_s", stats.get("mean_steps") * self.dt)
            stats.set("median_s", stats.get("median_steps") * self.dt)
        out.batch_size = torch.Size([b])
        return out

    # ----------------------------------------------------------------- inputs
    def _start_states(self, start: Tensor | TensorDictBase) -> Tensor:
        """Validated start states ``[*B, S]`` (finite, at least one)."""
        name = "start_states"
        if isinstance(start, TensorDictBase):
            key = self.tensor_keys.observation
            if key not in start.keys(include_nested=True):
                raise KeyError(f"start: expected the start states [*B, S] under {key!r}")
            start, name = start.get(key), f"start[{key!r}]"
        if not isinstance(start, Tensor):
            raise TypeError(f"{name}: expected a torch.Tensor, got {type(start).__name__}")
        obs_dim = self.model_env.ensemble.config.obs_dim
        if start.ndim < 1 or start.shape[-1] != obs_dim or start.numel() == 0:
            raise ValueError(
                f"{name}: expected shape [*B, S={obs_dim}] with at least one start state, "
                f"got {tuple(start.shape)}"
            )
        _checks.check_floating(name, start)
        _checks.check_dtype(name, start, self.model_env.ensemble.dtype)
        bad = ~torch.isfinite(start.reshape(-1, obs_dim)).all(dim=-1)
        if bool(bad.any()):
            raise ValueError(
                f"{name}: expected finite values, got NaN or inf in start state(s) "
                f"{bad.nonzero().flatten().tolist()} (flattened over [*B] = "
                f"{list(start.shape[:-1])})"
            )
        return start

    def _controls(
        self, policy: Policy | None, actions: Tensor | None, batch: torch.Size
    ) -> tuple[Policy | None, Tensor | None]:
        """``(policy, None)`` for closed loop or ``(None, actions [B', T, A])`` for open loop."""
        if policy is not None and actions is not None:
            raise ValueError(
                "policy, actions: expected one of them (policy: closed loop, actions: open "
                "loop), got both"
            )
        if actions is not None:
            return None, self._action_plan(actions, batch)
        policy = self.policy if policy is None else policy
        if policy is None:
            raise ValueError(
                "policy, actions: expected a policy (closed loop) or actions (open loop), got "
                "neither (and the assessor has no default policy)"
            )
        if self.horizon is None:
            raise ValueError(
                "horizon: a closed-loop assessment needs a horizon; give the assessor one, or "
                "a boundary with a time limit"
            )
        return policy, None

    def _action_plan(self, actions: Tensor, batch: torch.Size) -> Tensor:
        """Open-loop actions ``[T, A]`` or ``[*B, T, A]``, checked, as ``[B', T, A]``."""
        if not isinstance(actions, Tensor):
            raise TypeError(f"actions: expected a torch.Tensor, got {type(actions).__name__}")
        action_dim = self.model_env.ensemble.config.action_dim
        if actions.ndim == 2:
            actions = actions.expand(*batch, *actions.shape)
        if (
            actions.ndim != len(batch) + 2
            or actions.shape[:-2] != batch
            or actions.shape[-1] != action_dim
            or actions.shape[-2] < 1
        ):
            raise ValueError(
                f"actions: expected shape [T, A] or [*B, T, A] with [*B] = {list(batch)}, "
                f"T >= 1 and A = {action_dim}, got {tuple(actions.shape)}"
            )
        if self.horizon is not None and actions.shape[-2] != self.horizon:
            raise ValueError(
                f"actions: expected T = horizon = {self.horizon} steps, got T = "
                f"{actions.shape[-2]} (shape {tuple(actions.shape)})"
            )
        _checks.check_finite("actions", actions)
        bounds = getattr(self.model_env, "action_bounds", None)
        if bounds is not None:
            low, high = (b.to(actions) for b in bounds)
            excess = torch.maximum(low - actions, actions - high).clamp_min(0)
            if bool((excess > 0).any()):
                # the model env would clip them, as the real env does: a plan written for other
                # bounds would be assessed as another plan, without a word
                raise ValueError(
                    f"actions: expected actions inside the env's action_spec bounds "
                    f"[{low.tolist()}, {high.tolist()}], got {int((excess > 0).any(-1).sum())} of "
                    f"{excess[..., 0].numel()} outside, by up to {float(excess.max()):.4g}; clip "
                    "them (the env would act on the clipped ones)"
                )
        return actions.reshape(-1, *actions.shape[-2:])


#: imagined rollouts per member whose states the novelty check looks at (at the steps of its
#: ``episode_steps``, as it looks at real episodes)
_NOVELTY_SAMPLES = 2


def _novelty_entries(
    novelty: Any, starts: Tensor, imagined: Tensor, ended: Tensor, actions: Tensor | None = None
) -> TensorDict:
    """``("novelty", ·)`` entries ``[b]``: ``"start"``, the start state's distance over the
    check's level of start states (above 1: unlike the training states); ``"imagined"``, the
    share of imagined states ``[E, N, b, T, S]`` beyond the states' level (every member's
    first samples, at steps spread over the horizon), a state after its episode ended
    (``ended`` ``[E, N, b, T]``, the boundary's success, failure or time limit) never beyond:
    such states decide nothing, and real episodes that an env ends there have none past it;
    and ``"leaves"`` (int64), the time index of the first of those steps at which most of the
    samples are beyond it (-1: none); where the check judges actions and the rollouts hold
    them (``[E, N, b, T, A]``), ``"actions"``, the share of the imagined steps (every sample's,
    while its episode runs) whose action lies outside the training actions' support."""
    at = novelty.episode_steps(imagined.shape[-2]).to(imagined.device)
    picked = imagined[:, :_NOVELTY_SAMPLES, :, at].movedim(2, 0)  # [b, E, n, steps, S]
    live = ~ended[:, :_NOVELTY_SAMPLES, :, at].movedim(2, 0)  # [b, E, n, steps]
    b = starts.shape[0]
    beyond = (novelty.ratio(picked.reshape(b, -1, picked.shape[-1])) > 1) & live.reshape(b, -1)
    share = beyond.float().mean(-1)
    most = beyond.reshape(b, -1, at.numel()).float().mean(-2) > 0.5  # [b, steps]
    leaves = torch.where(most.any(-1), at[most.int().argmax(-1)], -1)
    entries = {
        "start": novelty.ratio(starts, starts=True).to(starts),
        "imagined": share.to(starts),
        "leaves": leaves.to(starts.device),
    }
    if actions is not None and getattr(novelty, "judges_actions", False):
        # the action of step t is taken in the state of step t - 1: live while that one is
        acted = torch.cat([torch.zeros_like(ended[..., :1]), ended[..., :-1]], dim=-1)
        live = ~acted.movedim(2, 0).reshape(b, -1)  # [b, E·N·T]
        unseen = novelty.unseen_actions(actions).movedim(2, 0).reshape(b, -1) & live
        entries["actions"] = (unseen.sum(-1) / live.sum(-1).clamp_min(1)).to(starts)
    return TensorDict(entries, batch_size=[b])


def _check_seed(seed: int | None, generator: torch.Generator | None) -> None:
    if seed is not None and generator is not None:
        raise ValueError("seed, generator: expected at most one of them, got both")
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(
            f"generator: expected a torch.Generator or None (or pass seed=), got "
            f"{type(generator).__name__}"
        )
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
        raise ValueError(f"seed: expected a non-negative int, got {seed!r}")
    if seed is None and distributed.is_active():
        raise ValueError(
            "seed: an assessment sharded over torch.distributed ranks needs a seed (each chunk "
            "of start states is seeded by it), got None"
        )


def _gathered(parts: list[TensorDictBase], device: torch.device) -> TensorDictBase:
    """This rank's chunks joined, or every rank's, in chunk order, under torch.distributed."""
    if not distributed.is_active():
        return torch.cat(parts, dim=0)
    local = torch.cat(parts, dim=0).cpu() if parts else None
    gathered = [p for p in distributed.all_gather(local) if p is not None]
    return torch.cat(gathered, dim=0).to(device)


def _check_model_env(model_env: object) -> int:
    """A world model that imagines rollouts over ``E >= 2`` members; returns its state dim."""
    # attribute look-ups, not isinstance(·, ImaginesRollouts): from Python 3.12 a protocol's
    # isinstance reads attributes statically and misses a module's submodules (``ensemble``)
    ensemble = getattr(model_env, "ensemble", None)
    if not callable(getattr(model_env, "imagine", None)) or not hasattr(ensemble, "config"):
        raise TypeError(
            "model_env: expected a world model with an ensemble and an imagine method (e.g. an "
            f"RCVAEEnsembleEnv), got {type(model_env).__name__}"
        )
    if model_env.ensemble.ensemble_size < 2:
        raise ValueError(
            "model_env: expected an ensemble of E >= 2 members (the aleatoric / epistemic split "
            f"needs them), got E = {model_env.ensemble.ensemble_size}"
        )
    _check_action_transforms(model_env)
    return model_env.ensemble.config.obs_dim


def _check_action_transforms(model_env: object) -> None:
    """Refuse a ``TransformedEnv`` one of whose transforms changes the action on its way to
    the model env: the assessor imagines with ``model_env.imagine``, which a
    ``TransformedEnv`` hands to its base env, past the transforms (a transform rounding a
    cart-pole's action to ±1: imagined with 0.3 as given, 4.3 off the rounded episode). Each
    transform's inverse is tried on actions drawn from the action spec; one that raises is
    passed over (it cannot be told here)."""
    if not isinstance(model_env, TransformedEnv):
        return
    changing = []
    given = model_env.full_action_spec.rand(torch.Size([8, *model_env.batch_size]))
    for transform in model_env.transform:
        try:
            out = transform.inv(given.clone())
            changed = any(
                not isinstance(out.get(key, None), torch.Tensor)
                or out.get(key).shape != value.shape
                or out.get(key).dtype != value.dtype
                or not torch.equal(out.get(key), value)
                for key, value in given.items(True, True)
            )
        except Exception:  # an inverse that needs more than actions: not told here
            continue
        if changed:
            changing.append(type(transform).__name__)
    if changing:
        many = len(changing) > 1
        raise ValueError(
            f"model_env: its transform{'s' if many else ''} {', '.join(changing)} "
            f"change{'' if many else 's'} the action on its way to the world model, and the "
            "assessor imagines with model_env.imagine, which a TransformedEnv hands to its base "
            "env past the transforms: the forecast would judge the actions as the policy gives "
            "them. Do the change in the policy (e.g. tensordict.nn.TensorDictSequential(policy, "
            "rounding_module)), and pass the model env without it"
        )


def _dim_names(names: Sequence[str] | None, config: Any) -> tuple[str, ...]:
    """The given names, else the model's (its config's ``names``, else ``obs[i]``)."""
    obs_dim = config.obs_dim
    if names is None:
        return tuple(getattr(config, "names", None) or (f"obs[{i}]" for i in range(obs_dim)))
    return _checks.check_names("dim_names", names, obs_dim)


def _derived_generator(source: torch.Generator) -> torch.Generator:
    """A CPU generator seeded by a digest of ``source``'s state (which it does not draw
    from)."""
    import hashlib

    digest = hashlib.sha256(source.get_state().cpu().numpy().tobytes()).digest()
    return torch.Generator().manual_seed(int.from_bytes(digest[:8], "little") >> 1)


def _horizon(horizon: int | None, boundary: SuccessBoundary) -> int | None:
    """``horizon``, else the boundary's time limit when finite, else ``None``."""
    if horizon is not None:
        _checks.check_positive_int("horizon", horizon)
        return horizon
    limit = boundary.time_limit
    return int(limit) if math.isfinite(limit) else None


def _dt(dt: float | None, boundary: SuccessBoundary) -> float | None:
    """``dt``, else the boundary's; both given must agree."""
    if dt is None:
        return boundary.dt
    _checks.check_positive("dt", dt)
    if boundary.dt is not None and not math.isclose(dt, boundary.dt):
        raise ValueError(f"dt: expected the boundary's dt = {boundary.dt}, got {dt!r}")
    return float(dt)


def _check_keywords(estimator: str, estimator_args: Mapping[str, Any]) -> None:
    """Keywords neither the assessor nor its estimator takes (a misspelt
    ``samples_per_member``), named with both lists and the nearest known one."""
    names = estimator_arg_names(estimator)[0] - {"ended"}  # the assessor passes "ended"
    unknown = sorted(set(estimator_args) - names)
    if not unknown:
        return
    own = [
        p for p in inspect.signature(CompetencyAssessor.__init__).parameters if p not in _NOT_OWN
    ]
    known = [*own, *sorted(names)]
    near = [n for n in known if n.startswith(unknown[0])] or difflib.get_close_matches(
        unknown[0], known, n=1, cutoff=0.5
    )
    raise TypeError(
        f"CompetencyAssessor: got unknown keyword argument(s) {unknown}, neither the "
        f"assessor's ({', '.join(own)}) nor the {estimator!r} estimator's "
        f"({', '.join(sorted(names))})" + (f"; did you mean {near[0]!r}?" if near else "")
    )


#: the assessor's parameters a user does not pass by keyword
_NOT_OWN = ("self", "model_env", "boundary", "estimator_args")


class _InBounds:
    """A closed-loop policy (as a tensor callable) whose actions are checked against the
    env's action bounds, once, after the rollout (a check at every step would make an
    accelerator wait for the host at every step): a policy acting outside them is refused by
    the real episodes (``run_episodes``, ``real_outcomes``), so a forecast of its clipped
    actions would be one of another agent."""

    def __init__(self, policy: Policy, low: Tensor, high: Tensor) -> None:
        self.policy = as_tensor_policy(policy)
        self._reset = policy_reset(policy)
        self.low, self.high = low, high
        self.excess: list[Tensor] = []  # per step: the largest excess over the bounds

    def reset(self) -> None:
        """The policy's own reset (where it has one): each batch of imagined episodes is new."""
        if self._reset is not None:
            self._reset()

    def __call__(self, observation: Tensor) -> Tensor:
        action = self.policy(observation)
        if isinstance(action, Tensor) and action.shape[-1:] == self.low.shape:
            low, high = self.low.to(action), self.high.to(action)
            self.excess.append(torch.maximum(low - action, action - high).amax(-1))
        return action

    def check(self) -> None:
        if not self.excess:
            return
        worst = torch.stack([x.amax() for x in self.excess])
        if not bool((worst > 0).any()):  # NaN actions are named by the rollout itself
            return
        t = int((worst > 0).nonzero()[0, 0])
        outside = self.excess[t] > 0
        raise ValueError(
            f"policy: expected actions inside the env's action_spec bounds "
            f"[{self.low.tolist()}, {self.high.tolist()}], got {int(outside.sum())} of "
            f"{outside.numel()} outside at step {t} of the imagined episodes, by up to "
            f"{float(self.excess[t].max()):.4g}; clip them in the policy: the real env's "
            "episodes (run_episodes, real_outcomes) refuse them, and a forecast of the clipped "
            "actions would be one of another agent"
        )


def _warn_success_unseen(boundary: SuccessBoundary, novelty: Any) -> None:
    """Warn when none of the training states the world model's novelty check keeps lies in
    the boundary's success region (for a survival boundary: outside its failure region, or
    none inside it): the model never saw a success (a state the task survives in; a failure),
    and every forecast of one extrapolates (data of a random policy on a task of a distant
    goal, or of a pendulum that never stood up on a task of balancing it), unless the predicate
    reads other dimensions or units than it means; and when all of them lie in the success
    region, or in the failure region of a task that has both (a predicate that holds
    everywhere: the forecast is 1, or 0, whatever the agent does)."""
    states = getattr(novelty, "states", None)
    if not isinstance(states, Tensor) or not states.shape[0]:
        return
    kept = (
        f"{states.shape[0]:,} training states the world model keeps (ensemble.novelty.states, "
        "drawn from its training episodes)"
    )

    def holds(predicate: Any, name: str) -> Tensor:
        return boundary._evaluate(predicate, f"{name}, on the world model's {kept}", states)

    reads = (
        "check that the predicate reads the dimensions and units it means (a slice past the "
        "state's end, a target's position in place of the distance to it, steps for seconds)"
    )
    if boundary.is_survival:
        failed = holds(boundary.failure, "failure")
        if not bool(failed.any()):
            warnings.warn(
                f"boundary: none of the {kept} lies in the failure region: the model never saw "
                f"a failure, so every failure it forecasts extrapolates past its data and a "
                f"forecast of none says only that it imagines none; train on episodes that "
                f"fail too, or {reads}",
                UserWarning,
                stacklevel=3,
            )
            return
        if not bool(failed.all()):
            return
        region, seen, reach = (
            "outside the failure region",
            "a state it survives in",
            "stay out of it",
        )
    else:
        inside = holds(boundary.success, "success")
        if bool(inside.all()):
            warnings.warn(
                f"boundary: all {kept} lie in the success region: a task met wherever the "
                f"model was trained is forecast as met from every start, whatever the agent "
                f"does; {reads}",
                UserWarning,
                stacklevel=3,
            )
            return
        if boundary.failure is not None and bool(holds(boundary.failure, "failure").all()):
            warnings.warn(
                f"boundary: all {kept} lie in the failure region: a task failed wherever the "
                f"model was trained is forecast as failed from every start, whatever the agent "
                f"does; {reads}",
                UserWarning,
                stacklevel=3,
            )
            return
        if bool(inside.any()):
            return
        region, seen, reach = "in the success region", "a success", "reach it"
    warnings.warn(
        f"boundary: none of the {kept} lies {region}: the model never saw {seen}, and every "
        f"forecast of one extrapolates, however much the members agree; train on episodes "
        f"that {reach}, or {reads}",
        UserWarning,
        stacklevel=3,
    )


def _warn_idle_ranks(starts: int, chunk: int, ranks: int) -> None:
    """Warn (on rank 0) when the chunks of starts are fewer than the ranks sharing them."""
    if not distributed.is_main():
        return
    chunks = math.ceil(starts / chunk)
    warnings.warn(
        f"start_chunk: {starts} start states in chunks of {chunk} make {chunks} for {ranks} "
        f"ranks, which share out chunks: {ranks - chunks} of them get no work; give "
        f"start_chunk={math.ceil(starts / ranks)} or less (the forecasts then draw other "
        f"noise: a chunk's seed is its own)",
        UserWarning,
        stacklevel=3,
    )


def _check_dt_against_real_env(dt: float | None, model_env: Any) -> None:
    """Seconds per step given (``dt``, the boundary's) must be the real env's, or the
    ensemble's training episodes', where the model env knows them (``real_control_step``): a
    frame skip left out of ``dt`` would make every time and time limit in seconds wrong by its
    factor, silently."""
    step = getattr(model_env, "real_control_step", None)
    if dt is None or step is None or math.isclose(dt, step[0], rel_tol=1e-6):
        return
    raise ValueError(
        f"dt: expected the seconds one step of the model env stands for, {step[0]:g} s "
        f"({step[1]}), got "
        f"{dt:g} s: every time in seconds, the time limit's included, would be off by "
        f"{step[0] / dt:.3g}x; give SuccessBoundary(..., dt={step[0]:g}) (a frame skip "
        "multiplies the simulator's control step)"
    )


def _per_sample(per_sample: Mapping[str, PerSample] | None) -> dict[str, PerSample]:
    out = dict(per_sample or {})
    for name, fn in out.items():
        if not isinstance(name, str) or not callable(fn):
            raise TypeError(
                f"per_sample[{name!r}]: expected a name -> callable mapping, got "
                f"{type(fn).__name__}"
            )
    return out


def _per_sample_value(name: str, fn: PerSample, observed: TensorDictBase, b: int) -> Tensor:
    """``fn`` of the imagined observations ``[E, N, b, T, S]``, start state first."""
    observation = observed.get("observation")
    value = fn(observation)
    if not isinstance(value, Tensor) or value.shape[:4] != observation.shape[:4]:
        got = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
        raise ValueError(
            f"per_sample[{name!r}]: expected a tensor of shape {tuple(observation.shape[:4])} + "
            f"(...) for observations {tuple(observation.shape)}, got {got}"
        )
    if value.is_floating_point() and bool(torch.isnan(value).any()):
        raise ValueError(
            f"per_sample[{name!r}]: expected no NaN (inf may stand for 'never'), got "
            f"{int(torch.isnan(value).sum())} NaN of {value.numel()} values from finite "
            "imagined observations"
        )
    return value.movedim(2, 0)
