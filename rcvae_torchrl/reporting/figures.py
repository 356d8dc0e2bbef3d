"""Figures of a competency assessment (matplotlib without pyplot: no global backend change).

- :func:`plot_uncertainty_over_time`: the paper's Figure 1, aleatoric and epistemic entropy over
  time for groups of state dimensions, one colour per condition.
- :func:`plot_reliability`: forecast P(success) against the observed frequency.
- :func:`plot_forecast_vs_reality`: a forecast band and the real trajectories of the same starts.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from matplotlib.figure import Figure

from rcvae_torchrl.competency import ReliabilityDiagram
from rcvae_torchrl.io import atomic_write

__all__ = ["plot_forecast_vs_reality", "plot_reliability", "plot_uncertainty_over_time"]

_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


def _figure(panels: int, width: float, height: float) -> tuple[Figure, list]:
    fig = Figure(figsize=(width * panels, height))
    axes = fig.subplots(1, panels, squeeze=False)
    return fig, list(axes[0])


def _save(fig: Figure, path: str | Path) -> Path:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=120, bbox_inches="tight")
    return atomic_write(path, lambda f: f.write(buffer.getvalue()))


def plot_uncertainty_over_time(
    curves: Mapping[str, Mapping[str, torch.Tensor]],
    panels: Mapping[str, Sequence[int]],
    dt: float,
    path: str | Path,
) -> Path:
    """Aleatoric (dashed, top row) and epistemic (solid, bottom row) entropy over time.

    One column per group of state dimensions, one colour per condition. The two parts get their
    own rows (and y scales): the epistemic bits are often an order of magnitude below the
    aleatoric ones and would lie flat on a shared axis.

    Args:
        curves: condition -> ``{"aleatoric": [T, D], "epistemic": [T, D]}`` bits per dimension
            and step (already averaged over start states).
        panels: panel title -> state-dimension indices summed in that panel.
        dt: seconds per step.
        path: PNG file.
    """
    fig = Figure(figsize=(4.2 * len(panels), 5.6))
    grid = fig.subplots(2, len(panels), squeeze=False, sharex=True)
    for column, (title, dims) in enumerate(panels.items()):
        for row, (part, style) in enumerate((("aleatoric", "--"), ("epistemic", "-"))):
            ax = grid[row][column]
            for colour, (condition, parts) in zip(_COLOURS, curves.items()):
                t = torch.arange(1, parts[part].shape[0] + 1) * dt
                ax.plot(
                    t,
                    parts[part][:, list(dims)].sum(-1),
                    color=colour,
                    lw=1.4,
                    ls=style,
                    label=f"{condition} {part}",
                )
            ax.set(ylabel=f"{part} (bits)")
            ax.grid(alpha=0.3)
        grid[0][column].set(title=title)
        grid[1][column].set(xlabel="time (s)")
    for row in grid:
        row[-1].legend(fontsize=7, loc="best")
    fig.tight_layout()
    return _save(fig, path)


def plot_reliability(
    diagrams: Mapping[str, ReliabilityDiagram], path: str | Path, counts_floor: int = 1
) -> Path:
    """Reliability diagram: mean forecast against observed frequency per bin and condition."""
    fig, (ax,) = _figure(1, 4.6, 4.2)
    ax.plot([0, 1], [0, 1], color="grey", lw=1, ls=":", label="perfect calibration")
    for colour, (name, d) in zip(_COLOURS, diagrams.items()):
        keep = d.counts >= counts_floor
        ax.plot(d.mean_forecast[keep], d.frequency[keep], "o-", color=colour, label=name)
    ax.set(
        xlim=(-0.02, 1.02),
        ylim=(-0.02, 1.02),
        xlabel="forecast P(success)",
        ylabel="observed success frequency",
        title="Reliability",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def plot_forecast_vs_reality(
    panels: Sequence[Mapping[str, object]],
    dt: float,
    path: str | Path,
    ylabel: str = "ball to target (m)",
    threshold: float | None = None,
) -> Path:
    """One panel per episode: forecast median and 5-95 % band, and the real trajectories.

    Each panel is a mapping with ``"title"``, ``"forecast"`` ``[M, T]`` (samples of the quantity
    over time) and ``"real"`` (a list of 1-D tensors, one per real run, any lengths).
    """
    fig, axes = _figure(len(panels), 4.0, 3.2)
    for ax, panel in zip(axes, panels):
        forecast = panel["forecast"]
        t = torch.arange(1, forecast.shape[-1] + 1) * dt
        lo, mid, hi = torch.quantile(forecast, torch.tensor([0.05, 0.5, 0.95]), dim=0)
        ax.fill_between(t, lo, hi, color="tab:blue", alpha=0.25, label="forecast 5-95 %")
        ax.plot(t, mid, color="tab:blue", lw=1.2, label="forecast median")
        for i, real in enumerate(panel["real"]):
            ax.plot(
                torch.arange(1, len(real) + 1) * dt,
                real,
                color="black",
                lw=0.9,
                alpha=0.8,
                label="real" if i == 0 else None,
            )
        if threshold is not None:
            ax.axhline(threshold, color="tab:green", lw=1, ls="--", label="success boundary")
        ax.set(title=str(panel["title"]), xlabel="time (s)", ylabel=ylabel)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    return _save(fig, path)
