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
    assert "chips" not in title and "fused" not in title  # today's chips: nothing to name


def test_demo_figure_names_6_and_9_axis_chips_and_the_fused_estimator(gaussian, tmp_path):
    fig = figures.demo_figure(tmp_path / "demo.png", gaussian, gaussian, np.zeros((14, 14)), shape="wave",
                              noise_pct_g=1.0, rate_hz=145.0, run_mean_error_pct=0.2, counter=5, link_length=L,
                              sensors="accel+gyro+mag")
    try:
        assert "'wave', accel+gyro+mag chips (fused estimator), 1 % g noise" in fig._suptitle.get_text()
    finally:
        plt.close(fig)


def test_a_failed_demo_run_is_marked_and_the_heat_map_says_it_is_one_snapshot(gaussian, tmp_path):
    # the run's mean (4.06 %) and the drawn snapshot's (12.86 %) differ: each title names its own
    err = np.full((14, 14), 12.86)
    fig = figures.demo_figure(tmp_path / "demo.png", gaussian, gaussian, err, shape="carry", noise_pct_g=1.0,
                              rate_hz=145.0, run_mean_error_pct=4.06, counter=77, link_length=L,
                              sensors="accel+gyro+mag", failed="80.0 % of SYNCs complete < 99 %", compared=500)
    ok = figures.demo_figure(tmp_path / "ok.png", gaussian, gaussian, err, shape="carry", noise_pct_g=1.0,
                             rate_hz=145.0, run_mean_error_pct=4.06, counter=77, link_length=L)
    try:
        title = fig._suptitle.get_text()
        assert title.startswith("FAIL: 80.0 % of SYNCs complete < 99 %") and fig._suptitle.get_color() == "red"
        assert "run mean error 4.06 % of side over 500 snapshots" in title and "counter 77" in title
        heat = fig.axes[2].get_title()
        assert "this snapshot only" in heat and "12.86 %" in heat and "4.06" not in heat
        assert "FAIL" not in ok._suptitle.get_text()
    finally:
        plt.close(fig)
        plt.close(ok)


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
        from host.analysis.estimator.priors import DEFAULT_PRIOR
        default = f"capsheet default (global, prior {DEFAULT_PRIOR!r}): mean ± std"
        assert sorted(_legend(ax)) == sorted([default, "paper's method: mean ± std",
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


@pytest.mark.parametrize("spread", [2.0, 1000.0])
def test_estimate_run_figure_labels_misfit_completeness_and_shape(gaussian, tmp_path, spread):
    """The misfit is in % of a link length per unit (a reader can picture it), on an axis with
    readable ticks: linear over a narrow range, a log axis with 1-2-5 ticks written as plain numbers
    over a wide one (the residual's log axis had two labels, 2e-1 and 4e-1)."""
    lat = Lattice(14, 14)
    n = 20
    t = np.arange(n) / 145
    residual = np.linspace(1e-3, spread * 1e-3, n)
    valid = np.ones((n, lat.n_links), bool)
    valid[5, :10] = False
    joints = np.repeat(gaussian[None], n, axis=0)
    fig = figures.estimate_run_figure(tmp_path / "e.png", t, residual, valid, joints, lat, L, title="run x")
    try:
        fig.canvas.draw()
        ax = fig.axes[0]
        ax3 = [a for a in fig.axes if a.name == "3d"][0]
        ax2 = [a for a in fig.axes if a is not ax and a is not ax3][0]
        assert _legend(ax) == ["eq. (8) misfit per unit, RMS", "links valid"]
        assert ax.get_ylabel() == "misfit per unit, RMS [% of a link length]" and ax.get_xlabel() == "time [s]"
        # snapshot 0: every one of the 13 x 13 units valid; the figure shows 100 sqrt(residual / 169)
        np.testing.assert_allclose(ax.lines[0].get_ydata()[0], 100 * np.sqrt(1e-3 / 169))
        lo, hi = ax.get_ylim()
        shown = [tk for tk in ax.get_yticklabels() if lo <= tk.get_position()[1] <= hi and tk.get_text()]
        assert len(shown) >= 3, [tk.get_text() for tk in shown]
        assert all("$" not in tk.get_text() and "^" not in tk.get_text() for tk in shown)
        assert ax.get_yscale() == ("log" if spread > 30 else "linear")
        assert ax3.get_zlabel() == "z [cm]" and _legend(ax3) == ["estimate, snapshot 19"]
        line = [ln for ln in ax2.lines if ln.get_label() == "links valid"][0]
        assert line.get_ydata().min() == pytest.approx(100 * (lat.n_links - 10) / lat.n_links)
    finally:
        plt.close(fig)


def test_estimate_run_figure_of_a_6_axis_run_draws_the_gyroscopes_and_the_fused_estimator(gaussian, tmp_path):
    """A 6/9-axis recording's figure adds the gyroscope axes of the link that turned most (°/s) with the
    fastest link's rate, and the fused estimator's own figures: its bias estimate, the common
    acceleration, the magnetometers' weight in the title."""
    lat = Lattice(14, 14)
    n = 30
    t = np.arange(n) / 145
    valid = np.ones((n, lat.n_links), bool)
    joints = np.repeat(gaussian[None], n, axis=0)
    gyro = np.zeros((n, lat.n_links, 3))
    gyro[:, 7] = np.radians([10.0, -20.0, 30.0])  # link 7 turns most: |ω| = sqrt(1400) °/s
    gyro[:, 3, 0] = np.radians(5.0)
    fused = {"gyro_bias_rms_dps": np.linspace(0, 0.1, n), "common_accel_mps2": np.full(n, 2.0),
             "mag_weight_mean": np.full(n, 0.75), "heading_absolute": np.ones(n, bool)}
    fig = figures.estimate_run_figure(tmp_path / "g.png", t, np.full(n, 1e-3), valid, joints, lat, L, title="run g",
                                      gyro=gyro, fused=fused)
    try:
        fig.canvas.draw()
        g_ax = next(a for a in fig.axes if a.get_title().startswith("gyroscopes"))
        assert _legend(g_ax) == ["link 7, x", "link 7, y", "link 7, z", "fastest link's |ω|, per snapshot"]
        np.testing.assert_allclose([ln.get_ydata()[0] for ln in g_ax.lines[:4]], [10, -20, 30, np.sqrt(1400)])
        assert g_ax.get_ylabel() == "angular rate [°/s]"
        f_ax = next(a for a in fig.axes if a.get_title().startswith("fused estimator"))
        assert "mean weight 0.75" in f_ax.get_title() and "heading absolute" in f_ax.get_title()
        assert _legend(f_ax) == ["gyroscope bias estimate, RMS over links", "|common acceleration| (translation)"]
        np.testing.assert_allclose(f_ax.lines[0].get_ydata()[-1], 0.1)
    finally:
        plt.close(fig)
    assert (tmp_path / "g.png").stat().st_size > 30_000


def test_motion_scenes_figure_draws_each_scene_in_one_cube_with_its_peaks(tmp_path):
    from virtual_sheet.motion import make_motion_scene

    t = np.arange(0.0, 1.5, 1 / 50)
    panels = []
    for name in ("wave", "tap"):
        tr = make_motion_scene(name, 6, 6, L).sample(t)
        panels.append({"name": name, "t_s": t, "peak_accel_mps2": np.linalg.norm(tr.acceleration, axis=-1).max(1),
                       "peak_rate_dps": np.degrees(np.linalg.norm(tr.angular_velocity, axis=-1).max(1)),
                       "snapshots": [(float(t[i]), tr.joints[i]) for i in (0, 20, 60)]})
    fig = figures.motion_scenes_figure(tmp_path / "m.png", panels, lattice="6x6", link_length=L, rate_hz=50)
    try:
        assert "6x6 joints" in fig._suptitle.get_text() and "50 Hz" in fig._suptitle.get_text()
        views = [ax for ax in fig.axes if ax.name == "3d"]
        assert len(views) == 6
        for ax in views:  # one cube per scene, every instant at the same scale, in cm
            assert (ax.get_xlabel(), ax.get_zlabel()) == ("x [cm]", "z [cm]")
            lims = np.array([ax.get_xlim(), ax.get_ylim(), ax.get_zlim()])
            assert np.ptp(lims, axis=1) == pytest.approx([np.ptp(lims[0])] * 3)
        assert [ax.get_title() for ax in views[:3]] == ["wave, t = 0.00 s", "wave, t = 0.40 s", "wave, t = 1.20 s"]
        series = [ax for ax in fig.axes if ax.name != "3d" and ax.get_xlabel() == "t [s]"]
        assert len(series) == 2 and series[0].get_ylabel() == "acceleration [m/s²]"
        assert "2 m/s² (the fused estimator's floor)" in _legend(series[0])
        assert f"peaks {panels[1]['peak_accel_mps2'].max():.1f} m/s²" in series[1].get_title()
    finally:
        plt.close(fig)
    assert (tmp_path / "m.png").stat().st_size > 20_000


def test_imu_stream_figure_shows_truth_and_readings_per_sensor(tmp_path):
    t = np.linspace(0, 1, 50)
    truth = np.stack([np.sin(t), np.cos(t), t], axis=-1)
    fig = figures.imu_stream_figure(tmp_path / "s.png", t, [("gyroscope", "°/s", truth, truth + 0.1),
                                                             ("magnetometer", "µT", truth, truth - 0.1)], title="x")
    try:
        assert [ax.get_ylabel() for ax in fig.axes] == ["gyroscope [°/s]", "magnetometer [µT]"]
        assert _legend(fig.axes[0])[:2] == ["truth x", "reading x"] and len(fig.axes[0].lines) == 6
    finally:
        plt.close(fig)
