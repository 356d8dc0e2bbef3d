"""Tables and figures of a competency assessment."""

import itertools

import matplotlib.image
import pytest
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg

from rcvae_torchrl.competency import reliability_diagram
from rcvae_torchrl.reporting import (
    escape_cell,
    forecast_vs_reality_figure,
    format_table,
    hold_after_success,
    plot_forecast_vs_reality,
    plot_reliability,
    plot_uncertainty_over_time,
    reliability_figure,
    uncertainty_figure,
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
    piped = [{"check": "|forecast - real| <= 0.1", "a|b": 0.25}]
    md, csv = format_table(piped, ["check", "a|b"])
    assert md.splitlines() == [
        "| check | a\\|b |",
        "|:---|---:|",
        "| \\|forecast - real\\| <= 0.1 | 0.250 |",  # a bare | would end the cell
    ]
    assert csv.splitlines()[1] == "|forecast - real| <= 0.1,0.25"  # CSV keeps the text
    assert escape_cell("a|b|") == "a\\|b\\|"


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


# ---------------------------------------------------------------- figures that read at a glance
CONDITIONS = ("deterministic", "stochastic", "out-of-distribution")


def _drawn_texts(fig):
    """The figure's texts that get drawn: tick labels of ticks inside the view only."""
    texts = [*fig.texts, *(t for legend in fig.legends for t in legend.get_texts())]
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis) if ax.axison else ():
            lo, hi = sorted(axis.get_view_interval())
            for loc, tick in zip(axis.get_majorticklocs(), axis.get_major_ticks()):
                if lo - 1e-9 <= loc <= hi + 1e-9:
                    texts += [tick.label1, tick.label2]
            texts += [axis.label, axis.get_offset_text()]
        texts += [ax.title, *ax.texts]
        if ax.get_legend() is not None:
            texts += ax.get_legend().get_texts()
        texts += [cell.get_text() for table in ax.tables for cell in table.get_celld().values()]
    return texts


def _texts(fig):
    """Every visible, non-empty drawn text of ``fig`` with its box on the canvas (pixels)."""
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)  # lays the figure out (constrained layout) as saving would
    return [
        (text.get_text(), text.get_window_extent(renderer))
        for text in _drawn_texts(fig)
        if text.get_visible() and text.get_text().strip()
    ]


def assert_no_text_overlaps(fig):
    texts = _texts(fig)
    assert len(texts) > 5
    clashes = [
        (a, b)
        for (a, box_a), (b, box_b) in itertools.combinations(texts, 2)
        if box_a.overlaps(box_b) and box_a.width > 0 and box_b.width > 0
    ]
    assert clashes == []
    width, height = fig.canvas.get_width_height()
    outside = [t for t, box in texts if box.x0 < -1 or box.y0 < -1 or box.x1 > width + 1]
    assert outside == [] and all(box.y1 <= height + 1 for _, box in texts)


def _legends(fig):
    return fig.legends, [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]


def test_uncertainty_figure_reads_at_a_glance():
    t, d = 60, 14
    g = torch.Generator().manual_seed(0)
    curves = {
        c: {
            "aleatoric": torch.rand(t, d, generator=g) * 40,
            "epistemic": torch.rand(t, d, generator=g),
        }
        for c in CONDITIONS
    }
    panels = {"arm position": [6, 7], "elbow angle": [2, 3], "ball velocity": [10, 11]}
    fig = uncertainty_figure(curves, panels, 0.05)
    assert_no_text_overlaps(fig)
    figure_legends, panel_legends = _legends(fig)
    assert len(figure_legends) == 1 and panel_legends == []
    labels = [t.get_text() for t in figure_legends[0].get_texts()]
    assert labels == [f"{c} {p}" for p in ("aleatoric", "epistemic") for c in CONDITIONS]
    ylabels = [a.get_ylabel() for a in fig.axes]  # row by row: only the first column's
    assert ylabels == ["aleatoric (bits)", "", "", "epistemic (bits)", "", ""]


def test_reliability_keeps_coincident_points_visible_and_prints_counts():
    ones = torch.ones(20)
    diagrams = {
        "deterministic": reliability_diagram(ones * 0.999, ones, n_bins=5),
        "stochastic": reliability_diagram(
            torch.linspace(0.5, 0.8, 100), (torch.arange(100) % 3 != 0).float(), n_bins=5
        ),
        "out-of-distribution": reliability_diagram(ones * 0.995, ones, n_bins=5),
    }
    fig = reliability_figure(diagrams)
    assert_no_text_overlaps(fig)
    ax = fig.axes[0]
    points = {c.get_label(): c for c in ax.collections}
    det = points["deterministic (20 episodes)"].get_offsets()
    ood = points["out-of-distribution (20 episodes)"].get_offsets()
    assert det.shape == ood.shape == (1, 2)
    assert abs(det[0, 0] - ood[0, 0]) > 0.015  # dodged apart, not on top of each other
    markers = {c.get_label(): c.get_paths()[0].vertices.shape for c in ax.collections}
    assert len(set(markers.values())) == 3  # a distinct marker per condition
    sizes = points["stochastic (100 episodes)"].get_sizes()
    counts = diagrams["stochastic"].counts[diagrams["stochastic"].counts > 0]
    largest = max(int(d.counts.max()) for d in diagrams.values())
    assert largest == 66  # the stochastic condition's fullest bin (0.6-0.8)
    assert sizes.tolist() == pytest.approx((20 + 280 * counts.float() / largest).tolist())
    (table,) = fig.axes[1].tables
    cells = {key: cell.get_text().get_text() for key, cell in table.get_celld().items()}
    header = [cells[0, j] for j in range(5)]
    assert header == ["0.0-0.2", "0.2-0.4", "0.4-0.6", "0.6-0.8", "0.8-1.0"]
    for i, (name, d) in enumerate(diagrams.items(), start=1):  # every bin's count printed
        assert cells[i, -1] == name
        assert [cells[i, j] for j in range(5)] == [str(int(c)) for c in d.counts]
    figure_legends, panel_legends = _legends(fig)
    assert len(figure_legends) == 1 and panel_legends == []


def test_imagined_episodes_end_at_success_like_the_real_ones():
    samples = torch.tensor([[0.10, 0.05, 0.02, 0.04, 0.08], [0.10, 0.09, 0.08, 0.07, 0.06]])
    held, ended = hold_after_success(samples, 0.03)
    assert held[0].tolist() == pytest.approx([0.10, 0.05, 0.02, 0.02, 0.02])
    assert torch.equal(held[1], samples[1])
    assert ended.tolist() == [0.0, 0.0, 0.5, 0.5, 0.5]
    with pytest.raises(ValueError, match=r"samples: expected \[M, T >= 1\]"):
        hold_after_success(samples[0], 0.03)


def test_forecast_median_reaches_the_boundary_when_most_episodes_succeed():
    t, m = 100, 200
    g = torch.Generator().manual_seed(1)
    # every imagined episode reaches 0.01 m by step 60, then drifts away to 0.065 m
    approach = torch.linspace(0.15, 0.01, 60).expand(m, 60)
    drift = torch.linspace(0.01, 0.065, t - 60).expand(m, t - 60)
    forecast = torch.cat([approach, drift], 1) + 0.002 * torch.rand(m, t, generator=g)
    real = [torch.linspace(0.15, 0.02, 55), torch.linspace(0.15, 0.025, 62)]
    panels = [
        {"title": f"{c}, start 0\nforecast P(success) = 1.00", "forecast": forecast, "real": real}
        for c in CONDITIONS
    ]
    fig = forecast_vs_reality_figure(panels, 0.05, threshold=0.03)
    assert_no_text_overlaps(fig)
    ax = fig.axes[0]
    median = next(line for line in ax.get_lines() if line.get_label() == "forecast median")
    assert median.get_ydata()[-1] <= 0.03  # held at success: the median ends below the line
    notes = [t.get_text() for t in ax.texts]
    assert notes == ["at the boundary by 5 s:\nimagined 100%, real 2 of 2"]
    figure_legends, panel_legends = _legends(fig)
    assert len(figure_legends) == 1 and panel_legends == []
    labels = [t.get_text() for t in figure_legends[0].get_texts()]
    assert labels == [
        "forecast 5-95 %",
        "forecast median",
        "real",
        "real episode ends",
        "success boundary",
    ]
    assert [a.get_ylabel() for a in fig.axes] == ["distance to the goal", "", ""]


def test_figures_of_nothing_or_of_a_mislabelled_grid_are_refused(tmp_path):
    """Empty inputs failed inside matplotlib, naming none of ours; a surface whose grid does
    not match its radii and deadlines was drawn with wrong labels."""
    from rcvae_torchrl.reporting.validation_figures import plot_competency_surface

    with pytest.raises(ValueError, match="curves: expected at least one entry to draw"):
        plot_uncertainty_over_time({}, {"x": [0]}, 0.1, tmp_path / "u.png")
    with pytest.raises(ValueError, match="diagrams: expected at least one entry"):
        plot_reliability({}, tmp_path / "r.png")
    with pytest.raises(ValueError, match="panels: expected at least one entry"):
        plot_forecast_vs_reality([], 0.1, tmp_path / "f.png")
    with pytest.raises(ValueError, match="surfaces: expected at least one entry"):
        plot_competency_surface({}, [0.01], [5.0], tmp_path / "s.png")
    grid = {"c": {"forecast": torch.zeros(2, 3), "real": torch.zeros(2, 3)}}
    with pytest.raises(ValueError, match=r"surfaces\['c'\]\['forecast'\]: expected a grid of"):
        plot_competency_surface(grid, [0.01, 0.02, 0.03], [5.0, 10.0], tmp_path / "s.png")
    assert not list(tmp_path.iterdir())  # nothing written
    plot_competency_surface(grid, [0.01, 0.02], [5.0, 10.0, 15.0], tmp_path / "s.png")


def test_a_table_prints_a_tensor_as_its_number_and_refuses_negative_digits():
    from rcvae_torchrl.reporting import format_table

    markdown, csv_text = format_table([{"x": torch.tensor(0.12345), "n": 3}], ["x", "n"])
    assert "| 0.123 | 3 |" in markdown and "0.123" in csv_text and "tensor" not in markdown
    with pytest.raises(ValueError, match="digits: expected an integer >= 0, got -1"):
        format_table([{"x": 1.0}], ["x"], digits=-1)


def test_signed_never_writes_minus_zero():
    from rcvae_torchrl.reporting import signed

    assert [signed(x) for x in (-0.0004, -0.0, 0.0004, -0.0005001, 0.0123)] == [
        "+0.000",
        "+0.000",
        "+0.000",
        "-0.001",
        "+0.012",
    ]
    assert signed(-0.004, 2) == "+0.00" and signed(-0.006, 2) == "-0.01"
    assert signed(torch.tensor(-0.25)) == "-0.250" and signed(float("nan")) == "+nan"


def test_a_check_with_no_gap_reads_plus_zero():
    from rcvae_torchrl.training import OutcomeCheck

    forecast = torch.tensor([0.2, 0.5, 0.9, 0.4], dtype=torch.float64)
    real = forecast + torch.tensor([1e-4, 3e-4, -1e-4, 2e-4], dtype=torch.float64)
    check = OutcomeCheck(forecast, real, runs=10, min_starts=4)
    assert -0.0005 < check.gap < 0  # rounds to zero at 3 decimals
    text = check.describe()
    assert "gap +0.000" in text and "-0.000" not in text


def test_a_table_stem_keeps_its_dots_and_a_directory_is_refused(tmp_path):
    rows = [{"a": 1}]
    md, csv = write_table(rows, ["a"], tmp_path / "table_lr0.5")
    other, _ = write_table(rows, ["a"], tmp_path / "table_lr0.1")
    assert md.name == "table_lr0.5.md" and csv.name == "table_lr0.5.csv" and md != other
    with pytest.raises(ValueError, match="stem: expected a file name without its suffix"):
        write_table(rows, ["a"], tmp_path)
    with pytest.raises(TypeError, match="columns: expected a sequence of column names"):
        format_table(rows, "a")
    with pytest.raises(TypeError, match="rows: expected a sequence of rows"):
        format_table({"a": 1.0}, ["a"])


def test_a_figure_is_written_in_the_format_its_name_says(tmp_path):
    forecast = torch.rand(100, generator=torch.Generator().manual_seed(0))
    diagram = reliability_diagram(forecast, (forecast > 0.5).float(), n_bins=5)
    pdf = plot_reliability({"all": diagram}, tmp_path / "r.pdf")
    assert pdf.read_bytes().startswith(b"%PDF")
    assert plot_reliability({"all": diagram}, tmp_path / "r.png").read_bytes()[1:4] == b"PNG"
    with pytest.raises(ValueError, match="path: expected a file name ending in one of"):
        plot_reliability({"all": diagram}, tmp_path / "r")
    three = reliability_diagram(forecast, (forecast > 0.5).float(), n_bins=3)
    with pytest.raises(ValueError, match="expected the same bins in every diagram"):
        plot_reliability({"a": diagram, "b": three}, tmp_path / "r.png")


def test_every_condition_is_drawn_when_there_are_more_than_colours():
    curves = {
        f"c{i}": {"aleatoric": torch.ones(5, 2), "epistemic": torch.ones(5, 2)} for i in range(8)
    }
    fig = uncertainty_figure(curves, {"p": [0]}, 0.1)
    labels = [t.get_text() for t in _legends(fig)[0][0].get_texts()]
    assert {f"c{i} aleatoric" for i in range(8)} <= set(labels)


def test_figure_inputs_of_another_shape_are_named_before_matplotlib_sees_them(tmp_path):
    curves = {"a": {"aleatoric": torch.ones(5, 2), "epistemic": torch.ones(5, 2)}}
    with pytest.raises(ValueError, match=r"panels\['p'\]: expected dimension indices below D=2"):
        uncertainty_figure(curves, {"p": [0, 7]}, 0.1)
    with pytest.raises(ValueError, match=r"dt: expected a positive number, got '0\.1'"):
        uncertainty_figure(curves, {"p": [0]}, "0.1")
    with pytest.raises(ValueError, match=r"samples: expected \[M, T >= 1\], got shape \(3, 0\)"):
        hold_after_success(torch.rand(3, 0), 0.5)
    panel = {"title": "s", "forecast": torch.rand(6), "real": [torch.rand(4)]}
    with pytest.raises(ValueError, match=r"panels\[0\]\['forecast'\]: expected samples \[M, T\]"):
        forecast_vs_reality_figure([panel], 0.1)
    with pytest.raises(ValueError, match=r"panels\[0\]\['real'\]: expected a list of 1-D tensors"):
        forecast_vs_reality_figure([{**panel, "forecast": torch.rand(3, 6), "real": "x"}], 0.1)
    from rcvae_torchrl.reporting import plot_competency_surface

    surface = {"c": {"forecast": torch.full((2, 2), 3.0), "real": torch.rand(2, 2)}}
    with pytest.raises(ValueError, match=r"surfaces\['c'\]\['forecast'\]: expected probabilities"):
        plot_competency_surface(surface, [0.01, 0.02], [1.0, 2.0], tmp_path / "s.png")
