"""The virtual gateway as a node on the wire (docs/protocol.md §13): discovery, assignment, its
table, its heartbeat, packing with a deadline (INVALID marking), and one SYNC source per segment.
All on a simulated clock, through the sans-I/O `Gateway` (frames in, frames out)."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.can import decode_can, to_can
from protocol.constants import SampleStatus
from protocol.framing import StreamDecoder, encode, encode_frame
from protocol.messages import (LINK_NONE, Ack, Announce, Assign, Capability, ChipState, Config, GatewayFlag,
                               GatewayInfo, GetInfo, Info, MsgType, Nack, NackReason, Reset, Sample, Snapshot,
                               Start, Status, Sync, provisional_node)
from protocol.state import ANNOUNCE_PERIOD_S, SNAPSHOT_DEADLINE_S
from virtual_sheet.gateway import Gateway, gateway_uid
from virtual_sheet.sheet import VirtualSheet


class Rig:
    """A sheet behind one gateway, frames in and decoded frames out, time stepped by hand."""

    def __init__(self, transport="serial", lattice="2x2", faults=None, **gw):
        self.can = transport == "can"
        fd = self.can and gw.get("packed", False)
        self.sheet = VirtualSheet("flat", lattice, noise=0.0, seed=3, transport=transport, fd=fd,
                                  faults=faults)
        self.gw = Gateway(self.sheet, **gw)
        self.t = 0.0
        self.dec = StreamDecoder()
        self.gw.power_on(0.0)

    def send(self, msg_or_frame, dt=0.001):
        f = msg_or_frame
        if not isinstance(f, (bytes, tuple)) or hasattr(f, "arbitration_id") and False:
            f = to_can(f) if self.can else encode(f)
        self.t += dt
        (self.gw.receive if self.can else self.gw.feed)(f, self.t)
        return self.out()

    def run(self, until):
        while self.t < until:
            self.t = min(until, self.t + 0.005)
            self.gw.poll(self.t)
        return self.out()

    def out(self):
        frames = self.gw.pop_output(self.t + 1.0)
        if self.can:
            return [decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) for f in frames]
        return self.dec.feed(b"".join(frames))


def _gateway_frames(ms, uid):
    nodes = {m.node for m in ms if isinstance(m, Announce) and m.uid == uid}
    return [m for m in ms if m.node in nodes and isinstance(m, (Announce, Info, GatewayInfo, Ack, Nack, Status))]


@pytest.mark.parametrize("transport", ["serial", "can"])
def test_a_packing_gateway_announces_itself_with_its_flags_and_links(transport):
    r = Rig(transport, packed=True)
    boot = r.out()
    uid = gateway_uid(3, 0)
    p0 = provisional_node(uid, 0)
    ann, info, ginfo = boot[:3]  # before its chips' boot frames
    assert ann == Announce(p0, uid)
    assert info.capabilities & Capability.GATEWAY and info.capabilities & Capability.SNAPSHOT
    assert (info.adc_bits, info.state, info.protocol_version) == (0, ChipState.BOOT, 1)
    assert ginfo == GatewayInfo(p0, GatewayFlag.PACKING, 0, 0, r.sheet.n_links, 0)
    again = r.run(ANNOUNCE_PERIOD_S + 0.001)  # unassigned: it announces again, from the next id
    assert _gateway_frames(again, uid)[0] == Announce(provisional_node(uid, 1), uid)


def test_a_transparent_gateway_is_no_node():
    r = Rig()  # per-chip, host-driven SYNC: it changes nothing, so it is not on the wire
    assert r.gw.node is None
    assert not [m for m in r.out() if isinstance(m, Info) and m.capabilities & Capability.GATEWAY]


def test_the_gateway_table():
    r = Rig(packed=True)
    r.out()
    uid = gateway_uid(3, 0)
    p0 = provisional_node(uid, 0)
    assert r.send(Assign(p0, new_node=0x7FFF, link=LINK_NONE, uid_low=(uid ^ 1) & 0xFFFFFFFF)) == []
    r.run(ANNOUNCE_PERIOD_S + 0.001)
    p1 = provisional_node(uid, 1)
    # an ASSIGN addressed to the previous round's id is taken (§3.3)
    assert r.send(Assign(p0, new_node=0x7FFF, link=LINK_NONE, uid_low=uid & 0xFFFFFFFF)) == [Ack(0x7FFF, MsgType.ASSIGN, 0)]
    assert r.gw.node.node == 0x7FFF and p1 != 0x7FFF
    assert r.send(Config(0x7FFF)) == [Nack(0x7FFF, MsgType.CONFIG, NackReason.UNSUPPORTED)]
    assert r.send(Start(0x7FFF)) == [Nack(0x7FFF, MsgType.START, NackReason.UNSUPPORTED)]
    raw = encode_frame(0x3F, 0x7FFF, b"")
    assert r.send(raw) == [Nack(0x7FFF, 0x3F, NackReason.UNKNOWN_COMMAND)]
    assert r.send(encode_frame(0x3F, 0, b"")) == []  # broadcast: never a NACK
    assert r.send(encode_frame(MsgType.GET_INFO, 0x7FFF, b"", version=2)) == [
        Nack(0x7FFF, MsgType.GET_INFO, NackReason.BAD_VERSION)]
    got = r.send(GetInfo(0))  # broadcast: the gateway and every chip
    assert [type(m) for m in got[:3]] == [Announce, Info, GatewayInfo] and got[1].state == ChipState.IDLE
    assert sum(isinstance(m, Announce) for m in got) == 1 + r.sheet.n_links
    r.send(bytes.fromhex("04010301020603012002030387a200"))  # a bad CRC
    r.send(b"\x01" * 1100 + b"\x00")  # OVERSIZE
    hb = [m for m in r.run(r.t + 1.01) if isinstance(m, Status)]  # STATUS every 1 s once assigned
    assert hb and hb[0].node == 0x7FFF and hb[0].state == ChipState.IDLE
    assert hb[0].rx_errors == 2  # the host frames it dropped for their integrity (§13.1)
    got = r.send(Reset(0x7FFF))
    assert got[0] == Ack(0x7FFF, MsgType.RESET, 0) and got[1] == Announce(provisional_node(uid, 0), uid)


def _commissioned(**kw):
    r = Rig(**kw)
    r.gw.commission(0.0)
    r.out()
    return r


def test_one_sync_source_per_segment_host_sync_is_refused_and_counted():
    """`capsheet virtual --rate 100` and a host that also sends SYNC: the chips answer the gateway's
    SYNC only, and count no gap (1.0: they answered both and missed_syncs saturated at 255)."""
    r = _commissioned(sync_rate_hz=100.0)
    assert r.gw.node is not None and r.gw.node.flags & GatewayFlag.SYNC_SOURCE
    ev = []
    for c in range(1000, 1030):  # the host's SYNCs, between the gateway's own
        ev += r.send(Sync(counter=c), dt=0.004)
        r.gw.poll(r.t)
    ev += r.run(r.t + 0.05)
    assert r.gw.stats.syncs_refused == 30
    assert not [m for m in ev if isinstance(m, Sample) and m.counter >= 1000]
    assert {m.counter for m in ev if isinstance(m, Sample)} <= {m.counter for m in ev if isinstance(m, Sync)}
    assert [c.missed_syncs for c in r.sheet.chips] == [0] * r.sheet.n_links
    st = [m for m in r.run(r.t + 1.1) if isinstance(m, Status) and m.node == r.gw.node.node]
    assert st and st[-1].missed_syncs == 30  # the gateway's STATUS reports what it refused


def test_without_the_rule_two_sources_saturate_missed_syncs():
    """The failure the rule prevents, shown on a transparent gateway: a foreign SYNC source interleaved
    with the host's counts every jump as a gap."""
    r = _commissioned()
    for i in range(20):
        r.send(Sync(counter=i), dt=0.002)
        r.send(Sync(counter=0x4000 + i), dt=0.002)
    assert min(c.missed_syncs for c in r.sheet.chips) == 255


def test_a_sync_line_follower_refuses_host_sync_too():
    sheet = VirtualSheet("flat", "2x2", noise=0.0, seed=3)
    lead, follow = Gateway(sheet, range(0, 2), sync_rate_hz=100.0, stream=0), Gateway(sheet, range(2, 4), stream=1)
    lead.followers = [follow]
    for g in (lead, follow):
        g.power_on(0.0)
    assert follow.node is not None and follow.node.flags & GatewayFlag.SYNC_SOURCE
    follow.feed(encode(Sync(counter=5)), 0.01)
    assert follow.stats.syncs_refused == 1


@pytest.mark.parametrize("transport", ["serial", "can"])
def test_packing_marks_a_link_invalid_after_the_deadline(transport):
    """A chip whose SAMPLE would arrive after SNAPSHOT_DEADLINE_S goes into the SNAPSHOT as INVALID
    (counts 0) and its late SAMPLE is dropped; the others are there."""
    late_ms = SNAPSHOT_DEADLINE_S * 1000 + 5
    r = _commissioned(transport=transport, packed=True,
                      faults=f"drift_chip=1,drift=0,drift_late_ms={late_ms:g}")
    node = r.gw.node.node
    got = r.send(Sync(counter=9))
    snaps = [m for m in got if isinstance(m, Snapshot)]
    assert snaps and all(s.node == node and s.counter == 9 for s in snaps)
    counts = np.concatenate([s.counts for s in snaps])
    status = np.concatenate([s.status for s in snaps])
    assert status[1] == SampleStatus.INVALID and counts[1].tolist() == [0, 0, 0]
    assert not (status[[0, 2, 3]] & SampleStatus.INVALID).any()
    assert not [m for m in got if isinstance(m, Sample)]
    assert r.gw.stats.late_dropped == 1


def test_packing_passes_on_a_sample_of_a_link_it_does_not_cover():
    sheet = VirtualSheet("flat", "2x2", noise=0.0, seed=3)
    gw = Gateway(sheet, range(0, 4), packed=True)
    gw.power_on(0.0)
    gw.commission(0.0)
    c = sheet.chips[2]
    gw.feed(encode(Config(c.node)), 0.0)  # (nothing: streaming) — then re-ASSIGN it outside the runs
    gw.feed(encode(Reset(c.node)), 0.0)
    gw.feed(encode(Assign(c.node, new_node=50, link=9, uid_low=c.uid & 0xFFFFFFFF)), 0.0)
    gw.feed(encode(Start(50)), 0.0)
    gw.pop_output(1.0)
    gw.feed(encode(Sync(counter=3)), 0.1)
    ev = StreamDecoder().feed(b"".join(gw.pop_output(1.0)))
    assert [m for m in ev if isinstance(m, Sample)] == [Sample(50, 3, 0, 0, 1024, 0)]
    snaps = [m for m in ev if isinstance(m, Snapshot)]
    assert len(snaps) == 1 and snaps[0].status[2] == SampleStatus.INVALID


@pytest.mark.parametrize("engine", ["array", "chips"])
@pytest.mark.parametrize("transport", ["serial", "can"])
def test_packing_packs_a_babbling_chips_sample_and_passes_on_only_its_junk(transport, engine):
    """§13.1: a packing gateway passes its chips' frames unchanged *except the SAMPLEs it packs*; §13.2:
    every link exactly once. A chip that floods STATUS frames beside its SAMPLE (a wrapped, faulty
    chip) has its SAMPLE in the SNAPSHOT like any other (a flat sheet without noise: 0, 0, 1024 g-counts
    on every link), and its STATUS frames, exactly as many as it sent, pass on — no SAMPLE does."""
    can = transport == "can"
    sheet = VirtualSheet("flat", "2x2", noise=0.0, seed=3, transport=transport, fd=can, engine=engine,
                         faults="babble_chip=1,babble_mode=flood,babble_rate=3,seed=4")
    gw = Gateway(sheet, packed=True)
    gw.power_on(0.0)
    gw.commission(0.0)
    gw.pop_output(1.0)
    babble = 0
    for counter in range(5):
        before = sheet.fault_stats.babble_frames
        sync = Sync(counter=counter)
        (gw.receive if can else gw.feed)(to_can(sync) if can else encode(sync), 0.1 * (counter + 1))
        frames = gw.pop_output(0.1 * (counter + 1) + 0.05)
        ev = [decode_can(f.arbitration_id, f.data, is_fd=f.is_fd) for f in frames] if can else \
            StreamDecoder().feed(b"".join(frames))
        snaps = [m for m in ev if isinstance(m, Snapshot)]
        assert len(snaps) == 1 and snaps[0].counter == counter
        assert snaps[0].counts.tolist() == [[0, 0, 1024]] * 4 and snaps[0].status.tolist() == [0] * 4
        rest = [m for m in ev if not isinstance(m, Snapshot)]
        assert len(rest) == sheet.fault_stats.babble_frames - before
        assert all(isinstance(m, Status) and m.node == 2 for m in rest)  # link 1 is node 2 (commission)
        babble += len(rest)
    assert babble > 0


def test_a_gateway_serves_the_chip_array_only_over_its_own_sorted_links():
    # Gateway.chip_array: the sheet's ChipArray when the sheet keeps one and the gateway's links are
    # sorted and distinct (its batch paths), else None (the chips one by one)
    array_sheet = VirtualSheet("flat", "4x4", seed=2)
    assert array_sheet.engine_name == "array" and array_sheet.array is not None
    assert Gateway(array_sheet).chip_array is array_sheet.array
    assert Gateway(array_sheet, [3, 1, 2]).chip_array is None
    chips_sheet = VirtualSheet("flat", "4x4", seed=2, engine="chips")
    assert chips_sheet.engine_name == "chips" and Gateway(chips_sheet).chip_array is None
