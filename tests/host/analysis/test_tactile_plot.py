"""The tactile heat map is looked at, not only written (issues 16, 17): a legend entry for every
mark, the true contacts overlaid, a round punch drawn round, a fixed colour scale (an untouched
sheet's noise is not stretched into contacts), the run's parameters in the title."""

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
    marks = [TrueMark(tuple(lattice_index(sc.rest_joints, t.position)), t.force_n,
                      (t.footprint_m[0] / L, t.footprint_m[1] / L), t.angle_rad)
             for t in sc.contacts(0.0)]
    untouched = TactileSensor(rest, Foam()).process(noisy_readings(r0, 1.0, g))
    return fr, marks, untouched


def test_every_mark_has_a_legend_entry_and_the_truth_is_drawn(setup):
    fr, marks, _ = setup
    assert len(fr.contacts) == 2
    fig = frame_figure(fr, title="virtual foam block, 14x14, noise 1 % g", truth=marks)
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["contact region", "contact centre (id, force)",
                      "half-depth footprint (principal half-axes)", "true contact (force)",
                      "true footprint (Winkler contact)"]
    assert ax.get_xlabel() == "joint j (link lengths)"
    assert ax.get_ylabel() == "joint i (link lengths)"
    assert "noise 1 % g" in ax.get_title() and "2 contact(s)" in ax.get_title()
    # the true crosses sit at the true centres
    crosses = [ln for ln in ax.get_lines() if ln.get_marker() == "x"]
    got = sorted((float(ln.get_ydata()[0]), float(ln.get_xdata()[0])) for ln in crosses)
    assert np.allclose(got, sorted(tuple(map(float, m.index)) for m in marks))
    texts = [t.get_text() for t in ax.texts]
    assert "2.00 N" in texts and "1.50 N" in texts


def test_a_round_punch_is_drawn_round(setup):
    fr, _, _ = setup
    fig = frame_figure(fr)
    punch = min(fr.contacts, key=lambda c: c.index[0])  # the punch sits at lower i
    ells = [p for p in fig.axes[0].patches if isinstance(p, Ellipse)
            and np.allclose(p.center, (punch.index[1], punch.index[0]))]
    assert len(ells) == 1
    w, h = ells[0].width, ells[0].height
    assert min(w, h) > 0.6 * max(w, h)  # was a line (minor axis 0) from the half-depth joints


def test_noise_is_not_stretched_into_contacts(setup):
    fr, _, untouched = setup
    assert untouched.contacts == []
    ax = frame_figure(untouched).axes[0]
    im = ax.get_images()[0]
    assert im.get_clim() == (-1.0, 1.0)  # ±1 mm, the noise (~0.1 mm) stays pale
    assert ax.get_legend() is None       # no marks, no legend
    lo, hi = frame_figure(fr).axes[0].get_images()[0].get_clim()
    assert lo == -hi and hi == pytest.approx(1e3 * np.max(np.abs(fr.displacement)))


def test_plot_frame_writes_a_png(setup, tmp_path):
    fr, marks, _ = setup
    out = tmp_path / "sub" / "t.png"
    plot_frame(fr, out, title="x", truth=marks)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
