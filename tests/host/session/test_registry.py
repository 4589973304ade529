"""`host.session.registry.ChipRegistry` alone: what an ANNOUNCE makes of the records (a new chip, a reboot, a
chip heard on a second port, a flood), the names and maps the other parts read. (`Layout` files:
tests/protocol/test_layout.py; through a running host: tests/host/session/test_session.py.)"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from host.session.errors import MismatchError
from host.session.registry import ChipRegistry, Layout, node_for_link
from protocol.lattice import Lattice
from protocol.messages import Info

LATTICE = Lattice.parse("3x3")  # 12 links


def registry(layout=None) -> ChipRegistry:
    return ChipRegistry(LATTICE, layout, threading.RLock())


def test_node_ids_are_link_plus_one():
    assert [node_for_link(k) for k in (0, 1, 11)] == [1, 2, 12]
    with pytest.raises(ValueError, match="link -1"):
        node_for_link(-1)


def test_a_layout_beyond_the_lattice_is_refused_naming_a_chip():
    with pytest.raises(MismatchError, match="2 chip.*0x0000000000000007 on link 12"):
        registry(Layout({5: 0, 7: 12, 9: 40}))


def test_an_announce_makes_a_record_and_the_node_names_it():
    reg = registry()
    rec, rebooted, was_started = reg.announced(0, 0xABC, 0x8001)
    assert (rec.uid, rec.node, rec.bus, rebooted, was_started) == (0xABC, 0x8001, 0, False, False)
    assert reg.uid_at(0, 0x8001) == 0xABC and reg.uid_at(1, 0x8001) is None
    reg.info(0, Info(0x8001, fw_major=2))
    reg.info(0, Info(0x8002, fw_major=3))  # nobody there: dropped
    assert reg.chips[0xABC].info.fw_major == 2


def test_an_assigned_chip_announcing_from_a_provisional_node_rebooted():
    reg = registry()
    rec, _, _ = reg.announced(0, 0xABC, 0x8001)
    rec.link = 4
    reg.assigned_to(rec, node_for_link(4))
    rec.configured = rec.started = True
    assert reg.uid_at(0, 5) == 0xABC and [r.uid for r in reg.assigned()] == [0xABC]
    same, rebooted, was_started = reg.announced(0, 0xABC, 0x8002)
    assert same is rec and rebooted and was_started
    assert not (rec.assigned or rec.configured or rec.started) and rec.node == 0x8002
    assert reg.assigned() == []
    # the same chip announcing again from its assigned node is no reboot
    reg.assigned_to(rec, 5)
    assert reg.announced(0, 0xABC, 5)[1:] == (False, False)


def test_a_chip_heard_on_two_ports_is_remembered_for_the_discovery_check():
    reg = registry()
    reg.announced(0, 0xABC, 0x8001)
    reg.announced(1, 0xABC, 0x8001)
    assert reg.cross_bus_uids == {0xABC: {0, 1}} and reg.chips[0xABC].bus == 1


def test_an_announce_flood_is_bounded_and_counted():
    reg = registry()
    assert reg.max_chips == 64  # max(4 x 12 links, 64)
    for uid in range(1, 101):
        reg.announced(0, uid, 0x8000 | uid)
    assert len(reg.chips) == 64 and reg.chips_dropped == 36


def test_the_node_map_and_calibration_of_the_assigned_chips():
    reg = registry()
    for uid, link in ((0xA, 2), (0xB, 7)):
        rec, _, _ = reg.announced(0, uid, 0x8000 + uid)
        rec.link = link
        reg.assigned_to(rec, node_for_link(link))
    reg.announced(0, 0xC, 0x800C)  # heard, never assigned
    reg.chips[0xA].offset[:] = (1.0, 2.0, 3.0)
    reg.chips[0xA].sensitivity[:] = 512.0  # nominal at ±4 g
    lut, unassigned = reg.node_map()
    assert lut[3] == 2 and lut[8] == 7 and np.count_nonzero(lut >= 0) == 2
    assert np.flatnonzero(~unassigned).tolist() == [2, 7]
    off, sens = reg.chip_calibration(range_code=1)  # ±4 g values: x2 in ±2 g counts
    assert off[2].tolist() == [2.0, 4.0, 6.0] and off[7].tolist() == [0.0, 0.0, 0.0]
    assert sens.shape == (12, 3) and sens[0, 0] == 1024.0 and sens[2].tolist() == [1024.0] * 3
    assert set(reg.by_node()) == {(0, 3), (0, 8)} and set(reg.by_node({0xB})) == {(0, 8)}
    assert reg.key_name(0xA) == "link 2 (uid 0x000000000000000A)"
    assert reg.key_name((0, 8)) == "link 7 (uid 0x000000000000000B)"
    assert reg.key_name(0xC) == "uid 0x000000000000000C" and reg.key_name((0, 99)) == "(0, 99)"


def test_node_ids_in_use_include_every_layout_link_and_forget_clears_all():
    reg = registry(Layout({0xA: 0, 0xB: 5}))
    rec, _, _ = reg.announced(0, 0xC, 0x800C)
    rec.link = 9
    reg.assigned_to(rec, 10)
    assert reg.node_ids_in_use() == {1, 6, 10}
    reg.unknown_chips.add(0xC)
    reg.forget()
    assert reg.chips == {} and reg.unknown_chips == set() and reg.uid_at(0, 10) is None


def test_auto_layout_places_chips_behind_a_gateway_on_its_runs_and_the_rest_in_uid_order():
    """Layout.auto with gateway runs: chips 1..4 behind a gateway announcing links 4-5 and 8-9 take
    those (in uid order), chip 5 behind a gateway whose runs are full takes the lowest free link,
    chips without a gateway the lowest free links in uid order; without runs, links 0, 1, ... ."""
    from protocol.lattice import Lattice
    from host.session.registry import Layout
    lat = Lattice(3, 3)  # 12 links
    runs = {u: [range(4, 6), range(8, 10)] for u in (4, 1, 3, 2, 5)}
    lay = Layout.auto([9, 5, 4, 3, 2, 1, 7], lat, runs=runs)
    assert lay.links == {1: 4, 2: 5, 3: 8, 4: 9, 5: 0, 7: 1, 9: 2}
    assert Layout.auto([9, 5, 1], lat).links == {1: 0, 5: 1, 9: 2}


def test_auto_layout_warns_about_arbitrary_positions_only_when_it_placed_a_chip(caplog):
    """No chip answered: no "0 chips placed" warning before the command's own line that says so
    (seen in ``capsheet calibrate`` on a port with no sheet); one chip placed: the warning."""
    lat = Lattice(2, 2)
    with caplog.at_level("WARNING", logger="capsheet.host"):
        assert Layout.auto([], lat).links == {}
    assert caplog.records == []
    with caplog.at_level("WARNING", logger="capsheet.host"):
        Layout.auto([7], lat)
    assert [r.getMessage().split(";")[0] for r in caplog.records] == ["auto-assign: 1 chip placed on links in uid order"]


def test_a_dropped_record_leaves_no_node_leading_to_it():
    """A uid heard from two nodes (it announced again from another one) and then dropped as a
    gateway's: an INFO or a heartbeat from either node finds nothing (was: a KeyError that ended a
    receive thread, seen at 64x64 under load)."""
    from protocol.messages import StatusBatch
    reg = registry()
    reg.announced(0, 0xABC, 0x8001)
    reg.announced(0, 0xABC, 0x8002)
    reg.drop(0, 0x8002, 0xABC)
    assert 0xABC not in reg.chips and reg.uid_at(0, 0x8001) is None and reg.uid_at(0, 0x8002) is None
    reg.info(0, Info(0x8001, fw_major=2))  # no KeyError
    reg.heartbeats(0, StatusBatch(np.array([0x8001, 0x8002], dtype=np.uint16), *([np.zeros(2, np.uint8)] * 4),
                                  np.zeros(2, np.uint32)))  # no KeyError
