"""Tables and figures of a competency assessment."""

import matplotlib.image
import pytest
import torch

from rcvae_torchrl.competency import reliability_diagram
from rcvae_torchrl.reporting import (
    format_table,
    plot_forecast_vs_reality,
    plot_reliability,
    plot_uncertainty_over_time,
    write_table,
)


def test_tables(tmp_path):
    rows = [
        {"condition": "deterministic", "total": 0.5051, "n": 3},
        {"condition": "stochastic", "total": 0.79, "n": 4},
    ]
    md, csv = format_table(rows, ["condition", "total", "n"], digits=2)
    assert md.splitlines()[0] == "| condition | total | n |"
    assert "| deterministic | 0.51 | 3 |" in md
    assert csv.splitlines() == ["condition,total,n", "deterministic,0.5051,3", "stochastic,0.79,4"]
    md_path, csv_path = write_table(rows, ["condition", "n"], tmp_path / "table")
    assert md_path.read_text().count("\n") == 4 and csv_path.exists()
    with pytest.raises(KeyError, match="missing"):
        format_table(rows, ["condition", "absent"])


def _image(path):
    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100
    assert image[..., :3].std() > 0.01, "the figure should not be blank"
    return image


def test_figures(tmp_path):
    t, d = 50, 14
    curves = {
        c: {"aleatoric": torch.rand(t, d) * s, "epistemic": torch.rand(t, d)}
        for c, s in [("deterministic", 0.1), ("stochastic", 1.0)]
    }
    _image(
        plot_uncertainty_over_time(
            curves, {"arm": [6, 7], "ball velocity": [10, 11]}, 0.05, tmp_path / "u.png"
        )
    )
    forecast = torch.rand(200)
    outcome = torch.rand(200) < forecast
    diagram = reliability_diagram(forecast, outcome.float(), n_bins=5)
    _image(plot_reliability({"all": diagram}, tmp_path / "r.png"))
    panel = {"title": "start 0", "forecast": torch.rand(40, t), "real": [torch.rand(30)]}
    _image(plot_forecast_vs_reality([panel, panel], 0.05, tmp_path / "f.png", threshold=0.03))
