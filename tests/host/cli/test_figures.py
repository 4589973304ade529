"""Figures fit for a paper (host/cli/figures.py): each is rendered and what it draws is checked —
axis labels and units, legend entries, scales, data ranges, ticks, titles, no overlapping labels."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from host.cli import figures  # noqa: E402
from protocol.lattice import Lattice  # noqa: E402
from virtual_sheet.shapes import make_sheet  # noqa: E402

L = 0.01


@pytest.fixture
def gaussian():
    return make_sheet("gaussian", 14, 14, L)


def _legend(ax) -> list[str]:
    leg = ax.get_legend()
    return [t.get_text() for t in leg.get_texts()] if leg else []


def _bbox(fig, artist):
    fig.canvas.draw()
    return artist.get_window_extent(fig.canvas.get_renderer())


def test_demo_figure_overlays_the_estimate_on_the_truth_with_integer_ticks(gaussian, tmp_path):
    rng = np.random.Generator(np.random.MT19937(1))
    est = gaussian + rng.normal(scale=2e-4, size=gaussian.shape)
    err = rng.random((14, 14))
    fig = figures.demo_figure(tmp_path / "demo.png", gaussian, est, err, shape="gaussian", noise_pct_g=1.0,
                              rate_hz=30.0, run_mean_error_pct=0.42, counter=77, link_length=L)
    try:
        ax_truth, ax_over, ax_map = fig.axes[:3]
        # the run's summary figure, and the run's parameters, in the title (not the snapshot's mean)
        title = fig._suptitle.get_text()
        assert "run mean error 0.42 % of side" in title
        for part in ("14x14", "'gaussian'", "1 % g noise", "30 Hz", "L = 1 cm"):
            assert part in title
        assert _legend(ax_over) == ["virtual truth", "estimate (overlaid)"]  # drawn over the truth
        assert len(ax_over.collections) == 2 and _legend(ax_truth) == ["virtual truth"]
        for ax in (ax_truth, ax_over):
            assert (ax.get_xlabel(), ax.get_ylabel(), ax.get_zlabel()) == ("x [cm]", "y [cm]", "z [cm]")
            xs = ax.collections[0]._segments3d
            span = np.ptp(np.concatenate([np.asarray(s) for s in xs])[:, 0])
            assert 12 < span < 14  # 13 links of 1 cm, in cm
        ticks = np.concatenate([ax_map.get_xticks(), ax_map.get_yticks()])
        assert np.all(ticks == np.round(ticks)) and ticks.min() >= 0 and ticks.max() <= 13
        assert (ax_map.get_xlabel(), ax_map.get_ylabel()) == ("joint j", "joint i")
        assert "counter 77" in ax_map.get_title()
        # no label overlaps another panel's: the heat map's "joint i" is clear of the 3D z label
        zlab = _bbox(fig, ax_over.zaxis.label)
        ilab = _bbox(fig, ax_map.yaxis.label)
        assert not zlab.overlaps(ilab)
        assert zlab.x1 < _bbox(fig, ax_map).x0
    finally:
        plt.close(fig)
    assert (tmp_path / "demo.png").stat().st_size > 20_000


def test_gaussian_figure_is_in_cm_with_a_legend_per_panel(gaussian, tmp_path):
    ests = {"global": gaussian + 1e-5, "paper": gaussian - 1e-5}
    fig = figures.gaussian_figure(tmp_path / "g.png", gaussian, ests, {"global": 0.1, "paper": 3.8},
                                  shape="gaussian", noise_pct_g=0.0, seed=2008, link_length=L)
    try:
        assert len(fig.axes) == 3
        for ax in fig.axes:
            assert ax.get_xlabel() == "x [cm]" and ax.get_zlabel() == "z [cm]"
            lo, hi = ax.get_xlim()
            assert hi - lo > 10  # cm, not metres (0.13)
        assert _legend(fig.axes[1]) == ["model (truth)", "global estimate (overlaid)"]
        assert _legend(fig.axes[2]) == ["model (truth)", "paper estimate (overlaid)"]
        assert "3.80 % of side" in fig.axes[2].get_title()
        assert "seed 2008" in fig._suptitle.get_text() and "L = 1 cm" in fig._suptitle.get_text()
    finally:
        plt.close(fig)
    fig = figures.gaussian_figure(tmp_path / "g.png", gaussian, ests, {"global": 0.1, "paper": 3.8},
                                  shape="fig9", noise_pct_g=0.0, seed=2008, link_length=L,
                                  caption="Paper, Fig. 9: ...\nHere: a Gaussian, A = σ = S/4")
    try:  # the paper's description of its figure beside what is drawn, clear of the panels
        text = fig.texts[-1]
        assert "Paper, Fig. 9" in text.get_text() and "A = σ = S/4" in text.get_text()
        assert _bbox(fig, text).y1 < min(_bbox(fig, ax.xaxis.label).y0 for ax in fig.axes)
    finally:
        plt.close(fig)


def _results():
    rows = []
    for level, base in ((0.0, 0.0), (1.0, 0.1), (5.0, 0.6)):
        row = {"noise_pct_g": level}
        for k, m in enumerate(("global", "paper")):
            f = 1 + 30 * k
            row[m] = {"mean_pct": base * f * 1.1, "std_pct": base * f * 0.5, "time_ms": 1.0 + 400 * k}
        rows.append(row)
    sv = np.full((13, 13), 0.4)
    sv[0, 0], sv[6, 7] = 0.05, 0.08
    flat = {"map": sv.tolist(), "below_0_1": 2, "units": 169}
    tilted = {"map": np.full((13, 13), 0.7).tolist(), "below_0_1": 0, "units": 169}
    return {"fig9": {"rows": rows, "solvability": flat, "works_up_to_pct_g": {"paper": 1.0}},
            "fig9-tilted": {"rows": rows, "solvability": tilted, "works_up_to_pct_g": {"paper": None}}}


def test_noise_figure_draws_mean_and_std_as_the_paper_with_its_failure_line_and_the_units(tmp_path):
    res = _results()
    fig = figures.noise_figure(tmp_path / "n.png", res, ("global", "paper"), trials=10, seed=2008,
                               side_joints=14)
    try:
        err_axes = [a for a in fig.axes if a.get_ylabel() == "joint error [% of side]"]
        map_axes = [a for a in fig.axes if a.get_ylabel() == "unit i"]
        assert len(err_axes) == 2 and len(map_axes) == 2
        ax = err_axes[0]
        assert ax.get_yscale() == "linear" and ax.get_ylim()[0] == 0  # as Fig. 10
        assert sorted(_legend(ax)) == sorted(["global (capsheet): mean ± std", "paper's method: mean ± std",
                                              "paper's failure line (5 % of side)"])
        line = [ln for ln in ax.lines if ln.get_label().startswith("paper's failure")][0]
        assert line.get_ydata()[0] == 5.0
        paper_bars = ax.containers[1]  # dots at the mean, bars mean ± std
        np.testing.assert_allclose(paper_bars.lines[0].get_ydata(), [0.0, 3.41, 20.46])
        segs = paper_bars.lines[2][0].get_segments()
        np.testing.assert_allclose(segs[2][:, 1], [20.46 - 9.3, 20.46 + 9.3])
        assert ax.get_ylim()[1] >= 20.46 + 9.3  # nothing clipped
        assert "up to 1 % g" in ax.get_title() and "no level" in err_axes[1].get_title()
        # the units' λ3/λ1: the data, the unsolvable ones marked, one colour scale for both maps
        im = map_axes[0].images[0]
        assert np.asarray(im.get_array())[0, 0] == pytest.approx(0.05)
        marks = [ln for ln in map_axes[0].lines if ln.get_label().startswith("λ3/λ1 < 0.1")][0]
        assert sorted(zip(marks.get_xdata(), marks.get_ydata())) == [(0, 0), (7, 6)]
        assert im.get_clim() == map_axes[1].images[0].get_clim()
        assert "2 of 169 below 0.1" in map_axes[0].get_title()
        assert "14x14" in fig._suptitle.get_text() and "10 trials" in fig._suptitle.get_text()
    finally:
        plt.close(fig)
    assert (tmp_path / "n.png").stat().st_size > 30_000
    one = {"fig9": res["fig9"]}  # one target, one column: the title still fits the figure
    fig = figures.noise_figure(tmp_path / "n1.png", one, ("global", "paper"), trials=10, seed=2008,
                               side_joints=14)
    try:
        box, width = _bbox(fig, fig._suptitle), fig.get_figwidth() * fig.dpi
        assert box.x0 >= 0 and box.x1 <= width
    finally:
        plt.close(fig)


def test_estimate_run_figure_labels_residual_completeness_and_shape(gaussian, tmp_path):
    lat = Lattice(14, 14)
    n = 20
    t = np.arange(n) / 145
    residual = np.linspace(1e-6, 1e-3, n)
    valid = np.ones((n, lat.n_links), bool)
    valid[5, :10] = False
    joints = np.repeat(gaussian[None], n, axis=0)
    fig = figures.estimate_run_figure(tmp_path / "e.png", t, residual, valid, joints, lat, L, title="run x")
    try:
        ax = fig.axes[0]
        ax3 = [a for a in fig.axes if a.name == "3d"][0]
        ax2 = [a for a in fig.axes if a is not ax and a is not ax3][0]
        assert _legend(ax) == ["eq. (8) residual", "links valid"]
        assert ax.get_yscale() == "log" and ax.get_xlabel() == "time [s]"
        assert ax3.get_zlabel() == "z [cm]" and _legend(ax3) == ["estimate, snapshot 19"]
        line = [ln for ln in ax2.lines if ln.get_label() == "links valid"][0]
        assert line.get_ydata().min() == pytest.approx(100 * (lat.n_links - 10) / lat.n_links)
    finally:
        plt.close(fig)
