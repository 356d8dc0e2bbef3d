"""Figures of a competency assessment (matplotlib without pyplot: no global backend change).

- :func:`uncertainty_figure` / :func:`plot_uncertainty_over_time`: the paper's Figure 1,
  aleatoric and epistemic entropy over time for groups of state dimensions, one colour per
  condition.
- :func:`reliability_figure` / :func:`plot_reliability`: forecast P(success) against the observed
  frequency, marker areas proportional to the bins' counts, the counts printed beneath.
- :func:`forecast_vs_reality_figure` / :func:`plot_forecast_vs_reality`: a forecast band and the
  real trajectories of the same starts, the imagined episodes ending as the real ones do.

The ``*_figure`` functions return the :class:`~matplotlib.figure.Figure` (to show or adjust);
the ``plot_*`` functions draw it and write the PNG atomically. Every figure uses matplotlib's
constrained layout and one legend for all its panels.
"""

from __future__ import annotations

import io
import itertools
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
from matplotlib.figure import Figure

from rcvae_torchrl._checks import check_positive, check_tensor
from rcvae_torchrl.competency import ReliabilityDiagram
from rcvae_torchrl.io import atomic_write

__all__ = [
    "forecast_vs_reality_figure",
    "hold_after_success",
    "plot_forecast_vs_reality",
    "plot_reliability",
    "plot_uncertainty_over_time",
    "reliability_figure",
    "uncertainty_figure",
]

_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")
_MARKERS = ("o", "s", "^", "D", "v", "P")


def _nonempty(name: str, value: object) -> None:
    """A figure of nothing is refused by name (matplotlib's own error names none of ours)."""
    if not isinstance(value, (Mapping, Sequence)) or isinstance(value, str):
        raise TypeError(f"{name}: expected a mapping or a sequence, got {type(value).__name__}")
    if len(value) == 0:
        raise ValueError(f"{name}: expected at least one entry to draw, got none")


def _save(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` atomically in the format its suffix names (``.png``, ``.pdf``, ``.svg``,
    ...; a path without one is refused: matplotlib would pick PNG bytes for any name)."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a str or a path, got {type(path).__name__}")
    kind = Path(path).suffix.lstrip(".").lower()
    formats = fig.canvas.get_supported_filetypes()
    if kind not in formats:
        raise ValueError(
            f"path: expected a file name ending in one of {sorted('.' + k for k in formats)}, "
            f"got {str(path)!r}"
        )
    buffer = io.BytesIO()
    fig.savefig(buffer, format=kind, dpi=120)
    return atomic_write(path, lambda f: f.write(buffer.getvalue()))


def _shared_legend(fig: Figure, axes: Sequence, columns: int) -> None:
    """One legend above the panels with every label of ``axes`` once."""
    handles: dict[str, object] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, handle)
    fig.legend(
        handles.values(),
        handles.keys(),
        loc="outside upper center",
        ncols=min(columns, len(handles)),
        fontsize=8,
        frameon=False,
    )


def uncertainty_figure(
    curves: Mapping[str, Mapping[str, torch.Tensor]],
    panels: Mapping[str, Sequence[int]],
    dt: float,
) -> Figure:
    """Aleatoric (dashed, top row) and epistemic (solid, bottom row) entropy over time.

    One column per group of state dimensions, one colour per condition. The two parts get their
    own rows (and y scales): the epistemic bits are often an order of magnitude below the
    aleatoric ones and would lie flat on a shared axis.

    Args:
        curves: condition -> ``{"aleatoric": [T, D], "epistemic": [T, D]}`` bits per dimension
            and step (already averaged over start states).
        panels: panel title -> state-dimension indices summed in that panel.
        dt: seconds per step.
    """
    _nonempty("curves", curves)
    _nonempty("panels", panels)
    check_positive("dt", dt)
    for condition, parts in curves.items():
        for part in ("aleatoric", "epistemic"):
            bits = parts.get(part) if isinstance(parts, Mapping) else None
            if not isinstance(bits, torch.Tensor) or bits.ndim != 2:
                raise ValueError(
                    f"curves[{condition!r}][{part!r}]: expected bits [T, D], got "
                    f"{tuple(bits.shape) if isinstance(bits, torch.Tensor) else bits!r}"
                )
            for title, dims in panels.items():
                if any(not -bits.shape[1] <= d < bits.shape[1] for d in dims):
                    raise ValueError(
                        f"panels[{title!r}]: expected dimension indices below D={bits.shape[1]} "
                        f"(those of curves[{condition!r}]), got {list(dims)}"
                    )
    fig = Figure(figsize=(3.8 * len(panels), 5.4), layout="constrained")
    grid = fig.subplots(2, len(panels), squeeze=False, sharex=True)
    for column, (title, dims) in enumerate(panels.items()):
        for row, (part, style) in enumerate((("aleatoric", "--"), ("epistemic", "-"))):
            ax = grid[row][column]
            for i, (condition, parts) in enumerate(curves.items()):
                colour = _COLOURS[i % len(_COLOURS)]  # every condition drawn, colours reused
                t = torch.arange(1, parts[part].shape[0] + 1) * dt
                ax.plot(
                    t,
                    parts[part][:, list(dims)].sum(-1),
                    color=colour,
                    lw=1.4,
                    ls=style,
                    label=f"{condition} {part}",
                )
            ax.grid(alpha=0.3)
        grid[0][column].set_title(title, fontsize=10)
        grid[1][column].set_xlabel("time (s)")
    grid[0][0].set_ylabel("aleatoric (bits)")
    grid[1][0].set_ylabel("epistemic (bits)")
    _shared_legend(fig, grid[:, 0], columns=2)  # a column per part
    return fig


def plot_uncertainty_over_time(
    curves: Mapping[str, Mapping[str, torch.Tensor]],
    panels: Mapping[str, Sequence[int]],
    dt: float,
    path: str | Path,
) -> Path:
    """:func:`uncertainty_figure` written to the PNG file ``path``."""
    return _save(uncertainty_figure(curves, panels, dt), path)


def reliability_figure(
    diagrams: Mapping[str, ReliabilityDiagram], counts_floor: int = 1, dodge: float = 0.012
) -> Figure:
    """Reliability diagram: mean forecast against observed frequency per bin and condition.

    Each condition has its own colour and (hollow) marker, with an area proportional to the
    bin's count; conditions are dodged sideways by ``dodge`` (forecast units) so that points at
    the same place, e.g. (1, 1), stay visible. The table beneath prints every bin's count.
    Bins with fewer than ``counts_floor`` episodes are not drawn.
    """
    _nonempty("diagrams", diagrams)
    if not isinstance(diagrams, Mapping):
        raise TypeError(
            f"diagrams: expected a mapping of condition name to ReliabilityDiagram, got "
            f"{type(diagrams).__name__}"
        )
    edges = {name: tuple(d.bin_edges.tolist()) for name, d in diagrams.items()}
    if len(set(edges.values())) > 1:  # one table of counts, one column per bin
        sizes = {name: len(e) - 1 for name, e in edges.items()}
        raise ValueError(f"diagrams: expected the same bins in every diagram, got {sizes} bins")
    fig = Figure(figsize=(5.2, 5.4), layout="constrained")
    ax, table_ax = fig.subplots(2, 1, height_ratios=(5, 1.1 + 0.25 * len(diagrams)))
    ax.plot([0, 1], [0, 1], color="grey", lw=1, ls=":", label="perfect calibration")
    largest = max(int(d.counts.max()) for d in diagrams.values()) or 1
    offsets = (torch.arange(len(diagrams)) - (len(diagrams) - 1) / 2) * dodge
    for i, (name, d) in enumerate(diagrams.items()):
        keep = d.counts >= counts_floor
        x, y = d.mean_forecast[keep] + offsets[i], d.frequency[keep]
        colour, marker = _COLOURS[i % len(_COLOURS)], _MARKERS[i % len(_MARKERS)]
        ax.plot(x, y, "-", color=colour, lw=1, alpha=0.6)
        ax.scatter(
            x,
            y,
            s=20 + 280 * d.counts[keep].float() / largest,
            marker=marker,
            facecolors="none",
            edgecolors=colour,
            linewidths=1.6,
            clip_on=False,
            label=f"{name} ({int(d.counts.sum())} episodes)",
        )
    ax.set(
        xlim=(-0.04, 1.04),
        ylim=(-0.04, 1.04),
        xlabel="forecast P(success)",
        ylabel="observed success frequency",
    )
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    _shared_legend(fig, [ax], columns=2)
    _count_table(table_ax, diagrams)
    return fig


def _count_table(ax, diagrams: Mapping[str, ReliabilityDiagram]) -> None:
    edges = next(iter(diagrams.values())).bin_edges.tolist()
    columns = [f"{lo:.1f}-{hi:.1f}" for lo, hi in itertools.pairwise(edges)]
    ax.axis("off")
    table = ax.table(
        cellText=[[str(int(c)) for c in d.counts] for d in diagrams.values()],
        rowLabels=list(diagrams),
        colLabels=columns,
        loc="center",
        cellLoc="center",
    )
    table.auto_set_font_size(False)
    table.set_fontsize(8)
    ax.set_title("episodes per forecast bin", fontsize=8)


def plot_reliability(
    diagrams: Mapping[str, ReliabilityDiagram], path: str | Path, counts_floor: int = 1
) -> Path:
    """:func:`reliability_figure` written to the PNG file ``path``."""
    return _save(reliability_figure(diagrams, counts_floor), path)


def hold_after_success(
    samples: torch.Tensor, threshold: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Imagined episodes that end at success, as the real env's do.

    Args:
        samples: ``[M, T]`` a quantity over time whose success is ``value <= threshold`` (e.g. a
            distance to the target); NaN where an episode had already ended.
        threshold: the success boundary.

    Returns:
        ``held`` ``[M, T]``: each sample held at its value at its first success from then on;
        ``ended`` ``[T]``: the fraction of the samples that have succeeded by each step.
    """
    check_tensor("samples", samples)
    if samples.ndim != 2 or samples.shape[1] == 0:
        raise ValueError(f"samples: expected [M, T >= 1], got shape {tuple(samples.shape)}")
    success = (samples <= threshold).cumsum(-1) > 0
    first = torch.where(success.any(-1), success.float().argmax(-1), samples.shape[-1] - 1)
    at_success = samples.gather(-1, first[:, None]).expand_as(samples)
    held = torch.where(success, at_success, samples)
    return held, success.float().mean(0)


def forecast_vs_reality_figure(
    panels: Sequence[Mapping[str, object]],
    dt: float,
    ylabel: str = "distance to the goal",
    threshold: float | None = None,
) -> Figure:
    """One panel per start state: forecast median and 5-95 % band, and the real trajectories.

    Each panel is a mapping with ``"title"``, ``"forecast"`` ``[M, T]`` (samples of the quantity
    over time) and ``"real"`` (a list of 1-D tensors, one per real run, any lengths: a real run
    stops when its episode ends). With a success ``threshold`` the imagined episodes end there
    too: each sample is held at its value at success (:func:`hold_after_success`), and the
    panel prints the fraction of imagined and real episodes that reached it by the horizon. The
    panels share the y axis.
    """
    _nonempty("panels", panels)
    check_positive("dt", dt)
    for i, panel in enumerate(panels):
        _check_panel(f"panels[{i}]", panel)
    fig = Figure(figsize=(3.3 * len(panels) + 0.6, 3.6), layout="constrained")
    axes = list(fig.subplots(1, len(panels), squeeze=False, sharey=True)[0])
    for ax, panel in zip(axes, panels):
        _forecast_panel(ax, panel, dt, threshold)
    axes[0].set_ylabel(ylabel)
    _shared_legend(fig, axes, columns=5)
    return fig


def _check_panel(name: str, panel: object) -> None:
    """One panel of :func:`forecast_vs_reality_figure`: a title, samples ``[M, T]`` and real
    runs (1-D tensors)."""
    if not isinstance(panel, Mapping) or not {"title", "forecast", "real"} <= set(panel):
        raise ValueError(
            f"{name}: expected a mapping with 'title', 'forecast' [M, T] and 'real' (1-D "
            f"tensors), got {type(panel).__name__}"
            + (f" with keys {sorted(map(str, panel))}" if isinstance(panel, Mapping) else "")
        )
    forecast = panel["forecast"]
    if not isinstance(forecast, torch.Tensor) or forecast.ndim != 2:
        got = tuple(forecast.shape) if isinstance(forecast, torch.Tensor) else forecast
        raise ValueError(f"{name}['forecast']: expected samples [M, T] (a tensor), got {got!r}")
    runs = panel["real"]
    if not isinstance(runs, (list, tuple)) or not all(
        isinstance(r, torch.Tensor) and r.ndim == 1 for r in runs
    ):
        raise ValueError(f"{name}['real']: expected a list of 1-D tensors (one per run)")


def _forecast_panel(ax, panel: Mapping[str, object], dt: float, threshold: float | None) -> None:
    forecast = panel["forecast"]
    if threshold is not None:
        forecast, ended = hold_after_success(forecast, threshold)
    t = torch.arange(1, forecast.shape[-1] + 1) * dt
    lo, mid, hi = torch.nanquantile(forecast, torch.tensor([0.05, 0.5, 0.95]), dim=0)
    ax.fill_between(t, lo, hi, color="tab:blue", alpha=0.25, lw=0, label="forecast 5-95 %")
    ax.plot(t, mid, color="tab:blue", lw=1.4, label="forecast median")
    for i, real in enumerate(panel["real"]):
        steps = torch.arange(1, len(real) + 1) * dt
        ax.plot(steps, real, color="black", lw=0.9, alpha=0.8, label="real" if i == 0 else None)
        ax.plot(steps[-1:], real[-1:], "o", color="black", ms=3, label="real episode ends")
    if threshold is not None:
        ax.axhline(threshold, color="tab:green", lw=1, ls="--", label="success boundary")
        real_ended = sum(bool((r <= threshold).any()) for r in panel["real"])
        ax.text(
            0.97,
            0.95,
            f"at the boundary by {t[-1]:.0f} s:\nimagined {ended[-1]:.0%}, "
            f"real {real_ended} of {len(panel['real'])}",
            transform=ax.transAxes,
            ha="right",
            va="top",
            fontsize=7,
            bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
        )
    ax.set_title(str(panel["title"]), fontsize=9)
    ax.set_xlabel("time (s)")
    ax.grid(alpha=0.3)


def plot_forecast_vs_reality(
    panels: Sequence[Mapping[str, object]],
    dt: float,
    path: str | Path,
    ylabel: str = "distance to the goal",
    threshold: float | None = None,
) -> Path:
    """:func:`forecast_vs_reality_figure` written to the PNG file ``path``."""
    return _save(forecast_vs_reality_figure(panels, dt, ylabel, threshold), path)
