"""The study's outputs: the paper's table with calibration, the figures, a GIF and report.md."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torchrl.envs import EnvBase

from rcvae_torchrl.competency import (
    AleatoricShare,
    PlattMap,
    bits_per_live_step,
    brier_score,
    expected_calibration_error,
    reliability_diagram,
    rescale_aleatoric,
)
from rcvae_torchrl.envs import CONTROL_TIMESTEP, OBSERVATION_NAMES
from rcvae_torchrl.envs.render import gl_unavailable_reason, record_episode
from rcvae_torchrl.io import atomic_write, read_json, write_json
from rcvae_torchrl.reporting import (
    escape_cell,
    plot_competency_surface,
    plot_forecast_vs_reality,
    plot_reliability,
    plot_start_reliability,
    plot_uncertainty_over_time,
    signed,
    write_table,
)
from rcvae_torchrl.stages import MARKERS
from rcvae_torchrl.training import DynamicsCheck, ModelChecks, OutcomeCheck

from .config import AssessConfig
from .pusher import CONDITIONS, FIGURE_PANELS
from .trust import (
    GAP_CONFIDENCE,
    RECALIBRATED_SCORES,
    RECALIBRATION_FOLDS,
    TARGETS,
    competency_surfaces,
    trust_checks,
    validation,
    validation_figures,
)

__all__ = ["COLUMNS", "agent_section", "condition_row", "pattern_checks", "write_report"]

COLUMNS = (
    "condition",
    "total_bits",
    "aleatoric_bits",
    "epistemic_bits",
    "forecast_p_success",
    "empirical_p_success",
    "brier",
    "ece",
    "start_states",
    "real_episodes",
)


def _pairs(forecast: Mapping[str, torch.Tensor], truth: Mapping[str, torch.Tensor]):
    """Forecast P(success) and real outcome for every real episode: ``[B·R]`` each."""
    outcome = truth["success"].float()
    p = forecast["p_success"].unsqueeze(-1).expand_as(outcome)
    return p.reshape(-1), outcome.reshape(-1)


def condition_row(
    name: str,
    forecast: Mapping[str, torch.Tensor],
    truth: Mapping[str, torch.Tensor],
    n_bins: int = 5,
) -> dict[str, Any]:
    """One table row: bits summed over state dimensions, averaged over time and start states."""
    p, outcome = _pairs(forecast, truth)
    bits = {k: forecast[k].sum(-1).mean().item() for k in ("total", "aleatoric", "epistemic")}
    return {
        "condition": name,
        "total_bits": bits["total"],
        "aleatoric_bits": bits["aleatoric"],
        "epistemic_bits": bits["epistemic"],
        "forecast_p_success": forecast["p_success"].mean().item(),
        "empirical_p_success": outcome.mean().item(),
        "brier": brier_score(p, outcome).item(),
        "ece": expected_calibration_error(p, outcome, n_bins=n_bins).item(),
        "start_states": int(forecast["p_success"].numel()),
        "real_episodes": int(outcome.numel()),
    }


#: Windows (s from the forecast's start) of the pattern diagnostic; the horizon is added.
PATTERN_WINDOWS_S = (1.0, 2.0, 5.0, 10.0)


def pattern_by_window(
    forecasts: Mapping[str, Mapping[str, torch.Tensor]],
    dt: float,
    windows_s: tuple[float, ...] = PATTERN_WINDOWS_S,
) -> dict[str, dict[str, float]]:
    """The pattern's three ratios with the bits averaged over the first seconds only.

    A diagnostic beside the table (which averages over the whole horizon): when the imagined
    spread reaches the histogram's ceiling after a few seconds, the differences between the
    conditions live in the first seconds. Keys are the windows in seconds (``"1s"``, ...,
    the horizon last); values ``aleatoric_stochastic_over_deterministic``,
    ``epistemic_ood_over_deterministic`` and ``aleatoric_ood_over_deterministic``.

    When every forecast holds ``"live"`` ``[B, T]`` (the share of its imagined episodes still
    running, from a forecast with ``episode_end``), a last entry ``"per live step"`` gives the
    ratios of the bits per step of the episodes' life: each start's bits summed over time,
    divided by the steps its episodes run on average. An ended episode counts as certain, so
    a time mean also measures how long the episodes last; this entry takes that out.
    """
    steps = forecasts["deterministic"]["aleatoric"].shape[-2]
    windows = sorted({min(round(w / dt), steps) for w in windows_s} | {steps})
    out = {
        f"{t * dt:g}s": _pattern_ratios(
            {
                (c, k): f[k][..., :t, :].sum(-1).mean().item()
                for c, f in forecasts.items()
                for k in ("aleatoric", "epistemic")
            }
        )
        for t in windows
    }
    if all("live" in f for f in forecasts.values()):
        out["per live step"] = _pattern_ratios(
            {
                (c, k): bits_per_live_step(f[k].sum(-1).mean(-1), f["live"]).mean().item()
                for c, f in forecasts.items()
                for k in ("aleatoric", "epistemic")
            }
        )
    return out


def _pattern_ratios(bits: Mapping[tuple[str, str], float]) -> dict[str, float]:
    """The pattern's three ratios from ``(condition, part) -> bits``."""
    det, ood = "deterministic", "out-of-distribution"
    return {
        "aleatoric_stochastic_over_deterministic": _ratio(
            bits["stochastic", "aleatoric"], bits[det, "aleatoric"]
        ),
        "epistemic_ood_over_deterministic": _ratio(bits[ood, "epistemic"], bits[det, "epistemic"]),
        "aleatoric_ood_over_deterministic": _ratio(bits[ood, "aleatoric"], bits[det, "aleatoric"]),
    }


def _ratio(a: float, b: float) -> float:
    """``a / b``; a rise from nothing is infinite, and nothing over nothing is no ratio (NaN,
    a check it decides is not met: with one sample per member and the shuffle correction,
    every epistemic part was 0 and 0 / 0 read as a rise of inf)."""
    if b > 0:
        return a / b
    return float("inf") if a > 0 else float("nan")


def _comparable(a: float, b: float) -> float:
    """``a / b`` for a check that the two are comparable: equal parts (nothing and nothing
    too, as a deterministic env's real aleatoric parts are) are a ratio of 1."""
    return 1.0 if a == b else _ratio(a, b)


def paper_pattern(rows: Mapping[str, Mapping[str, Any]], after: str = "") -> dict[str, dict]:
    """The paper's qualitative pattern in the table's ``rows``: its three ratios, each with
    whether it is met; ``after`` is added to each check's name (e.g. the split it is of)."""
    det, sto, ood = rows["deterministic"], rows["stochastic"], rows["out-of-distribution"]
    checks = {
        "aleatoric stochastic / deterministic >= 1.5": _ratio(
            sto["aleatoric_bits"], det["aleatoric_bits"]
        ),
        "epistemic out-of-distribution / deterministic >= 1.3": _ratio(
            ood["epistemic_bits"], det["epistemic_bits"]
        ),
        "aleatoric out-of-distribution / deterministic within 0.7-1.3": _comparable(
            ood["aleatoric_bits"], det["aleatoric_bits"]
        ),
    }
    return {
        name + after: {
            "value": value,
            "met": bool(
                value >= 1.5
                if ">= 1.5" in name
                else value >= 1.3
                if ">= 1.3" in name
                else 0.7 <= value <= 1.3
            ),
        }
        for name, value in checks.items()
    }


def pattern_checks(
    rows: Mapping[str, Mapping[str, Any]], overall: Mapping[str, float]
) -> dict[str, dict[str, Any]]:
    """The qualitative pattern of the paper and the calibration targets, as measured."""
    out = paper_pattern(rows)
    for name, row in rows.items():
        gap = abs(row["forecast_p_success"] - row["empirical_p_success"])
        out[f"|forecast - empirical| <= 0.10 ({name})"] = {"value": gap, "met": gap <= 0.10}
    out["Brier < constant forecast (all start states)"] = {
        "value": overall["brier"],
        "constant": overall["constant_brier"],
        # a perfect forecast meets it where the constant one is perfect too (all alike)
        "met": overall["brier"] < overall["constant_brier"] or overall["brier"] == 0.0,
    }
    return out


def _figures(run_dir: Path, forecasts, truths, panels: int, radius: float) -> dict[str, Path]:
    curves = {
        c: {"aleatoric": f["aleatoric"].mean(0), "epistemic": f["epistemic"].mean(0)}
        for c, f in forecasts.items()
    }
    paths = {
        "uncertainty": plot_uncertainty_over_time(
            curves, FIGURE_PANELS, CONTROL_TIMESTEP, run_dir / "uncertainty_over_time.png"
        )
    }
    diagrams = {
        c: reliability_diagram(*_pairs(forecasts[c], truths[c]), n_bins=5) for c in forecasts
    }
    paths["reliability"] = plot_reliability(diagrams, run_dir / "reliability.png")
    episodes = []
    for c, f in forecasts.items():
        for b in range(min(panels, f["p_success"].numel()) if c == "stochastic" else 1):
            real = [t[~t.isnan()] for t in truths[c]["trace"][b]]
            episodes.append(
                {
                    "title": f"{c}, start {b}\nforecast P(success) = {f['p_success'][b]:.2f}",
                    "forecast": f["ball_to_target"][b],
                    "real": real,
                }
            )
    paths["forecast_vs_reality"] = plot_forecast_vs_reality(
        episodes,
        CONTROL_TIMESTEP,
        run_dir / "forecast_vs_reality.png",
        ylabel="ball to target (m)",
        threshold=radius,
    )
    return paths


def _episode_gif(run_dir: Path, policy: Callable, env: EnvBase, seed: int) -> str:
    reason = gl_unavailable_reason()
    if reason is not None:
        return f"no GIF: {reason}"
    env.set_seed(seed)
    if hasattr(type(policy), "reset"):
        policy.reset()
    record_episode(env, policy, run_dir / "episode.gif", max_steps=600)
    return "episode.gif"


def write_report(
    run_dir: Path,
    forecasts: Mapping[str, Mapping[str, torch.Tensor]],
    truths: Mapping[str, Mapping[str, torch.Tensor]],
    config: Any,
    policy: Callable,
    episode_env: EnvBase,
    model_checks: Mapping[str, ModelChecks | None] | None = None,
    far_checks: Mapping[str, Sequence[ModelChecks]] | None = None,
    forecast_checks: Mapping[str, OutcomeCheck] | None = None,
    held_out_maps: Mapping[str, PlattMap] | None = None,
    real_spreads: Mapping[str, Mapping[str, torch.Tensor]] | None = None,
    split_shares: Mapping[str, AleatoricShare] | None = None,
    dynamics_checks: Mapping[str, DynamicsCheck] | None = None,
) -> dict[str, Any]:
    """Write table.md/.csv, the figures, episode.gif and report.md; return the summary.

    ``model_checks``: each world model's self-checks (``ensemble.checks``), reported in their
    own section (a model that failed them is named with its reasons) and in the summary.
    ``far_checks``: per model, the same checks with their coverage at horizons up to the
    forecast's, against replays of the held-out episodes' actions in the real env
    (``Study.far_checks``). ``forecast_checks``: per condition, the agent's forecasts from start
    states not scored against its real episodes from them (``Study.forecast_check``).
    ``held_out_maps``: per condition, the Platt map fitted on those episodes, whose
    recalibration of the scored forecasts is reported beside them. ``real_spreads``: per
    condition, the real episodes' spread from some of its start states against the
    forecast's aleatoric bits there (``Study.real_spread``). ``split_shares``: per condition,
    the share of its world model's aleatoric bits that the real episodes from held-out start
    states showed (``Study.aleatoric_share``); with one for every condition, the table's bits
    and the paper's pattern are given again with the split calibrated by it.
    ``dynamics_checks``: per condition, whether its real env moves as its world model learned
    (``Study.dynamics_check``), a check each where measured."""
    rows = {c: condition_row(c, forecasts[c], truths[c]) for c in forecasts}
    write_table(list(rows.values()), COLUMNS, run_dir / "table")
    p, y = (torch.cat(t) for t in zip(*(_pairs(forecasts[c], truths[c]) for c in forecasts)))
    overall = {
        "brier": brier_score(p, y).item(),
        "constant_brier": brier_score(torch.full_like(y, y.mean().item()), y).item(),
        "success_rate": y.mean().item(),
    }
    checks = pattern_checks(rows, overall)
    shares = dict(split_shares or {})
    calibrated = {}
    if shares and set(shares) == set(forecasts):
        calibrated = {
            c: condition_row(c, calibrated_split(forecasts[c], shares[c]), truths[c])
            for c in forecasts
        }
        checks.update(paper_pattern(calibrated, AFTER_SHARE))
    a = config.assess
    scores = validation(forecasts, truths, a.success_radius, held_out_maps)
    deadlines = [round(d / CONTROL_TIMESTEP) for d in a.surface_deadlines_s]
    surfaces = competency_surfaces(forecasts, truths, list(a.surface_radii), deadlines)
    checks.update(trust_checks(scores, surfaces))
    dynamics_checks = dict(dynamics_checks or {})
    checks.update(dynamics_rows(dynamics_checks))
    model_checks = {k: v for k, v in (model_checks or {}).items() if v is not None}
    far_checks = {k: list(v) for k, v in (far_checks or {}).items() if v}
    forecast_checks = dict(forecast_checks or {})
    by_window = pattern_by_window(forecasts, CONTROL_TIMESTEP)
    figures = _figures(run_dir, forecasts, truths, a.forecast_panels, a.success_radius)
    figures["start_reliability"] = plot_start_reliability(
        validation_figures(forecasts, truths), run_dir / "start_reliability.png"
    )
    figures["surface"] = plot_competency_surface(
        surfaces, list(a.surface_radii), list(a.surface_deadlines_s), run_dir / "surface.png"
    )
    gif = _episode_gif(run_dir, policy, episode_env, config.seed)
    summary = {
        "rows": rows,
        "overall": overall,
        "checks": checks,
        "validation": scores,
        "surfaces": {
            c: {k: v.tolist() if torch.is_tensor(v) else v for k, v in x.items()}
            for c, x in surfaces.items()
        },
        "pattern_by_window": by_window,
        "gif": gif,
        "model_checks": {name: found.as_dict() for name, found in model_checks.items()},
        "model_checks_far": {
            name: [found.as_dict() for found in by_horizon]
            for name, by_horizon in far_checks.items()
        },
        "forecast_checks": {c: found.as_dict() for c, found in forecast_checks.items()},
        "dynamics_checks": {c: found.as_dict() for c, found in dynamics_checks.items()},
        "novelty": novelty_rows(forecasts, truths),
        "real_spread": spread_rows(real_spreads or {}, shares if calibrated else None),
        "calibrated_split": {
            c: {
                **{k: row[k] for k in ("total_bits", "aleatoric_bits", "epistemic_bits")},
                "share": dict(zip(OBSERVATION_NAMES, shares[c].share.tolist())),
                "fitted_on": shares[c].start_states,
                "real": float(shares[c].real.sum()),
                "imagined": float(shares[c].imagined.sum()),
            }
            for c, row in calibrated.items()
        },
    }
    # checksummed: a value edited by hand (a verdict, a record's field) is refused on reading
    write_json(run_dir / "summary.json", summary, checksum=True)
    residual = config.planner.policy_prior  # the agent is then the scripted prior + correction
    texts = {"bits": _bits_text(config.assess), "agent": _agent_text(run_dir, config.agent)}
    text = _markdown(rows, overall, checks, by_window, figures, gif, run_dir, residual, texts)
    text = text.replace("## The agent", _validation_text(scores, a) + "## The agent", 1)
    if forecast_checks:
        told = _told_text(rows, forecast_checks, scores)
        text = text.replace("## Table", told + "## Table", 1)
    if summary["real_spread"]:
        spread = _spread_text(summary["real_spread"])
        text = text.replace("## Uncertainty over time", spread + "## Uncertainty over time", 1)
    if calibrated:
        split = _calibrated_text(rows, summary["calibrated_split"], checks, a.samples_per_member)
        text = text.replace("## Uncertainty over time", split + "## Uncertainty over time", 1)
    novelty = _novelty_text(summary["novelty"])
    text = text.replace("## The agent", novelty + "## The agent", 1)
    if model_checks or far_checks or forecast_checks or dynamics_checks:
        section = (
            _model_checks_text(model_checks)
            + _far_checks_text(far_checks)
            + _forecast_checks_text(forecast_checks)
            + _dynamics_checks_text(dynamics_checks)
        )
        text = text.replace("## The agent", section + "## The agent", 1)
    atomic_write(run_dir / "report.md", lambda f: f.write(text.encode()))
    return summary


#: the name the paper's pattern checks take with the calibrated split
AFTER_SHARE = " (split calibrated on held-out real episodes)"


def calibrated_split(
    forecast: Mapping[str, torch.Tensor], share: AleatoricShare
) -> dict[str, torch.Tensor]:
    """A stored forecast's bits with its split calibrated by ``share``
    (:func:`~rcvae_torchrl.competency.rescale_aleatoric`: each dimension keeps the share of
    its aleatoric bits the real episodes showed, the rest is epistemic); the rest unchanged."""
    parts = TensorDict({k: forecast[k] for k in ("total", "aleatoric", "epistemic")})
    return {**forecast, **rescale_aleatoric(parts, share.share).to_dict()}


def _calibrated_text(
    rows: Mapping[str, Mapping[str, Any]],
    calibrated: Mapping[str, Mapping[str, Any]],
    checks: Mapping[str, Mapping[str, Any]],
    runs: int,
) -> str:
    first = next(iter(calibrated.values()))
    lines = [
        "### The split calibrated against real episodes",
        "",
        "The table's split is the world models' own: their aleatoric part is all the spread "
        "their members agree on, the env's noise or an error they all make. Here the agent ran "
        f"{runs} more real episodes from each of {first['fitted_on']} start states of each "
        "world model's own env that no score uses (its held-out episodes' first states), and each "
        "dimension keeps the share of its aleatoric bits that their spread showed "
        "(`AleatoricShare`); the rest counts as epistemic, the model's own error. The totals "
        "and every forecast stay as they are. Before and after, in time-mean bits:",
        "",
        "| condition | aleatoric before | epistemic before | aleatoric after | epistemic after "
        "| held-out real spread / imagined aleatoric (bits per live step) |",
        "|:---|---:|---:|---:|---:|---:|",
        *[
            f"| {c} | {rows[c]['aleatoric_bits']:.3f} | {rows[c]['epistemic_bits']:.3f} | "
            f"{r['aleatoric_bits']:.3f} | {r['epistemic_bits']:.3f} | "
            f"{r['real']:.2f} / {r['imagined']:.2f} |"
            for c, r in calibrated.items()
        ],
        "",
        "The paper's pattern with the calibrated split (two equal parts compare as 1, "
        "nothing against nothing included):",
        "",
        "| check | measured | met |",
        "|:---|---:|:---:|",
        *[
            f"| {escape_cell(name.replace(AFTER_SHARE, ''))} | {c['value']:.3f} | "
            f"{'yes' if c['met'] else 'no'} |"
            for name, c in checks.items()
            if name.endswith(AFTER_SHARE)
        ],
        "",
    ]
    return "\n".join(lines) + "\n"


def spread_rows(
    spreads: Mapping[str, Mapping[str, torch.Tensor]],
    shares: Mapping[str, AleatoricShare] | None = None,
) -> dict[str, dict[str, Any]]:
    """Per condition: the forecast's aleatoric bits and the real episodes' spread from the same
    start states (means over them), their ratio, and the dimensions with the largest excess;
    with the condition's share (fitted on other start states), the aleatoric bits it keeps
    there and their ratio to the real spread: an out-of-sample check of the calibration."""
    rows = {}
    for condition, saved in spreads.items():
        imagined, real = float(saved["imagined"].mean()), float(saved["real"].mean())
        excess = (saved["imagined_by_dim"] - saved["real_by_dim"]).mean(0)
        top = excess.argsort(descending=True)[:3].tolist()
        rows[condition] = {
            "starts": int(saved["index"].numel()),
            "imagined": imagined,
            "real": real,
            "ratio": _ratio(imagined, real),
            "per_live_step": bool(saved["per_live_step"]),
            "largest_excess": {OBSERVATION_NAMES[d]: float(excess[d]) for d in top},
        }
        if shares and condition in shares:
            kept = float((saved["imagined_by_dim"] * shares[condition].share).sum(-1).mean())
            rows[condition].update(calibrated=kept, calibrated_ratio=_comparable(kept, real))
    return rows


def _spread_text(rows: Mapping[str, Mapping[str, Any]]) -> str:
    unit = "bits per live step" if all(r["per_live_step"] for r in rows.values()) else "bits"
    calibrated = all("calibrated" in r for r in rows.values())
    lines = [
        "### The aleatoric bits against the real episodes' spread",
        "",
        "The aleatoric part claims the spread of the agent's own episodes from a start state. "
        "Here the agent ran many more times in the real env from some of the start states "
        "(evenly spread over the scored ones), its observations kept, and their spread was "
        "measured as the forecast's bits are (the same bins and episode end). A model that "
        "learned the env's noise imagines about as many bits; bits far above the real ones are "
        "the model's own error, which its members share, so the split does not call them "
        f"epistemic. In {unit}, summed over the dimensions:",
        "",
        "| condition | start states | imagined aleatoric | real spread | imagined / real | "
        "largest excess (dimension: bits) |",
        "|:---|---:|---:|---:|---:|:---|",
        *[
            f"| {c} | {r['starts']} | {r['imagined']:.2f} | {r['real']:.2f} | "
            f"{_number(r['ratio'])} | "
            + ", ".join(f"{name}: {bits:.2f}" for name, bits in r["largest_excess"].items())
            + " |"
            for c, r in rows.items()
        ],
        "",
    ]
    if calibrated:
        lines += [
            "With the split calibrated on held-out start states (below), the aleatoric bits "
            "these start states keep, against the same real spread (none of these start "
            "states was used to fit it; two equal parts compare as 1):",
            "",
            "| condition | calibrated aleatoric | real spread | calibrated / real |",
            "|:---|---:|---:|---:|",
            *[
                f"| {c} | {r['calibrated']:.2f} | {r['real']:.2f} | "
                f"{_number(r['calibrated_ratio'])} |"
                for c, r in rows.items()
            ],
            "",
        ]
    return "\n".join(lines) + "\n"


def novelty_rows(
    forecasts: Mapping[str, Mapping[str, torch.Tensor]],
    truths: Mapping[str, Mapping[str, torch.Tensor]],
) -> dict[str, dict[str, Any]]:
    """Per condition whose forecast holds the novelty check's verdicts (a world model trained
    with it): the start states unlike the training states, those the report cautions (the
    start, or a share of its imagined states: ``CompetencyReport.novel``), and the per-start
    error of the forecast among them and among the others."""
    rows = {}
    for condition, forecast in forecasts.items():
        if "novel" not in forecast:
            continue
        p = forecast["p_success"]
        real = truths[condition]["success"].float().reshape(p.numel(), -1).mean(-1)
        error, novel = (p - real).abs(), forecast["novel"]
        rows[condition] = {
            "starts": int(p.numel()),
            "start_unlike": int((forecast["novelty_start"] > 1).sum()),
            "cautioned": int(novel.sum()),
            "mae_cautioned": float(error[novel].mean()) if bool(novel.any()) else None,
            "mae_rest": float(error[~novel].mean()) if not bool(novel.all()) else None,
        }
    return rows


def _novelty_text(rows: Mapping[str, Mapping[str, Any]]) -> str:
    """The section on start states unlike the world model's training states."""
    if not rows:
        return ""
    lines = [
        "### Start states unlike the training states",
        "",
        "Apart from the members' disagreement, each start state and a sample of its imagined "
        "states are compared with the states the world model was trained on (the distance to "
        "the 5th nearest of them, against the level 99 % of the episodes' first states, or "
        "of their states, stay within). A cautioned start is unlike them, or imagines more of "
        "its states unlike them than 99 % of real episodes have: its forecast extrapolates. "
        "The per-start error is |forecast - real rate|.",
        "",
        "| condition | starts | start unlike | cautioned | per-start error, cautioned | "
        "per-start error, the others |",
        "|:---|---:|---:|---:|---:|---:|",
    ]
    for condition, row in rows.items():
        cells = ["–" if row[k] is None else _number(row[k]) for k in ("mae_cautioned", "mae_rest")]
        lines.append(
            f"| {condition} | {row['starts']} | {row['start_unlike']} | {row['cautioned']} | "
            f"{' | '.join(cells)} |"
        )
    return "\n".join(lines) + "\n\n"


def _model_checks_text(model_checks: Mapping[str, ModelChecks]) -> str:
    """The world models' self-checks on held-out episodes: verdicts and coverage."""
    lines = [
        "## The world models' self-checks",
        "",
        "On held-out episodes, after training: is every state dimension predicted better than "
        "copying the previous state or guessing its mean, and does the real state lie inside "
        "the model's interval as often as it should (open loop from each episode's start, the "
        "episode's own actions)?",
        "",
    ]
    for name, found in model_checks.items():
        verdict = "passed" if found.passed else found.message()
        wide = found.wide_sentence()  # does not fail the checks: said beside the verdict
        lines.append(f"- **{name}**: {verdict}" + (f"; but {wide}." if wide else "."))
    coverage = {k: v for k, v in model_checks.items() if v.coverage is not None}
    if coverage:
        first = next(iter(coverage.values()))
        dims = first.checked
        lines += [
            "",
            f"Coverage of the {first.interval:.0%} interval after {first.coverage_steps} steps "
            f"({first.episodes} held-out episodes):",
            "",
            "| model | " + " | ".join(first.names[d] for d in dims) + " |",
            "|:---|" + "---:|" * len(dims),
            *[
                f"| {name} | " + " | ".join(f"{float(c.coverage[d]):.2f}" for d in dims) + " |"
                for name, c in coverage.items()
            ],
        ]
    return "\n".join(lines) + "\n\n"


def _stage_time(summary: dict[str, Any]) -> str:
    """A stage's seconds in this run, and where it ran when it was reused from another run."""
    text = f"{summary.get('seconds', '?')} s"
    other = summary.get("reused_from")
    if isinstance(other, dict):
        text += f" (reused from {other.get('run_dir')!r}, where it took {other.get('seconds')} s)"
    return text


def _far_checks_text(far_checks: Mapping[str, Sequence[ModelChecks]]) -> str:
    """The coverage at horizons up to the forecast's, against replayed held-out episodes."""
    if not far_checks:
        return ""
    horizons = [c.coverage_steps for c in next(iter(far_checks.values()))]
    lines = [
        "### As far ahead as the forecast",
        "",
        "The same coverage test further ahead. Its truth is a replay: each held-out episode's "
        "recorded actions sent open loop to the real env from the episode's first state, with "
        "new noise (the recorded episodes of a closed-loop controller are no fair truth far "
        "ahead in a stochastic env: its later actions answer the noise the episode met). The "
        "test's level is shared out over the horizons. Per model and horizon: the fewest "
        "held-out episodes covered on any checked dimension, and the dimensions named "
        "overconfident (✗).",
        "",
        "| model | " + " | ".join(f"{k} steps" for k in horizons) + " |",
        "|:---|" + "---|" * len(horizons),
    ]
    verdicts = []
    for name, by_horizon in far_checks.items():
        cells, named = [], []
        for found in by_horizon:
            if found.coverage is None:
                cells.append("not measured")
                continue
            fewest = int(min(found.covered[d] for d in found.checked))
            over = [found.names[d] for d in found.overconfident]
            flag = f" ✗ {', '.join(over)}" if over else ""
            cells.append(f"{fewest} of {found.episodes}{flag}")
            named += [f"{', '.join(over)} {found.coverage_steps} steps ahead"] if over else []
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
        if all(found.coverage is None for found in by_horizon):
            verdict = "not measured (too few held-out episodes this long)"
        elif named:
            used = [c for c, (model, _) in CONDITIONS.items() if model == name]
            verdict = (
                f"overconfident on {'; '.join(named)}: forecasts made with it "
                f"({', '.join(used) or 'none here'}) that hinge on these dimensions then may be "
                "too sure"
            )
        else:
            verdict = "covered as often as it should at every horizon"
        verdicts.append(f"- **{name}**: {verdict}.")
    return "\n".join([*lines, "", *verdicts]) + "\n\n"


def _told_text(
    rows: Mapping[str, Mapping[str, Any]],
    forecast_checks: Mapping[str, OutcomeCheck],
    scores: Mapping[str, Mapping[str, Any]],
) -> str:
    """What a person would be told before any scored outcome is known: per condition, the
    mean forecast and whether the forecast check, from start states no score uses, vouches
    for it; where it names a bias, the forecast through the Platt map fitted on that check's
    episodes (the table below then holds what the agent really did)."""
    lines = [
        "## What the forecasts can be trusted for",
        "",
        "Before any scored outcome: each condition's mean forecast, and the verdict of its "
        "forecast check on start states no score uses (*The forecasts, from start states they "
        "are not scored on*, below).",
        "",
    ]
    for condition, found in forecast_checks.items():
        forecast = rows[condition]["forecast_p_success"]
        head = f"- **{condition}**: forecast {forecast:.2f}"
        if not (found.measured or found.biased):  # too few starts in doubt to tell a gap
            told = "vouched for where it is 0 or 1 alone" if found.passed else found.verdict
            lines.append(f"{head}: {told} (the check's {found.starts} start states).")
            continue
        low, high = found.interval()
        gap = (
            f"gap {signed(found.gap)} on {found.starts} start states, "
            f"{100 * (1 - found.alpha):g} % interval {signed(low)} to {signed(high)}"
        )
        if found.biased:
            mapped = scores.get(condition, {}).get("recalibrated_held_out")
            after = (
                f"; through the map fitted on the check's episodes it reads "
                f"{mapped['forecast']:.2f}"
                if mapped
                else ""
            )
            lines.append(f"{head}, **{found.verdict}** ({gap}){after}.")
        elif found.passed:
            lines.append(f"{head}: the check finds no bias ({gap}).")
        else:
            lines.append(f"{head}: not vouched for, {found.verdict} ({gap}).")
    return "\n".join(lines) + "\n\n"


def _forecast_checks_text(forecast_checks: Mapping[str, OutcomeCheck]) -> str:
    """The agent's forecasts from start states they are not scored on against its real
    episodes from them, per condition, with the verdicts."""
    if not forecast_checks:
        return ""
    first = next(iter(forecast_checks.values()))
    lines = [
        "### The forecasts, from start states they are not scored on",
        "",
        "The forecast itself, checked as it is made but from other start states, against the "
        "agent's real episodes from each: in the conditions of the world models' own envs, "
        "the first states of the model's held-out episodes, topped up (where they give too "
        "few real episodes for a sharp test) with start states drawn by the condition's env's "
        "reset with seeds no scored start uses. A bias found here is one the scored forecasts "
        "above can be expected to share; this check needs no scored start. Where each start "
        "runs once (a deterministic env), only the forecasts' mean is judged, and they are "
        "imagined with `assess.check_samples_per_member` samples per member where the scored "
        "ones have more. The test is two-sided, at level "
        f"{first.alpha:g}, on the per-start differences.",
        "",
        f"| condition | starts | real runs each | forecast | real | gap "
        f"({100 * (1 - first.alpha):g} % interval) | p | verdict |",
        "|:---|---:|---:|---:|---:|---:|---:|:---|",
    ]
    verdicts = []
    for condition, found in forecast_checks.items():
        sure = getattr(found, "sure_only", False)  # passed for forecasts of 0 or 1 alone
        if not found.measured and not found.biased and not sure:  # a bias is named from fewer
            lines.append(f"| {condition} | {found.starts} | {found.runs} | | | | | not measured |")
            verdicts.append(f"- **{condition}**: {found.message()}.")
            continue
        low, high = found.interval()
        # a passed check one of whose two tests finds the gap beyond chance: said, since it
        # leans (a bias is named only where both tests find it)
        leans = not found.biased and min(found.p_value, found.exact_p_value) < found.alpha
        if not found.passed or sure or leans:  # biased, too imprecise, sure alone, or leaning
            verdicts.append(f"- **{condition}**: {found.describe()}.")
        lines.append(
            f"| {condition} | {found.starts} | {found.runs} | "
            f"{float(found.forecast.mean()):.3f} | {float(found.real.mean()):.3f} | "
            f"{signed(found.gap)} ({signed(low)} to {signed(high)}) | {found.p_value:.2g} | "
            f"{found.verdict} |"
        )
    return "\n".join([*lines, "", *verdicts]) + "\n\n"


#: the name of a condition's dynamics check among the checks
DYNAMICS_CHECK = "its env moves as its world model learned ({})"


def dynamics_rows(dynamics_checks: Mapping[str, DynamicsCheck]) -> dict[str, dict]:
    """A check per condition whose dynamics were measured: its p-value (the smallest
    dimension's, times the dimensions tested), met where the check passed."""
    return {
        DYNAMICS_CHECK.format(c): {"value": found.p_value, "met": found.passed}
        for c, found in dynamics_checks.items()
        if found.measured
    }


def _dynamics_checks_text(dynamics_checks: Mapping[str, DynamicsCheck]) -> str:
    """Per condition, whether its real env moves as its world model learned."""
    if not dynamics_checks:
        return ""
    first = next(iter(dynamics_checks.values()))
    lines = [
        "### Does each env move as its world model learned?",
        "",
        "The agent ran again in each condition's real env, from the forecast check's start "
        "states (none scored), and each episode's one-step errors under the condition's world "
        "model, over the horizon, were ranked against those of the agent's own episodes in "
        "the model's env from other start states (`check_dynamics`: per dimension, a one-sided "
        f"rank test of their size against {first.tolerance:g} times their errors and a "
        f"two-sided one of which way they lean, at level {first.alpha:g} over all the tests). "
        "A failed check says the env does not move as the model "
        "learned, in physics that changed or in states whose motion it never saw: a forecast "
        "made there extrapolates, however few epistemic bits it shows. A passed one says "
        "nothing of the outcome (the forecast check above judges that), and a change the "
        "model takes for noise it learned (an arm a little weaker, within the range the "
        "stochastic env draws its strength from) can pass it.",
        "",
        "| condition | episodes | beyond the reference's level | p | verdict |",
        "|:---|---:|---:|---:|:---|",
    ]
    verdicts = []
    for condition, found in dynamics_checks.items():
        verdict = "passed" if found.passed else "failed" if found.measured else "not measured"
        p = f"{found.p_value:.2g}" if found.measured else ""
        lines.append(f"| {condition} | {found.episodes} | {found.beyond} | {p} | {verdict} |")
        verdicts.append(f"- **{condition}**: {verdict}: {found.describe()}.")
    return "\n".join([*lines, "", *verdicts]) + "\n\n"


_SCORE_COLUMNS = (
    ("forecast", "forecast"),
    ("real", "real"),
    ("gap", "gap"),
    ("per_start_mae", "per-start MAE"),
    ("spearman", "Spearman"),
    ("real_rate_span", "real rate span"),
    ("auroc", "AUROC"),
    ("bss_overall", "BSS (overall rate)"),
    ("brier_skill", "BSS (own rate)"),
    ("brier_skill_members_limit", "BSS (own rate), infinite members"),
    ("oracle_auroc", "oracle AUROC"),
    ("oracle_brier_skill", "oracle BSS (own rate)"),
    ("chance_brier_skill", "true-chance BSS (expected)"),
    ("oracle_spearman", "oracle Spearman"),
    ("tts_crps", "TTS CRPS (steps)"),
    ("tts_crps_climatology", "climatology"),
    ("starts", "starts"),
    ("episodes", "episodes"),
)


def _validation_text(scores, assess: AssessConfig) -> str:
    """The per-task validation section of report.md."""
    head = "| condition | " + " | ".join(label for _, label in _SCORE_COLUMNS) + " |"
    rule = "|:---|" + "---:|" * len(_SCORE_COLUMNS)
    body = [
        f"| {c} | " + " | ".join(_score_cell(s.get(k, "")) for k, _ in _SCORE_COLUMNS) + " |"
        for c, s in scores.items()
    ]
    return "\n".join(
        [
            "## Per task: the forecast start by start",
            "",
            f"Each start state's forecast against the success rate of its real episodes "
            f"({assess.stochastic_seeds_per_start} per start in the stochastic env, "
            f"{assess.seeds_per_start} where the env is deterministic). BSS: Brier skill against "
            "a constant forecast of the overall or the condition's own base rate. TTS: the "
            "forecast distribution of the time to success against the real times, by CRPS, "
            "beside the condition's climatological distribution (lower is better). Infinite "
            "members: the Brier skill that the mean of infinitely many members like these would "
            "have (estimated from the members' own forecasts): below the target, the error is "
            "one the members share, not their disagreement. Oracle: the "
            "scores of a forecast equal to each start's own real success rate, the ceiling that "
            "the outcomes' randomness leaves to any forecast (in-sample, so a little "
            "optimistic); true-chance BSS: the Brier skill that a forecast of each start's true "
            "chance has in expectation (the same ceiling without that optimism; a start run "
            "once counts as fixed); oracle Spearman: about the rank "
            "correlation that a forecast of each start's true chance reaches against rates of "
            "this many runs (the square root of their split-half reliability), where a start "
            "has several runs.",
            "",
            head,
            rule,
            *body,
            "",
            *_gap_text(scores),
            "![reliability over start states](start_reliability.png)",
            "",
            *_recalibration_text(scores),
            "## Competency surface",
            "",
            "P(success) for other boundaries (success radius x deadline), answered by the same "
            "imagined and real episodes (the real ones go on after success).",
            "",
            "![competency surface](surface.png)",
            "",
            "",
        ]
    )


def _score_cell(value: Any) -> str:
    """A cell of the per-task table: 3 decimals, "–" where a score is undefined (NaN)."""
    if isinstance(value, float):
        return f"{value:.3f}" if math.isfinite(value) else "–"
    return str(value)


def _gap_text(scores) -> list[str]:
    """Each condition's gap with its interval: how precisely these start states measure it."""
    parts = [
        f"{c} {signed(s['gap_signed'])} ({signed(s['gap_low'])} to {signed(s['gap_high'])})"
        for c, s in scores.items()
        if "gap_signed" in s
    ]
    if not parts:
        return []
    tolerance = TARGETS["gap"]
    return [
        f"Forecast minus real, with its {GAP_CONFIDENCE:.0%} interval over the start states "
        "(Student's t on the per-start differences): " + "; ".join(parts) + ". A gap whose "
        f"interval lies wholly beyond ±{tolerance} misses the study's tolerance by more than "
        "the draw of start states explains; one whose interval holds ±"
        f"{tolerance} is a pass or a miss that these start states cannot tell apart.",
        "",
    ]


def _recalibration_text(scores) -> list[str]:
    """Before and after a cross-fitted recalibration: the lines of report.md."""
    rows = [(c, s) for c, s in scores.items() if s.get("recalibrated")]
    if not rows:
        return []
    keys = RECALIBRATED_SCORES
    labels = {**dict(_SCORE_COLUMNS), "ece": "ECE"}
    head = "| condition | " + " | ".join(f"{labels[k]} before | after" for k in keys) + " |"
    body = [
        f"| {c} | " + " | ".join(f"{s[k]:.3f} | {s['recalibrated'][k]:.3f}" for k in keys) + " |"
        for c, s in rows
    ]
    lines = [
        "### Recalibrated: cross-fitted on the scored start states, and by the held-out map",
        "",
        f"Not the forecast above, but what a Platt map fitted on real episodes would make of it. "
        f"The cross-fitted map (this table): each condition's scored start states are split "
        f"into {RECALIBRATION_FOLDS} folds (one start each where it has fewer) and each fold's "
        "forecasts are recalibrated with the "
        "map fitted on the other folds' episodes, so no start is recalibrated with its own "
        "outcomes. The checks score the forecast itself, and those marked through the held-out "
        "map score it through the second map below, not this one.",
        "",
        head,
        "|:---|" + "---:|" * (2 * len(keys)),
        *body,
        "",
    ]
    held = [(c, s) for c, s in scores.items() if s.get("recalibrated_held_out")]
    if held:
        lines += [
            "The held-out map (this table): the Platt map fitted on the real episodes of the "
            "forecast check above, from start states none of them scored: what a user who ran "
            "the agent from some start states can make of its forecasts for new ones. slope, "
            "intercept: "
            "the map, σ(slope·logit(f) + intercept) (overall: each condition's forecasts "
            "through its own map, pooled).",
            "",
            head.replace(" |", " | slope | intercept |", 1),
            "|:---|---:|---:|" + "---:|" * (2 * len(keys)),
            *(
                f"| {c} | {_map_cells(s['recalibrated_held_out'])} | "
                + " | ".join(f"{s[k]:.3f} | {s['recalibrated_held_out'][k]:.3f}" for k in keys)
                + " |"
                for c, s in held
            ),
            "",
        ]
    return lines


def _map_cells(after: Mapping[str, Any]) -> str:
    """A Platt map's slope and intercept cells ("–" for a pool of several maps)."""
    if "slope" not in after:
        return "– | –"
    return f"{after['slope']:.2f} | {signed(after['intercept'], 2)}"


_AGENT_TEXT = {
    True: "The scripted pusher plus a small MLP correction distilled from the policy-guided "
    "CEM/MPC planner over the deterministic model (MPC episodes, then DAgger rounds)",
    False: "An MLP policy distilled from the CEM/MPC planner over the deterministic model (MPC "
    "episodes, then DAgger rounds)",
}


#: The agent stage's numbers as the report names them (``stages/agent.json`` keys).
AGENT_LINES = {
    "mpc_noisy_success_rate": "MPC episodes (executed actions perturbed): success rate",
    "mpc_median_steps": "MPC episodes: median steps",
    "policy_success_rate": "the agent in its evaluation episodes: success rate",
    "policy_median_steps": "the agent in its evaluation episodes: median steps",
    "pairs": "state-action pairs it was distilled from (last round)",
}
#: The columns of the DAgger table: round-record key -> column title.
DAGGER_COLUMNS = {
    "round": "round",
    "pairs": "pairs",
    "policy_success_before": "policy success before the round",
    "train_mse": "train MSE",
    "val_mse": "validation MSE",
    "epochs": "epochs",
}


def _number(value: Any) -> str:
    if isinstance(value, float) and value.is_integer() and abs(value) >= 1:
        return str(int(value))
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 0.01 and value else f"{value:.3f}"
    return str(value)


def agent_section(agent: Mapping[str, Any], settings: Any) -> str:
    """The agent stage in words and tables: settings, outcomes, one row per DAgger round."""
    lines = [
        f"Settings: {settings.mpc_episodes} MPC episodes with action noise of std "
        f"{settings.action_noise}, then {settings.dagger_rounds} DAgger round(s) of "
        f"{settings.dagger_episodes} policy episodes, the agent evaluated on "
        f"{settings.eval_episodes} episodes.",
        "",
        "| measured | value |",
        "|:---|---:|",
        *[f"| {title} | {_number(agent[k])} |" for k, title in AGENT_LINES.items() if k in agent],
    ]
    rounds = agent.get("dagger", [])
    if rounds:
        lines += [
            "",
            "Distillation rounds (round 0: the MPC episodes alone; then each DAgger round adds "
            "the agent's own states, labelled by the planner):",
            "",
            "| " + " | ".join(DAGGER_COLUMNS.values()) + " |",
            "|" + "|".join([":---", *["---:"] * (len(DAGGER_COLUMNS) - 1)]) + "|",
            *[
                "| " + " | ".join(_number(r[k]) if k in r else "–" for k in DAGGER_COLUMNS) + " |"
                for r in rounds
            ],
        ]
    return "\n".join(lines)


def _agent_text(run_dir: Path, settings: Any) -> str:
    marker = run_dir / MARKERS / "agent.json"
    return (
        agent_section(read_json(marker, "stage marker", checksum=True), settings)
        if marker.is_file()
        else ""
    )


def _bits_text(assess: AssessConfig) -> str:
    """How the table's bits were measured, from the assessment's settings."""
    text = (
        "Bits: per-dimension histogram entropies at the declared resolution, summed over the "
        "state dimensions, averaged over time and start states."
    )
    if assess.episode_end:
        text += (
            " An episode ends at success, as in the real env: from the next step on, its samples "
            "count in one shared terminal bin, so a forecast whose episodes have all ended has "
            "no uncertainty left."
        )
    if assess.bias_correction == "shuffle":
        text += (
            " The epistemic part is corrected for the histogram's sampling bias (minus the "
            "divergence of the same samples with shuffled member labels)."
        )
    return text + (
        " Brier and ECE compare each start state's forecast with the outcomes of its real episodes."
    )


def _markdown(
    rows, overall, checks, by_window, figures, gif, run_dir: Path, residual: bool, texts: dict
) -> str:
    table = (run_dir / "table.md").read_text()
    order = ("data", "models", "agent", "forecast", "truth", "report")
    found = {p.stem: p for p in (run_dir / MARKERS).glob("*.json")}
    stages = {
        name: read_json(found[name], "stage marker", checksum=True)
        for name in order
        if name in found
    }
    lines = [
        "# Pusher competency assessment",
        "",
        "Forecasts of the agent's outcome (ball within the success radius of the target within "
        "the time limit), made in imagination with an ensemble of recurrent conditional VAEs, "
        "then checked against real rollouts of the same agent from the same start states.",
        "",
        "## Table (the paper's Table 1, plus the check against reality)",
        "",
        texts["bits"],
        "",
        table,
        f"Over all start states: Brier {overall['brier']:.4f} against "
        f"{overall['constant_brier']:.4f} for a constant forecast equal to the overall success "
        f"rate ({overall['success_rate']:.3f}).",
        "",
        "## Checks",
        "",
        "| check | measured | met |",
        "|:---|---:|:---:|",
        *[
            f"| {escape_cell(name)} | {c['value']:.3f} | {'yes' if c['met'] else 'no'} |"
            for name, c in checks.items()
        ],
        "",
        "## The pattern over the first seconds",
        "",
        "The checks above average the bits over the whole horizon, as the paper's table does. "
        "The same ratios with the bits averaged over the first seconds only"
        + (
            "; and, last, per live step: each start's bits summed over time and divided by the "
            "steps its imagined episodes run on average. An ended episode counts as certain, so "
            "a time mean also measures how long the episodes last; this row takes that out."
            if "per live step" in by_window
            else ":"
        ),
        "",
        "| window | aleatoric stochastic / deterministic | epistemic out-of-distribution / "
        "deterministic | aleatoric out-of-distribution / deterministic |",
        "|:---|---:|---:|---:|",
        *[
            f"| {w} | {r['aleatoric_stochastic_over_deterministic']:.2f} | "
            f"{r['epistemic_ood_over_deterministic']:.2f} | "
            f"{r['aleatoric_ood_over_deterministic']:.2f} |"
            for w, r in by_window.items()
        ],
        "",
        "## Uncertainty over time (the paper's Figure 1)",
        "",
        f"![uncertainty over time]({figures['uncertainty'].name})",
        "",
        "## Calibration",
        "",
        f"![reliability]({figures['reliability'].name})",
        "",
        "## Forecast against reality",
        "",
        f"![forecast vs reality]({figures['forecast_vs_reality'].name})",
        "",
        "## The agent",
        "",
        f"{_AGENT_TEXT[residual]}; it is the agent that acts in the real env and the one forecast.",
        "",
        texts["agent"],
        "",
        f"One episode: {'![episode](episode.gif)' if gif == 'episode.gif' else gif}",
        "",
        "## Stages",
        "",
        *[f"- {name}: {_stage_time(s)}" for name, s in stages.items()],
        "",
    ]
    return "\n".join(lines)
