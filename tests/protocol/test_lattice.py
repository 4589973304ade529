"""`protocol.lattice`: the link order and the units of docs/design.md §3, written out by hand for
small lattices (the expected values are the document's, not the code's), and `Lattice.parse`."""

import numpy as np
import pytest

from protocol.lattice import AXIS_I, AXIS_J, Lattice, Link


def test_the_link_order_of_the_design_document():
    # "for 3 x 4 joints the i-links are 0..7 and the j-links 8..16; link 8 is (0,0)->(0,1)"
    lat = Lattice(3, 4)
    assert (lat.n_i_links, lat.n_j_links, lat.n_links, lat.n_joints, lat.n_units) == (8, 9, 17, 12, 6)
    assert [lat.link(k).axis for k in range(17)] == [AXIS_I] * 8 + [AXIS_J] * 9
    assert lat.link(8).joints == ((0, 0), (0, 1))
    assert lat.link(7).joints == ((1, 3), (2, 3))  # the last i-link: row-major, lower joint (1, 3)
    assert lat.link(16).joints == ((2, 2), (2, 3))
    # endpoints as flat joint ids i * cols + j, sensor x from the first to the second
    assert lat.endpoints[4].tolist() == [4, 8] and lat.endpoints[11].tolist() == [4, 5]  # (1,0)->(1,1)


def test_index_of_and_link_are_inverse_over_every_link():
    lat = Lattice(4, 5)
    for k in range(lat.n_links):
        ln = lat.link(k)
        assert lat.index_of(ln.axis, ln.i, ln.j) == k
    assert lat.link(0) == Link(0, AXIS_I, 0, 0)


def test_units_are_numbered_as_in_the_paper():
    # 3 x 3 joints: i-links 0..5 ((0,0)->(1,0) is 0), j-links 6..11 ((0,0)->(0,1) is 6).
    # Unit (0, 0): 0 the j-link (0,0)->(0,1) = 6; 1 the i-link (0,1)->(1,1) = 1;
    # 2 the j-link (1,0)->(1,1) = 8; 3 the i-link (0,0)->(1,0) = 0.
    lat = Lattice(3, 3)
    assert lat.units.shape == (2, 2, 4)
    assert lat.units[0, 0].tolist() == [6, 1, 8, 0]
    assert lat.units[1, 1].tolist() == [9, 5, 11, 4]


def test_both_routes_round_a_unit_meet_on_any_sheet():
    # d0 + d1 = d3 + d2 (eq. 4) for the vectors of any joints: the numbering closes every unit
    rng = np.random.Generator(np.random.MT19937(5))
    lat = Lattice(4, 6)
    v = lat.link_vectors(rng.normal(size=(4, 6, 3)))
    u = lat.units.reshape(-1, 4)
    np.testing.assert_allclose(v[u[:, 0]] + v[u[:, 1]], v[u[:, 3]] + v[u[:, 2]], atol=1e-12)


@pytest.mark.parametrize("text, size", [("14x14", (14, 14)), ("3X5", (3, 5)), ("2x2", (2, 2))])
def test_parse_reads_rows_by_cols(text, size):
    lat = Lattice.parse(text)
    assert (lat.rows, lat.cols) == size


@pytest.mark.parametrize("text", ["14by14", "14x", "x14", "1x5", "3x4x5", "", "ax3"])
def test_parse_refuses_what_is_no_lattice_in_one_line(text):
    with pytest.raises(ValueError, match="Invalid lattice"):
        Lattice.parse(text)


def test_out_of_range_addresses_are_named():
    lat = Lattice(3, 4)
    with pytest.raises(ValueError, match="Invalid link index 17 for lattice 3x4"):
        lat.link(17)
    with pytest.raises(ValueError, match=r"Invalid i-link joint \(2, 0\)"):
        lat.index_of(AXIS_I, 2, 0)
    with pytest.raises(ValueError, match="Invalid link axis: 2"):
        lat.index_of(2, 0, 0)
    with pytest.raises(ValueError, match=r"Expected `joints` to have shape \(3, 4, 3\)"):
        lat.link_vectors(np.zeros((4, 3, 3)))
