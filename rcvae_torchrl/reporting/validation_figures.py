"""Figures of a forecast held against reality, start state by start state.

- :func:`plot_start_reliability`: per bin of start-state forecasts, the real success frequency
  of their episodes with its confidence interval, the bin's start and episode counts printed.
- :func:`plot_competency_surface`: P(success) over a grid of boundaries (success radius x
  deadline), forecast beside real.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from matplotlib.figure import Figure

from rcvae_torchrl.competency import StartReliability

from .figures import _COLOURS, _MARKERS, _nonempty, _save

__all__ = ["plot_competency_surface", "plot_start_reliability"]


def plot_start_reliability(diagrams: Mapping[str, StartReliability], path) -> object:
    """Reliability over start states, one colour and marker per condition.

    Each bin is drawn at its mean forecast against the pooled success frequency of its
    episodes, with the binomial interval as an error bar; markers grow with the bin's start
    states and conditions are offset sideways by a little so that coinciding bins stay visible.
    """
    _nonempty("diagrams", diagrams)
    fig = Figure(figsize=(5.6, 5.0), layout="constrained")
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1], color="grey", lw=1, ls=":", label="perfect calibration")
    offsets = torch.linspace(-0.012, 0.012, max(len(diagrams), 1))
    for k, (name, d) in enumerate(diagrams.items()):
        keep = d.episodes > 0
        x = d.mean_forecast[keep] + offsets[k]
        y, low, high = d.frequency[keep], d.low[keep], d.high[keep]
        colour, marker = _COLOURS[k % len(_COLOURS)], _MARKERS[k % len(_MARKERS)]
        ax.errorbar(
            x, y, yerr=torch.stack([y - low, high - y]), fmt="none", ecolor=colour, alpha=0.6
        )
        sizes = 20 + 8 * d.starts[keep].to(torch.float64)
        ax.scatter(x, y, s=sizes, color=colour, marker=marker, label=name, alpha=0.85, zorder=3)
        for xi, yi, n, m in zip(x, y, d.starts[keep], d.episodes[keep]):
            ax.annotate(
                f"{int(n)}/{int(m)}",
                (float(xi), float(yi)),
                textcoords="offset points",
                xytext=(6, -10 - 9 * k),
                fontsize=6,
                color=colour,
            )
    ax.set(
        xlim=(-0.04, 1.04),
        ylim=(-0.04, 1.04),
        xlabel="forecast P(success) of the start state",
        ylabel="real success frequency (95% interval)",
        title="Reliability over start states (labels: starts/episodes per bin)",
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    return _save(fig, path)


def plot_competency_surface(
    surfaces: Mapping[str, Mapping[str, torch.Tensor]],
    radii: Sequence[float],
    deadlines_s: Sequence[float],
    path,
) -> object:
    """P(success) on a grid of boundaries, forecast and real side by side per condition.

    Args:
        surfaces: condition -> ``{"forecast": [R, D], "real": [R, D]}`` probabilities (mean over
            start states) for ``radii`` (m) x ``deadlines_s`` (s).
    """
    _nonempty("surfaces", surfaces)
    grid = (len(radii), len(deadlines_s))
    for name, s in surfaces.items():
        for kind in ("forecast", "real"):
            got = tuple(s[kind].shape) if kind in s else None
            if got != grid:
                raise ValueError(
                    f"surfaces[{name!r}][{kind!r}]: expected a grid of len(radii) x "
                    f"len(deadlines_s) = {grid}, got {got}"
                )
            if not bool(((s[kind] >= 0) & (s[kind] <= 1)).all()):  # NaN fails too
                raise ValueError(
                    f"surfaces[{name!r}][{kind!r}]: expected probabilities in [0, 1], got "
                    f"values from {float(s[kind].min()):g} to {float(s[kind].max()):g}"
                )
    rows = len(surfaces)
    fig = Figure(figsize=(8.4, 2.6 * rows + 0.6), layout="constrained")
    axes = fig.subplots(rows, 2, squeeze=False)
    image = None
    for row, (name, s) in zip(axes, surfaces.items()):
        for ax, kind in zip(row, ("forecast", "real")):
            grid = s[kind].to(torch.float64)
            image = ax.imshow(grid, vmin=0, vmax=1, cmap="viridis", origin="lower", aspect="auto")
            for (i, j), value in zip(
                ((i, j) for i in range(grid.shape[0]) for j in range(grid.shape[1])),
                grid.reshape(-1),
            ):
                ax.text(
                    j,
                    i,
                    f"{value:.2f}",
                    ha="center",
                    va="center",
                    fontsize=7,
                    color="white" if value < 0.6 else "black",
                )
            ax.set_xticks(range(len(deadlines_s)), [f"{d:g}" for d in deadlines_s])
            ax.set_yticks(range(len(radii)), [f"{100 * r:g}" for r in radii])
            ax.set(xlabel="deadline (s)", ylabel="radius (cm)", title=f"{name}: {kind}")
    fig.colorbar(image, ax=axes, shrink=0.8, label="P(success)")
    return _save(fig, path)
