"""Two agents on the same tasks: which succeeds more often, by how much, and whether the world
model knows enough to say.

:func:`compare_agents` takes two :class:`~rcvae_torchrl.competency.CompetencyReport` of the same
task (boundary, deadline, world model) from the same start states, one per agent, and gives the
difference of their P(success) start by start and over all of them, with intervals for the
imagined samples' chance, and each ensemble member's own difference: where the members disagree
on which agent is better, the choice rests on what the model has not learned (epistemic), not
on chance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from rcvae_torchrl._checks import check_unit_interval
from rcvae_torchrl.competency.report import CompetencyReport

__all__ = ["AgentComparison", "compare_agents"]


@dataclass(frozen=True)
class AgentComparison:
    """P(success) of agent ``a`` minus agent ``b``, from the same start states ``[B]``."""

    difference: Tensor  #: ``[B]`` P_a − P_b per start state
    low: Tensor  #: ``[B]`` lower end of its interval (the imagined samples' chance)
    high: Tensor  #: ``[B]`` upper end
    by_member: Tensor  #: ``[B, E]`` each member's P_a − P_b
    p_a: Tensor  #: ``[B]`` agent a's P(success)
    p_b: Tensor  #: ``[B]`` agent b's
    confidence: float
    names: tuple[str, str] = ("A", "B")
    #: what the reports answer (their task), for the message
    outcome: str = "success"
    #: why either report is not trustworthy ('' when both are)
    warning: str = ""

    @property
    def mean(self) -> float:
        """P_a − P_b averaged over the start states."""
        return float(self.difference.mean())

    @property
    def interval(self) -> tuple[float, float]:
        """The interval of :attr:`mean` over the start states (a normal interval of the mean of
        the per-start differences at :attr:`confidence`: the tasks' spread and the imagined
        samples' chance; one start state: its own interval)."""
        n = self.difference.numel()
        if n == 1:
            return float(self.low), float(self.high)
        se = float(self.difference.std()) / math.sqrt(n)
        z = _z(self.confidence)
        return max(self.mean - z * se, -1.0), min(self.mean + z * se, 1.0)

    @property
    def members(self) -> Tensor:
        """``[E]`` each member's P_a − P_b averaged over the start states."""
        return self.by_member.mean(0)

    @property
    def members_agree(self) -> bool:
        """Whether every member gives the same agent the higher chance over the start states
        (and none a tie): where they disagree, which agent is better is epistemic doubt."""
        members = self.members
        return bool((members > 0).all() or (members < 0).all())

    def summary(self) -> str:
        """One paragraph: the two chances, their difference and its interval, and whether the
        members agree on which agent is better."""
        a, b = self.names
        low, high = self.interval
        n = self.difference.numel()
        starts = "one start state" if n == 1 else f"{n} start states"
        text = (
            f"Over {starts}: P({self.outcome}) {float(self.p_a.mean()):.2f} for {a} and "
            f"{float(self.p_b.mean()):.2f} for {b}: {a} − {b} = {self.mean:+.2f} "
            f"({self.confidence:.0%} interval {low:+.2f} to {high:+.2f})."
        )
        members = self.members
        spread = f"{float(members.min()):+.2f} to {float(members.max()):+.2f}"
        better = int((members > 0).sum())
        if not bool(members.any()):
            text += (
                f" No member of the world model tells them apart (each of the "
                f"{members.numel()} gives 0.00)."
            )
        elif self.members_agree:
            text += (
                f" All {members.numel()} members of the world model agree on the sign (each "
                f"gives {spread})."
            )
        else:
            text += (
                f" The members disagree: {better} of {members.numel()} give {a} the higher "
                f"chance (their differences {spread}), so the world model does not know enough "
                "of these states to choose between the agents (epistemic doubt); real episodes "
                "of both, or more data where they differ, would tell."
            )
        if low <= 0 <= high:
            text += " The interval holds 0: the imagined chances do not tell the agents apart."
        return (f"Warning: {self.warning}. " if self.warning else "") + text


def compare_agents(
    a: CompetencyReport,
    b: CompetencyReport,
    *,
    names: tuple[str, str] = ("A", "B"),
    confidence: float = 0.95,
) -> AgentComparison:
    """Agent ``a``'s P(success) minus agent ``b``'s, from two reports of the same task (the same
    boundary, deadline and world model: their ``task``) and the same start states.

    Per start state the difference's interval comes from the imagined samples, sample by sample
    (``a``'s sample ``i`` of member ``m`` against ``b``'s: the same noise where both were assessed
    with the same ``seed``, which narrows it; independent samples give the right width too), a
    normal interval at ``confidence``. Each member's own difference shows the epistemic side: where
    the members disagree on which agent is better, more imagined samples would not settle it.
    Reports of two agents acting otherwise are expected; reports of one agent (the same weights)
    compare it with itself."""
    for name, report in (("a", a), ("b", b)):
        if not isinstance(report, CompetencyReport):
            raise TypeError(
                f"{name}: expected a CompetencyReport (CompetencyAssessor.assess), got "
                f"{type(report).__name__}"
            )
    check_unit_interval("confidence", confidence, include_zero=False)
    if len(names) != 2 or not all(isinstance(n, str) and n for n in names):
        raise ValueError(f"names: expected two non-empty names, got {names!r}")
    if a.task != b.task or not a.task:
        raise ValueError(
            "b: expected a report of the same task as a (the same boundary, deadline and world "
            f"model), got task {b.task[:12] or 'unknown'} against {a.task[:12] or 'unknown'}; "
            "assess both agents with one assessor"
        )
    starts = [r.data.get(r.observation_key) for r in (a, b)]
    if starts[0].shape != starts[1].shape or not torch.equal(starts[0], starts[1]):
        raise ValueError(
            "b: expected the same start states as a, in the same order (shapes "
            f"{tuple(starts[1].shape)} and {tuple(starts[0].shape)}); assess both agents from "
            "the same starts"
        )
    success = [r.competency.get("success").flatten(0, -3) for r in (a, b)]  # [B, E, N]
    if success[0].shape != success[1].shape:
        mine, theirs = tuple(success[0].shape[1:]), tuple(success[1].shape[1:])
        raise ValueError(
            f"b: expected as many members and samples per member as a ({mine} [E, N]), got {theirs}"
        )
    pairs = success[0].double() - success[1].double()  # [B, E, N]
    flat = pairs.flatten(1)
    difference = flat.mean(1)
    n = flat.shape[1]
    se = flat.std(1) / math.sqrt(n) if n > 1 else torch.zeros_like(difference)
    z = _z(confidence)
    said = {name: r.warning for name, r in zip(names, (a, b)) if r.warning}
    if len(said) == 2 and a.warning == b.warning:  # one world model's warning, said once
        warnings = [f"both reports: {a.warning}"]
    else:
        warnings = [f"{name}'s report: {text}" for name, text in said.items()]
    return AgentComparison(
        difference=difference,
        low=(difference - z * se).clamp(-1.0, 1.0),
        high=(difference + z * se).clamp(-1.0, 1.0),
        by_member=pairs.mean(-1),
        p_a=success[0].double().flatten(1).mean(1),
        p_b=success[1].double().flatten(1).mean(1),
        confidence=float(confidence),
        names=tuple(names),
        outcome=a._outcome(),
        warning="; ".join(warnings),
    )


def _z(confidence: float) -> float:
    """The standard normal quantile of a two-sided interval at ``confidence``."""
    return float(torch.distributions.Normal(0.0, 1.0).icdf(torch.tensor(0.5 + confidence / 2)))
