"""Reporting: tables and figures of competency assessments."""

from .figures import plot_forecast_vs_reality, plot_reliability, plot_uncertainty_over_time
from .tables import format_table, write_table
from .validation_figures import plot_competency_surface, plot_start_reliability

__all__ = [
    # figures
    "plot_forecast_vs_reality",
    "plot_reliability",
    "plot_uncertainty_over_time",
    # forecast against reality
    "plot_competency_surface",
    "plot_start_reliability",
    # tables
    "format_table",
    "write_table",
]
