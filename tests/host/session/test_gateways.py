"""host/session/gateways.py: the host discovers gateway nodes like chips, assigns them, and learns from them
that a port packs SNAPSHOTs and that a gateway drives its segment's SYNC (docs/protocol.md §13) —
on a simulated clock, in process (tests/host/test_back2back.py's rig)."""

from __future__ import annotations

import pytest

from host.session.core import CapacityError, SyncConflictError
from protocol.messages import Capability, Status
from tests.host.session.test_session import rigs  # noqa: F401 (the fixture)
from virtual_sheet.gateway import gateway_uid


def test_a_packing_gateway_is_a_gateway_not_a_chip_and_is_assigned(rigs):
    rig = rigs("memory", packed=True)
    out = rig.host.bring_up(0.2)
    assert out["gateways"] == 1 and out["discovered"] == rig.sheet.n_links
    uid = gateway_uid(rig.sheet.seed, 0)
    assert uid not in rig.host.chips
    rec = rig.host.gateway_nodes.by_uid[uid]
    assert rec.assigned and rec.node == 0x7FFF and rec.info.capabilities & Capability.GATEWAY
    assert [(r.start, r.stop) for r in rec.links] == [(0, rig.sheet.n_links)]
    assert rig.host.gateway_nodes.packing(0)
    snaps = rig.stream(0.5)
    assert snaps and sum(s.complete for s in snaps) >= len(snaps) - 1
    assert rig.device.gateway.node.node == 0x7FFF  # the device's gateway took the id
    rig.stream(1.2)
    assert isinstance(rec.last_status, Status) and rec.last_status.node == 0x7FFF  # its heartbeat, not a chip's
    # its heartbeats while streaming come in runs with the chips' (StatusBatch): still its own
    before = rec.last_status.uptime_s
    rig.stream(1.2)
    assert rec.last_status.node == 0x7FFF and rec.last_status.uptime_s > before
    assert all(c.last_status is None or c.last_status.node != 0x7FFF for c in rig.host.chips.values())
    assert rig.host.summary()["gateways"][0]["packing"] is True


def test_the_host_learns_packing_for_the_capacity_check(rigs):
    """The same 4x4 sheet on a 250 kbaud link: per-chip SAMPLEs at 100 Hz need 14x %; packed, the
    gateway's SNAPSHOT fits (the host was not told --packed: the gateway node said so)."""
    plain = rigs("memory")
    plain.host.bring_up(0.2, capacity="off")
    plain.host.transports[0].capabilities = type(plain.host.transports[0].capabilities)(
        kind="serial", mtu=1018, bitrate=250_000)
    with pytest.raises(CapacityError, match="per-chip SAMPLE"):
        plain.host.check_capacity("refuse")
    packed = rigs("memory", packed=True)
    packed.host.bring_up(0.2, capacity="off")
    packed.host.transports[0].capabilities = type(packed.host.transports[0].capabilities)(
        kind="serial", mtu=1018, bitrate=250_000)
    (row,) = packed.host.check_capacity("refuse")
    assert row["load_pct"] < 100


def test_a_sync_source_gateway_is_followed_without_being_heard_first(rigs):
    """sync=auto: the gateway's GATEWAY_INFO says it drives SYNC; the host follows before it listens."""
    rig = rigs("memory", gateway_sync_hz=50.0)
    rig.host.sync_policy, rig.host.sync_mode = "auto", "drive"
    rig.host.feed.set_trust("sent")
    rig.host.sync_listen_s = 0.0  # no listening: only the gateway node can tell
    rig.host.bring_up(0.2)
    assert rig.host.sync_mode == "follow" and rig.host.syncs_sent == 0
    snaps = rig.stream(1.0)
    assert len(snaps) >= 40 and sum(s.complete for s in snaps) >= len(snaps) - 2
    assert rig.device.gateway.stats.syncs_refused == 0


def test_a_driving_host_is_told_which_gateway_drives_sync(rigs):
    rig = rigs("memory", gateway_sync_hz=50.0)
    rig.host.sync_policy, rig.host.sync_mode = "drive", "drive"
    rig.host.feed.set_trust("sent")
    rig.host.sync_listen_s = 0.0
    with pytest.raises(SyncConflictError, match=r"gateway 0x6A7E[0-9A-F]{12} \(node 0x7FFF.*SYNC source"):
        rig.host.bring_up(0.2)


def test_snapshots_in_an_unknown_sample_format_are_not_read(rigs):
    """A gateway whose GATEWAY_INFO names a sample format 1.1 does not define: the host reports it and
    reads none of its SNAPSHOT words (docs/protocol.md §4.16) — counted, not taken for accelerations."""
    rig = rigs("memory", packed=True)
    node = rig.device.gateway.node
    node.sample_format = 7  # what its next GATEWAY_INFO says: a format of a later revision
    rig.host.bring_up(0.2)
    snaps = rig.stream(0.3)
    assert rig.host.gateway_nodes.unreadable_frames > 0
    assert not any(s.valid.any() for s in snaps)
    assert rig.host.event_counts["not_a_sheet"] == 1


def test_a_gateways_streaming_heartbeat_in_a_run_of_chips_heartbeats_is_the_gateways(rigs):
    """STATUS runs are taken at once (`StatusBatch`); a gateway node's STATUS among them (a real
    gateway may say STREAMING while it forwards, §13) goes to its gateway record, not to a chip's,
    and the chip's beside it to that chip."""
    from protocol.framing import encode
    from protocol.messages import ChipState
    rig = rigs("memory", packed=True)
    rig.host.bring_up(0.2)
    list(rig.host.snapshots(duration_s=0.2))
    gw = rig.host.gateway_nodes.by_uid[gateway_uid(rig.sheet.seed, 0)]
    chip = rig.host.registry.assigned()[3]
    rig.device._end.write(encode(Status(gw.node, ChipState.STREAMING, 0, 0, 0, 123456))
                          + encode(Status(chip.node, ChipState.STREAMING, 0, 0, 0, 654321)))
    rig.host.idle(0.002)
    assert gw.last_status.node == gw.node and gw.last_status.uptime_s == 123456
    assert chip.last_status.node == chip.node and chip.last_status.uptime_s == 654321



@pytest.mark.parametrize("gate", [True, False])
def test_a_following_host_takes_no_snapshot_before_it_streams(rigs, monkeypatch, gate):
    """The gateway's SYNC runs through the bring-up, so the chips started first answer it while the
    others are still being started. Those samples open no snapshot (counted as
    ``frames_before_start``): a following host's snapshots begin, as a driving host's do, when it
    streams, every one of them complete. (``gate=False``: the host without the rule, which took
    the partial snapshots.)"""
    from host.session.receive import Receiver
    if not gate:
        monkeypatch.setattr(Receiver, "before_start", lambda self, events: events)
    rig = rigs("memory", gateway_sync_hz=200.0)
    rig.host.sync_policy, rig.host.sync_mode = "follow", "follow"
    rig.host.feed.set_trust("follow")
    real = rig.host.bringup.start_chips

    def staggered(uids=None):  # half the chips, ten SYNC periods, the other half (a big sheet's START)
        if uids is not None:
            return real(uids)
        every = [r.uid for r in rig.host.registry.assigned()]
        n = real(every[:len(every) // 2])
        rig.host.idle(0.05)
        return n + real(every[len(every) // 2:])
    monkeypatch.setattr(rig.host.bringup, "start_chips", staggered)
    rig.host.bring_up(0.2)
    at_start = rig.host.frames_before_start
    snaps = list(rig.host.drain()) + list(rig.host.snapshots(duration_s=0.2))
    # `stop` clears `streaming` while the counters in flight complete: samples read then are
    # taken as before, not counted as before the start
    rig.host.streaming.clear()
    rig.host.idle(0.05)
    assert rig.host.frames_before_start == at_start
    rig.host.streaming.set()
    snaps += rig.stream(0.3)
    n_links = rig.sheet.n_links
    if gate:
        assert rig.host.frames_before_start >= 8 * (n_links // 2)  # ~10 SYNCs of the first half
        assert rig.host.summary()["frames_before_start"] == rig.host.frames_before_start
        assert len(snaps) >= 90 and all(s.complete for s in snaps)
    else:
        assert rig.host.frames_before_start == 0
        assert sum(not s.complete for s in snaps) >= 8  # the partial snapshots of the start


def test_a_gateways_info_from_a_node_a_chip_once_spoke_from_is_the_gateways(rigs):
    """A chip announced from a node id (the registry still maps that id to it) and a known gateway
    then announces from the same id: the INFO that follows is the gateway's (§4.2: INFO follows
    every ANNOUNCE). Taking the registry's uid for it dropped the chip and made a gateway of it."""
    from protocol.messages import Announce, Info
    rig = rigs("memory", packed=True)
    rig.host.bring_up(0.2)
    gw_uid = gateway_uid(rig.sheet.seed, 0)
    chip_uid = next(iter(rig.host.chips))
    node = 0x8123  # a provisional id the chip spoke from before its assignment
    rig.host.registry.announced(0, chip_uid, node)
    gws = rig.host.gateway_nodes
    assert gws.observe(0, Announce(node, gw_uid))  # the gateway (it rebooted) announces from that id
    assert gws.observe(0, Info(node, capabilities=int(Capability.GATEWAY)))
    assert chip_uid in rig.host.chips and chip_uid not in gws.by_uid
    assert gws.by_uid[gw_uid].node == node and set(gws.by_uid) == {gw_uid}
