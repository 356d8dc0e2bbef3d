"""Reporting: tables and figures of competency assessments."""

from rcvae_torchrl._text import signed

from .figures import (
    forecast_vs_reality_figure,
    hold_after_success,
    plot_forecast_vs_reality,
    plot_reliability,
    plot_uncertainty_over_time,
    reliability_figure,
    uncertainty_figure,
)
from .tables import escape_cell, format_table, write_table
from .validation_figures import plot_competency_surface, plot_start_reliability

__all__ = [
    # figures
    "forecast_vs_reality_figure",
    "hold_after_success",
    "plot_forecast_vs_reality",
    "plot_reliability",
    "plot_uncertainty_over_time",
    "reliability_figure",
    "uncertainty_figure",
    # forecast against reality
    "plot_competency_surface",
    "plot_start_reliability",
    # tables
    "signed",
    "escape_cell",
    "format_table",
    "write_table",
]
