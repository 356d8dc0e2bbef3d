"""Reporting: tables and figures of competency assessments."""

from .figures import plot_forecast_vs_reality, plot_reliability, plot_uncertainty_over_time
from .tables import format_table, write_table

__all__ = [
    # figures
    "plot_forecast_vs_reality",
    "plot_reliability",
    "plot_uncertainty_over_time",
    # tables
    "format_table",
    "write_table",
]
