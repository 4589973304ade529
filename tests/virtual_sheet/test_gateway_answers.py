"""The reference gateway against what docs/protocol.md 1.4 decided about gateways (§18, G07-G21): each
test is one gateway scenario, named as §18 names it, run on a simulated clock through real frames (the
host's serial bytes in, the gateway's serial bytes out, decoded by the host's decoder). Expectations are
written from the text, not from the gateway."""

from __future__ import annotations

import pytest

from protocol.framing import StreamDecoder, encode
from protocol.messages import (LINK_NONE, Ack, Announce, Assign, Config, GatewayInfo, ImuSample, MsgType, Reset,
                               Sample, Snapshot, SnapshotImu, Start, Status, Sync, provisional_node)
from virtual_sheet.gateway import Gateway
from virtual_sheet.sheet import VirtualSheet

GW = 0x7FFF  #: the node id the scenarios give the gateway
N_LINKS = 4  #: a 2 x 2 sheet: 2 i-links, 2 j-links


def _gateway(sensors: str = "accel", **kw) -> Gateway:
    sheet = VirtualSheet("flat", "2x2", noise=0.0, sensors=sensors)
    g = Gateway(sheet, packed=True, **kw)
    g.power_on(0.0)
    return g


def _run(g: Gateway, t0: float, t1: float, step: float = 0.001) -> list[tuple[float, object]]:
    """Serve the gateway from t0 to t1 (inclusive); every message it sends, with when."""
    dec = StreamDecoder()
    out = []
    n = int(round((t1 - t0) / step))
    for k in range(n + 1):
        t = t0 + k * step
        g.poll(t)
        for f in g.pop_output(t):
            out += [(t, m) for m in dec.feed(f)]
    return out


def _send(g: Gateway, msg, t: float) -> list:
    g.feed(encode(msg), t)
    return [m for _, m in _run(g, t, t)]


def _assign_gateway(g: Gateway, t: float) -> list:
    node = g.node.node
    return _send(g, Assign(node, new_node=GW, link=LINK_NONE, uid_low=g.uid & 0xFFFFFFFF), t)


def _commissioned(sensors: str = "accel", **kw) -> Gateway:
    g = _gateway(sensors, **kw)
    g.commission(0.0, start=True, first_node=1)  # chips on links 0..3 at nodes 1..4, the gateway at 0x7FFF
    _run(g, 0.0, 0.0)
    return g


def _snapshot_links(msgs, counter: int, node: int) -> list[tuple[int, int]]:
    """(link, status) of every link of the SNAPSHOT frames of ``counter`` from ``node``."""
    out = []
    for m in msgs:
        if isinstance(m, (Snapshot, SnapshotImu)) and m.counter == counter and m.node == node:
            st = m.status if isinstance(m, Snapshot) else m.arrays()[1]
            out += [(m.first_link + k, int(st[k])) for k in range(m.count)]
    return out


def test_the_runs_are_announced_from_power_on():
    """G15: before any ASSIGN, GATEWAY_INFO carries the runs of the gateway's configuration."""
    sheet = VirtualSheet("flat", "2x2", noise=0.0)
    g = Gateway(sheet, packed=True)
    g.power_on(0.0)
    infos = [m for _, m in _run(g, 0.0, 0.0) if isinstance(m, GatewayInfo)]
    assert [(i.node, i.first_link, i.link_count) for i in infos] == [(provisional_node(g.uid, 0), 0, N_LINKS)]


def test_first_status_one_second_after_the_assign():
    """G07: the first STATUS 1 s after the ASSIGN that left BOOT; a second ASSIGN does not move it."""
    g = _gateway()
    _run(g, 0.0, 0.5)
    assert Ack(GW, MsgType.ASSIGN, 0) in _assign_gateway(g, 0.5)
    got = _run(g, 0.501, 1.199)
    assert Ack(GW, MsgType.ASSIGN, 0) in _send(g, Assign(GW, new_node=GW, link=LINK_NONE,
                                                         uid_low=g.uid & 0xFFFFFFFF), 1.2)  # assigned: moves nothing
    got += _run(g, 1.201, 1.6)
    statuses = [t for t, m in got if isinstance(m, Status) and m.node == GW]
    assert len(statuses) == 1 and 1.5 <= statuses[0] <= 1.5 + 0.011  # served every 10 ms (CHIP_POLL_PERIOD_S)


def test_a_damaged_host_run_is_passed_on_and_counted():
    """G18: a frame with a bad CRC is passed to the chips (each counts it in rx_errors) and counted by
    the gateway node too."""
    g = _commissioned()
    bad = bytearray(encode(Config(1)))
    bad[-2] ^= 0x40  # a CRC bit: BAD_CRC for every receiver (no 0x00 made or lost)
    assert 0 not in bad[:-1]
    g.feed(bytes(bad), 0.5)
    got = [m for _, m in _run(g, 0.5, 1.05)]
    rx = {m.node: m.rx_errors for m in got if isinstance(m, Status)}
    assert rx == {1: 1, 2: 1, 3: 1, 4: 1, GW: 1}


def test_the_gateways_reset_keeps_packing_its_chips():
    """G19: the gateway's own RESET takes it to BOOT but it goes on packing every link of its chips."""
    g = _commissioned()
    before = _send(g, Sync(counter=10), 0.1)
    assert _snapshot_links(before, 10, GW) == [(k, 0) for k in range(N_LINKS)]
    ans = _send(g, Reset(GW), 0.2)
    assert ans[:2] == [Ack(GW, MsgType.RESET, 0), Announce(provisional_node(g.uid, 0), g.uid)]
    after = _send(g, Sync(counter=11), 0.3)
    assert _snapshot_links(after, 11, provisional_node(g.uid, 0)) == [(k, 0) for k in range(N_LINKS)]
    assert not [m for m in after if isinstance(m, Sample)]  # nothing passed on unpacked


def test_an_unassigned_gateway_packs_from_its_provisional_id():
    """G20: chips assigned and started, the gateway never assigned: it packs, from its provisional id."""
    g = _gateway()
    for k, c in enumerate(g.chips):
        _send(g, Assign(c.node, new_node=k + 1, link=k, uid_low=c.uid & 0xFFFFFFFF), 0.1)
    acks = _send(g, Start(0), 0.1)
    assert sorted(m.node for m in acks if isinstance(m, Ack)) == [1, 2, 3, 4]
    got = _send(g, Sync(counter=3), 0.2)
    assert _snapshot_links(got, 3, provisional_node(g.uid, 0)) == [(k, 0) for k in range(N_LINKS)]


def test_a_repeated_sync_is_answered_twice():
    """G10: each SYNC frame is answered on its own, a repeated counter too."""
    g = _commissioned()
    g.feed(encode(Sync(counter=7)) + encode(Sync(counter=7)), 0.1)
    got = [m for _, m in _run(g, 0.1, 0.12)]
    assert _snapshot_links(got, 7, GW) == [(k, 0) for k in range(N_LINKS)] * 2


def test_a_sync_source_counts_from_power_on_across_its_reset():
    """G21: SYNC from power-on, unassigned, counter 0 first; the gateway's RESET does not restart it."""
    g = _gateway(sync_rate_hz=100.0)
    syncs = [m.counter for _, m in _run(g, 0.0, 0.035) if isinstance(m, Sync)]
    assert syncs == [0, 1, 2, 3]
    _assign_gateway(g, 0.036)
    assert Ack(GW, MsgType.RESET, 0) in _send(g, Reset(GW), 0.037)
    syncs = [m.counter for _, m in _run(g, 0.038, 0.065) if isinstance(m, Sync)]
    assert syncs == [4, 5, 6]


@pytest.mark.parametrize("sensors, fmt", [("accel+gyro", 1), ("accel+gyro+mag", 2)])
def test_an_imu_gateway_configures_its_chips_before_start_and_keeps_their_acks(sensors, fmt):
    """G08: the gateway sends CONFIG_IMU of its format before it passes START on; the host sees only the
    ACKs to its START, and then every link in SNAPSHOT_IMU of that format."""
    g = _gateway(sensors)
    for k, c in enumerate(g.chips):
        _send(g, Assign(c.node, new_node=k + 1, link=k, uid_low=c.uid & 0xFFFFFFFF), 0.1)
    _assign_gateway(g, 0.1)
    ans = _send(g, Start(0), 0.2)
    assert sorted((m.node, m.command) for m in ans if isinstance(m, Ack)) == [(k, MsgType.START) for k in (1, 2, 3, 4)]
    got = _send(g, Sync(counter=9), 0.3)
    snaps = [m for m in got if isinstance(m, SnapshotImu)]
    assert snaps and all(int(s.format) == fmt for s in snaps)
    assert _snapshot_links(got, 9, GW) == [(k, 0) for k in range(N_LINKS)]
    assert not [m for m in got if isinstance(m, (Sample, ImuSample))]


def test_a_record_of_another_format_is_passed_on_and_its_link_invalid():
    """G09: behind a format-2 gateway, a chip the host set to format 1 is not packed (a gateway never
    converts a record): its 6-axis IMU_SAMPLE is passed on unchanged and its link is an INVALID record."""
    from protocol.messages import ConfigImu
    g = _gateway("accel+gyro+mag")
    for k, c in enumerate(g.chips):
        _send(g, Assign(c.node, new_node=k + 1, link=k, uid_low=c.uid & 0xFFFFFFFF), 0.1)
    _assign_gateway(g, 0.1)
    assert _send(g, ConfigImu(1, 1, 3, 0, 0), 0.15) == [Ack(1, MsgType.CONFIG_IMU, 0)]  # the host's: passed on
    _send(g, Start(0), 0.2)
    got = _send(g, Sync(counter=4), 0.3)
    invalid = 8
    assert _snapshot_links(got, 4, GW) == [(0, invalid)] + [(k, 0) for k in range(1, N_LINKS)]
    passed = [m for m in got if isinstance(m, ImuSample)]
    assert [(m.node, m.counter, int(m.format)) for m in passed] == [(1, 4, 1)]
