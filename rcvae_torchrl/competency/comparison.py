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

from dataclasses import dataclass

from torch import Tensor

from rcvae_torchrl import fingerprint
from rcvae_torchrl._checks import check_same_starts, check_unit_interval
from rcvae_torchrl._text import signed
from rcvae_torchrl.competency.intervals import mean_interval, paired_difference_interval
from rcvae_torchrl.competency.report import CompetencyReport

__all__ = ["AgentComparison", "compare_agents"]


@dataclass(frozen=True)
class AgentComparison:
    """P(success) of agent ``a`` minus agent ``b``, from the same start states ``[B]``."""

    difference: Tensor  #: ``[B]`` P_a − P_b per start state
    low: Tensor  #: ``[B]`` lower end of its interval (the imagined samples' chance)
    high: Tensor  #: ``[B]`` upper end
    by_member: Tensor  #: ``[B, E]`` each member's P_a − P_b
    #: ``[E]`` lower end of the interval of each member's difference over the start states
    #: (its own imagined samples' chance)
    member_low: Tensor
    member_high: Tensor  #: ``[E]`` its upper end
    p_a: Tensor  #: ``[B]`` agent a's P(success)
    p_b: Tensor  #: ``[B]`` agent b's
    confidence: float
    names: tuple[str, str] = ("A", "B")
    #: what the reports answer (their task), for the message
    outcome: str = "success"
    #: why either report is not trustworthy ('' when both are)
    warning: str = ""
    #: whether both reports are of one agent (the same weights, or the same settings of a
    #: controller without weights: :func:`~rcvae_torchrl.fingerprint.agent_digest`)
    same_agent: bool = False
    #: the reports whose forecasts no check against real episodes vouches for
    unchecked: tuple[str, ...] = ()
    #: the paired interval of every start state's samples pooled (the imagined samples'
    #: chance alone, :func:`~rcvae_torchrl.competency.paired_difference_interval`), which
    #: :attr:`interval` never is narrower than; ``None``: not known (built by hand)
    pooled: tuple[float, float] | None = None

    @property
    def mean(self) -> float:
        """P_a − P_b averaged over the start states."""
        return float(self.difference.mean())

    @property
    def interval(self) -> tuple[float, float]:
        """The interval of :attr:`mean` over the start states (a Student's t interval of the
        mean of the per-start differences at :attr:`confidence`, :func:`mean_interval`: the
        start states' spread and the imagined samples' chance), widened to :attr:`pooled`
        where it is narrower (start states alike have no spread, their samples still have
        their chance); one start state: its own interval."""
        if self.difference.numel() == 1:
            return float(self.low), float(self.high)
        low, high = mean_interval(self.difference, self.confidence)
        if self.pooled is None:
            return low, high
        return min(low, self.pooled[0]), max(high, self.pooled[1])

    @property
    def members(self) -> Tensor:
        """``[E]`` each member's P_a − P_b averaged over the start states."""
        return self.by_member.mean(0)

    @property
    def member_verdicts(self) -> Tensor:
        """``[E]`` each member's verdict over the start states: 1 where it gives ``a`` the
        higher chance beyond its imagined samples' chance (its interval,
        :attr:`member_low` to :attr:`member_high`, above 0), -1 where it gives ``b`` the
        higher one (below 0), 0 where it does not tell them apart."""
        return (self.member_low > 0).long() - (self.member_high < 0).long()

    @property
    def members_agree(self) -> bool:
        """Whether every member gives the same agent the higher chance, each beyond its own
        samples' chance."""
        verdicts = self.member_verdicts
        return bool((verdicts == 1).all() or (verdicts == -1).all())

    @property
    def members_disagree(self) -> bool:
        """Whether some members give ``a`` the higher chance and others ``b``, each beyond its
        own samples' chance: which agent is better is then epistemic doubt."""
        verdicts = self.member_verdicts
        return bool((verdicts == 1).any() and (verdicts == -1).any())

    def summary(self) -> str:
        """One paragraph: the two chances, their difference and its interval, and whether the
        members agree on which agent is better."""
        a, b = self.names
        low, high = self.interval
        n = self.difference.numel()
        starts = "one start state" if n == 1 else f"{n} start states"
        text = (
            f"Over {starts}: P({self.outcome}) {float(self.p_a.mean()):.2f} for {a} and "
            f"{float(self.p_b.mean()):.2f} for {b}: {a} − {b} = {signed(self.mean, 2)} "
            f"({self.confidence:.0%} interval {signed(low, 2)} to {signed(high, 2)})."
        )
        members = self.members
        spread = f"{signed(members.min(), 2)} to {signed(members.max(), 2)}"
        verdicts = self.member_verdicts
        favour_a, favour_b = int((verdicts == 1).sum()), int((verdicts == -1).sum())
        count = members.numel()
        if self.members_agree:
            text += (
                f" All {count} members of the world model give "
                f"{a if favour_a else b} the higher chance (each {spread})."
            )
        elif self.members_disagree:
            text += (
                f" The members disagree: {favour_a} of {count} give {a} the higher chance and "
                f"{favour_b} give {b} (their differences {spread}), each beyond its imagined "
                "samples' chance, so the world model does not know enough of these states to "
                "choose between the agents (epistemic doubt); real episodes of both, or more "
                "data where they differ, would tell."
            )
        elif favour_a or favour_b:
            text += (
                f" {favour_a + favour_b} of {count} members give "
                f"{a if favour_a else b} the higher chance beyond their imagined samples' "
                f"chance, the others tell the agents apart no better than chance (differences "
                f"{spread})."
            )
        else:
            text += (
                f" No member of the world model tells them apart beyond its imagined samples' "
                f"chance (differences {spread})."
            )
        if low <= 0 <= high and n == 1:
            text += " The interval holds 0: the imagined chances do not tell the agents apart."
        elif low <= 0 <= high:
            text += (
                " The interval holds 0: over these start states the imagined chances do not "
                "tell the agents apart (the start states' spread and the imagined samples' "
                "chance; more start states narrow it)."
            )
        if self.same_agent:
            text += (
                " Both reports are of one agent (the same weights, or a controller's same "
                "settings): any difference is the imagined samples' chance."
            )
        if self.unchecked:
            which = "Neither report's" if len(self.unchecked) == 2 else f"{self.unchecked[0]}'s"
            text += (
                f" {which} forecasts are checked against real episodes (with_forecast_check): "
                "this is the world model's verdict."
            )
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
    paired score interval at ``confidence``
    (:func:`~rcvae_torchrl.competency.paired_difference_interval`: where every sample of both
    agents succeeds, a normal interval had no width at all). Each member's own difference,
    with the same interval over its samples of all start states, shows the epistemic side: where
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
            f"b: expected a report of the same task as a, got one of {_other_task(a, b)}; "
            "assess both agents with one assessor"
        )
    check_same_starts("b", a.start_states, b.start_states, "a report")
    success = [r.competency.get("success").flatten(0, -3).bool() for r in (a, b)]  # [B, E, N]
    if success[0].shape != success[1].shape:
        mine, theirs = tuple(success[0].shape[1:]), tuple(success[1].shape[1:])
        raise ValueError(
            f"b: expected as many members and samples per member as a ({mine} [E, N]), got {theirs}"
        )
    pairs = success[0].double() - success[1].double()  # [B, E, N]
    low, high = paired_difference_interval(success[0].flatten(1), success[1].flatten(1), confidence)
    by_member = [s.transpose(0, 1).flatten(1) for s in success]  # [E, B·N]
    member_low, member_high = paired_difference_interval(*by_member, confidence)
    pooled = paired_difference_interval(success[0].flatten(), success[1].flatten(), confidence)
    said = {name: r.warning for name, r in zip(names, (a, b)) if r.warning}
    if len(said) == 2 and a.warning == b.warning:  # one world model's warning, said once
        warnings = [f"both reports: {a.warning}"]
    else:
        warnings = [f"{name}'s report: {text}" for name, text in said.items()]
    return AgentComparison(
        difference=pairs.flatten(1).mean(1),
        low=low,
        high=high,
        by_member=pairs.mean(-1),
        member_low=member_low,
        member_high=member_high,
        p_a=success[0].double().flatten(1).mean(1),
        p_b=success[1].double().flatten(1).mean(1),
        confidence=float(confidence),
        names=tuple(names),
        outcome=a._outcome(),
        warning="; ".join(warnings),
        same_agent=a.agent is not None and a.agent == b.agent,
        unchecked=tuple(n for n, r in zip(names, (a, b)) if r.forecast_check is None),
        pooled=(float(pooled[0]), float(pooled[1])),
    )


def _other_task(a: CompetencyReport, b: CompetencyReport) -> str:
    """What makes ``b``'s task another than ``a``'s, in words."""
    if not (a.task and b.task):
        return "a task not known (a report built by hand)"
    return fingerprint.task_difference(b.task, a.task)
