"""Reporting: tables and figures of competency assessments."""

from .figures import (
    forecast_vs_reality_figure,
    hold_after_success,
    plot_forecast_vs_reality,
    plot_reliability,
    plot_uncertainty_over_time,
    reliability_figure,
    uncertainty_figure,
)
from .tables import format_table, write_table

__all__ = [
    # figures
    "forecast_vs_reality_figure",
    "hold_after_success",
    "plot_forecast_vs_reality",
    "plot_reliability",
    "plot_uncertainty_over_time",
    "reliability_figure",
    "uncertainty_figure",
    # tables
    "format_table",
    "write_table",
]
