"""The tactile figures are looked at, not only written: a legend entry for
every mark, the true contacts overlaid, a round punch drawn round, a fixed colour scale (an
untouched sheet's noise is not stretched into contacts), the run's parameters in the title on
lines of their own, the numbers in a table beside the map (no label on the map but the ids);
the footprint figure draws every body and indenter's estimated and true footprints."""

import numpy as np
import pytest
from matplotlib.patches import Ellipse

from host.analysis.tactile import Foam, TactileSensor, lattice_index
from host.analysis.tactile.plot import TrueMark, frame_figure, plot_frame
from virtual_sheet.foam import FlatPunch, FoamBlock, FoamScene, Press, SphereIndenter
from virtual_sheet.geometry import ideal_readings
from virtual_sheet.sensor import noisy_readings

L = 0.01


@pytest.fixture(scope="module")
def setup():
    g = np.random.Generator(np.random.MT19937(31))
    r0 = ideal_readings(FoamScene(FoamBlock(), [], 14, 14, L).rest_joints)
    rest = TactileSensor.learn_rest([noisy_readings(r0, 1.0, g) for _ in range(16)], 14, 14, L)
    sc = FoamScene(FoamBlock(), [Press(FlatPunch(0.0075), (-0.025, -0.01), 2.0),
                                 Press(SphereIndenter(0.015), (0.02, 0.01), 1.5)], 14, 14, L)
    fr = TactileSensor(rest, Foam()).process(noisy_readings(ideal_readings(sc.joints(0.0)), 1.0, g))
    fps = sc.footprints(0.0)
    marks = [TrueMark(tuple(lattice_index(sc.rest_joints, t.position)), t.force_n,
                      (fp.dent_axes_m[0] / L, fp.dent_axes_m[1] / L), fp.dent_angle_rad)
             for t, fp in zip(sc.contacts(0.0), fps)]
    untouched = TactileSensor(rest, Foam()).process(noisy_readings(r0, 1.0, g))
    return fr, marks, untouched


def test_every_mark_has_a_legend_entry_and_the_truth_is_drawn(setup):
    fr, marks, _ = setup
    assert len(fr.contacts) == 2
    fig = frame_figure(fr, title="virtual foam block, 14x14, noise 1 % g; foam h 20 mm, E 20 "
                                 "kPa; t = 0.50 s", truth=marks)
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["contact region", "contact centre (#id)", "half-depth footprint",
                      "true contact", "true half-depth footprint"]
    assert ax.get_xlabel() == "joint j (link lengths)"
    assert ax.get_ylabel() == "joint i (link lengths)"
    # every part of the title on its own line (a long one was clipped at the figure's edge)
    assert ax.get_title().split("\n") == ["virtual foam block, 14x14, noise 1 % g",
                                          "foam h 20 mm, E 20 kPa", "t = 0.50 s",
                                          "2 contact(s), total " f"{fr.total_force_n:.2f} N"]
    # a part too long for a line breaks after a comma, never between a value and its unit
    long = frame_figure(fr, title="virtual foam cylinder, sphere and punch, 14x14, L = 1 cm, "
                                  "noise 0.3 % g; foam h 20 mm").axes[0].get_title()
    assert long.split("\n")[:3] == ["virtual foam cylinder, sphere and punch, 14x14, L = 1 cm,",
                                    "noise 0.3 % g", "foam h 20 mm"]
    # the true crosses sit at the true centres
    crosses = [ln for ln in ax.get_lines() if ln.get_marker() == "x"]
    got = sorted((float(ln.get_ydata()[0]), float(ln.get_xdata()[0])) for ln in crosses)
    assert np.allclose(got, sorted(tuple(map(float, m.index)) for m in marks))
    # each contact centre is a ring drawn above the crosses, larger than a cross's arms are thick:
    # an estimate on its true contact is seen around the cross, not hidden under it
    rings = [ln for ln in ax.get_lines() if ln.get_marker() == "o"]
    assert len(rings) == len(fr.contacts)
    for ring in rings:
        assert ring.get_markerfacecolor() == "none"
        assert ring.get_zorder() > max(c.get_zorder() for c in crosses)
        assert ring.get_markersize() >= 0.8 * crosses[0].get_markersize()
    # on the map only the ids, on white boxes; the forces (with their standard deviations)
    # and the truth's in the table below it
    assert sorted(t.get_text() for t in ax.texts) == ["#0", "#1"]
    assert all(t.get_bbox_patch() is not None for t in ax.texts)
    table = fig.axes[-1].texts[0].get_text()
    for c in fr.contacts:
        assert f"#{c.id}: {c.force_n:.2f} ± {c.force_std_n:.2f} N" in table
    assert table.splitlines()[-1] == "true: 2.00 N, 1.50 N"


def test_the_figure_fits_its_canvas(setup, tmp_path):
    """Every text inside the figure with a margin of 2 % of its width (the old title ran to 5 px
    from the left edge and looked clipped)."""
    fr, marks, _ = setup
    fig = frame_figure(fr, title="virtual foam block, 14x14, L = 1 cm, noise 1 % g; foam h 20 "
                                 "mm, E 20 kPa, nu 0.25; t = 1.12 s", truth=marks)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    canvas = FigureCanvasAgg(fig)
    canvas.draw()                      # lays it out as savefig does
    renderer = canvas.get_renderer()
    W, H = fig.bbox.width, fig.bbox.height
    m = 0.02 * W
    for ax in fig.axes:
        for art in [ax.title] + list(ax.texts):
            bb = art.get_window_extent(renderer)
            assert bb.x0 >= m and bb.x1 <= W - m and bb.y0 >= 0 and bb.y1 <= H, art


def test_a_round_punch_is_drawn_round(setup):
    fr, _, _ = setup
    fig = frame_figure(fr)
    punch = min(fr.contacts, key=lambda c: c.index[0])  # the punch sits at lower i
    ells = [p for p in fig.axes[0].patches if isinstance(p, Ellipse)
            and np.allclose(p.center, (punch.index[1], punch.index[0]))]
    assert len(ells) == 1
    w, h = ells[0].width, ells[0].height
    assert min(w, h) > 0.7 * max(w, h)  # was a line (minor axis 0) from the half-depth joints


def test_noise_is_not_stretched_into_contacts(setup):
    fr, _, untouched = setup
    assert untouched.contacts == []
    ax = frame_figure(untouched).axes[0]
    im = ax.get_images()[0]
    assert im.get_clim() == (-1.0, 1.0)  # ±1 mm, the noise (~0.1 mm) stays pale
    assert ax.get_legend() is None       # no marks, no legend
    lo, hi = frame_figure(fr).axes[0].get_images()[0].get_clim()
    assert lo == -hi and hi == pytest.approx(1e3 * np.max(np.abs(fr.displacement)))


def test_footprint_figure_draws_every_body_and_indenter(setup, tmp_path):
    """One panel per (body, indenter) with the estimated and true footprints (two ellipses
    each: half-depth footprint and contact patch), and per body a panel of force errors with
    their standard deviations."""
    from host.analysis.tactile.plot import footprint_figure
    fr, marks, _ = setup
    sc = FoamScene(FoamBlock(), [Press(FlatPunch(0.0075), (-0.025, -0.01), 2.0),
                                 Press(SphereIndenter(0.015), (0.02, 0.01), 1.5)], 14, 14, L)
    idx = [np.array(m.index) for m in marks]
    cases = [("block", "punch", None, 0, fr, sc.contacts(0.0), idx, sc.footprints(0.0)),
             ("block", "sphere", 2.0, 0, fr, sc.contacts(0.0), idx, sc.footprints(0.0))]
    out = tmp_path / "f.png"
    fig = footprint_figure(cases, out, L)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    axes = fig.axes
    assert [a.get_title() for a in axes] == ["flat punch a 7.5 mm, 2 N", "two spheres 2 L apart",
                                             "force, every placement (±1 std)"]
    for a in axes[:2]:   # two true and two estimated contacts, two ellipses each
        assert sum(isinstance(p, Ellipse) for p in a.patches) == 8
    errs = [c for c in axes[2].containers]
    assert len(errs) == 4      # every matched contact of both panels, with its error bar


def test_plot_frame_writes_a_png(setup, tmp_path):
    fr, marks, _ = setup
    out = tmp_path / "sub" / "t.png"
    plot_frame(fr, out, title="x", truth=marks)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_footprint_figure_keeps_the_force_box_off_the_footprints(tmp_path):
    """Two fingers side by side whose lower one reaches into the panel's lower left corner (where
    the box used to sit, over its tip): the drawn box covers no point of any ellipse."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.text import Text

    from host.analysis.tactile.plot import footprint_figure
    from virtual_sheet.foam import CapsuleIndenter

    g = np.random.Generator(np.random.MT19937(7))
    r0 = ideal_readings(FoamScene(FoamBlock(), [], 14, 14, L).rest_joints)
    rest = TactileSensor.learn_rest([noisy_readings(r0, 1.0, g) for _ in range(16)], 14, 14, L)
    ang = 0.7    # from the i direction towards j: the pair runs lower left to upper right
    e = np.array([np.cos(ang), np.sin(ang)])
    side = 0.02 * np.array([-e[1], e[0]])
    sc = FoamScene(FoamBlock(), [Press(CapsuleIndenter(0.01, 0.02, angle_rad=ang), tuple(side / 2), 3.0),
                                 Press(CapsuleIndenter(0.01, 0.02, angle_rad=ang), tuple(-side / 2), 3.0)],
                   14, 14, L)
    fr = TactileSensor(rest, Foam()).process(noisy_readings(ideal_readings(sc.joints(0.0)), 1.0, g))
    assert len(fr.contacts) == 2
    idx = [np.array(lattice_index(sc.rest_joints, t.position)) for t in sc.contacts(0.0)]
    fig = footprint_figure([("block", "capsule", 2.0, 0, fr, sc.contacts(0.0), idx,
                             sc.footprints(0.0))], tmp_path / "f.png", L)
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)
    ax = fig.axes[0]
    ells = [p for p in ax.patches if isinstance(p, Ellipse)]
    assert len(ells) == 8
    # the lower left corner is where an ellipse is: the old place of the box would cover it
    lower_left = ax.transAxes.transform([[0.0, 0.0], [0.5, 0.25]])
    pts = np.vstack([p.get_verts() for p in ells])          # display coordinates
    inside = lambda b, xy: (xy[:, 0] >= b[0][0]) & (xy[:, 0] <= b[1][0]) & (xy[:, 1] >= b[0][1]) & (xy[:, 1] <= b[1][1])  # noqa: E731
    assert inside(lower_left, pts).any()
    (box,) = [t for t in ax.texts if isinstance(t, Text) and "true" in t.get_text()]
    bb = box.get_bbox_patch().get_window_extent(renderer)
    assert not inside(((bb.x0, bb.y0), (bb.x1, bb.y1)), pts).any()
