"""host/session/core.py: sessions that survive real life, in process on a simulated clock with
exact counts — bring-up from any state, recovery of rebooted chips, counter trust, one SYNC source,
capacity, mismatches before streaming, bounded state under floods. The same behaviours through the
real CLI over ptys, SLCAN and udp_multicast are in tests/host/cli/test_host.py."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from host.session.core import CapacityError, Host, Layout, MismatchError, SyncConflictError, link_ranges
from host.transport.ports import SerialTransport
from protocol.messages import Announce, ChipState, Nack, NackReason, MsgType, Reset, Sample, Stop, Sync
from tests.host.test_back2back import Rig
from virtual_sheet.chip import ChipModel


@pytest.fixture
def rigs():
    made = []

    def make(*a, **kw):
        kw.setdefault("chip_class", ChipModel)
        r = Rig(*a, **kw)
        made.append(r)
        return r
    yield make
    for r in made:
        r.close()


def inject(rig, msg):
    """A frame on the sheet's bus from somewhere else (another host, a tool): every chip sees it."""
    for gw in rig.device.gateways:
        gw._inject(msg, rig.clock.t)


def complete_after(snaps, t):
    after = [s for s in snaps if s.timestamp > t]
    return after, sum(s.complete for s in after)


# -- 1. bring-up from any state ------------------------------------------------------------------

@pytest.mark.parametrize("first_node", [1, 200])
def test_bring_up_of_a_sheet_left_streaming_by_another_session(rigs, first_node):
    """A killed host left every chip assigned (here or at other node ids) and streaming, with SYNC
    answers still in the pipe: the new session STOPs, drains, RESETs and gets every chip."""
    rig = rigs("memory")
    for gw in rig.device.gateways:
        gw.commission(rig.clock.t, first_node=first_node)
    for c in range(50):  # a previous session's SYNCs: samples pile up in the port
        inject(rig, Sync(counter=c))
    up = rig.host.bring_up(0.2)
    n = rig.sheet.n_links
    assert up == {"discovered": n, "assigned": n, "configured": n, "calibrated": n, "started": n, "gateways": 0}
    assert rig.host.stale_frames >= 50 * n  # the backlog was drained, not ingested
    assert rig.host.nack_counts == {}
    snaps = rig.stream(0.5)
    assert len(snaps) == 50 and all(s.complete for s in snaps)


def test_bring_up_without_quiesce_fails_on_the_same_sheet(rigs):
    """The broken path the fix replaces: no STOP/RESET, chips streaming at other node ids refuse
    ASSIGN (BAD_STATE) and nothing is assigned."""
    rig = rigs("memory")
    for gw in rig.device.gateways:
        gw.commission(rig.clock.t, first_node=200)
    up = rig.host.bring_up(0.2, reset=False)
    assert up["assigned"] < rig.sheet.n_links
    assert rig.host.nack_counts[("ASSIGN", "BAD_STATE")] > 0


def test_ten_sessions_in_a_row_on_one_sheet(rigs):
    rig = rigs("memory")
    n = rig.sheet.n_links
    for session in range(10):
        host = Host(rig.host.transports, rig.sheet.lattice, layout=Layout(dict(rig.sheet.layout)),
                    clock=rig.clock, driver=rig.host._driver, timeout_s=0.15, deadline_s=0.02)
        assert host.bring_up(0.2)["started"] == n, session
        snaps = list(host.snapshots(count=10))
        assert len(snaps) == 10 and all(s.complete for s in snaps)
        host.streaming.clear()  # the session ends without STOP (killed): the next one must cope


# -- 2. recovery without a person --------------------------------------------------------------

def test_reset_broadcast_mid_stream_is_recovered_once(rigs):
    rig = rigs("memory")
    rig.host.bring_up(0.2)
    snaps = list(rig.host.snapshots(duration_s=0.3))
    inject(rig, Reset(0))
    snaps += list(rig.host.snapshots(duration_s=2.0))
    rec = [e for e in rig.host.events if e.kind == "recovery"]
    n = rig.sheet.n_links
    assert len(rec) == 1 and f"{n} of {n} chip(s) streaming again" in rec[0].detail
    assert rig.host.recoveries == 1 and rig.host.recovered_chips == n
    after, ok = complete_after(snaps, rec[0].t)
    assert len(after) >= 150 and ok >= 0.99 * len(after)
    # calibration was read again: readings are calibrated (flat sheet: |g| within 2 %)
    g = np.linalg.norm(after[-1].readings, axis=1)
    assert np.all(np.abs(g - 9.80665) < 0.2)


def test_one_chip_rebooting_is_recovered_alone(rigs):
    rig = rigs("memory")
    rig.host.bring_up(0.2)
    list(rig.host.snapshots(duration_s=0.2))
    inject(rig, Reset(node_for := 6))  # link 5's chip
    snaps = list(rig.host.snapshots(duration_s=1.5))
    [rec] = [e for e in rig.host.events if e.kind == "recovery"]
    assert "1 of 1 chip(s)" in rec.detail
    [ann] = [e for e in rig.host.events if e.kind == "announce"]
    assert ann.link == node_for - 1
    after, ok = complete_after(snaps, rec.t)
    assert ok >= 0.99 * len(after) and len(after) > 50


def test_a_chip_stopped_from_elsewhere_is_restarted(rigs):
    """STATUS says IDLE while the host streams (a STOP it did not send): CONFIG/START again."""
    rig = rigs("memory")
    rig.host.heartbeat_ms = 100
    rig.host.bring_up(0.2)
    list(rig.host.snapshots(duration_s=0.5))
    inject(rig, Stop(0))
    snaps = list(rig.host.snapshots(duration_s=2.0))
    rec = [e for e in rig.host.events if e.kind == "recovery"]
    assert rec and "streaming again" in rec[0].detail
    after, ok = complete_after(snaps, rec[-1].t)
    assert ok >= 0.99 * len(after) and len(after) > 50


# -- 3. counters the host trusts -----------------------------------------------------------------

@pytest.mark.parametrize("jump", [1000, 16384])
def test_a_stray_future_counter_frame_costs_at_most_its_own_snapshot(rigs, jump):
    rig = rigs("memory")
    rig.host.bring_up(0.2)
    snaps = list(rig.host.snapshots(duration_s=0.3))
    host = rig.host
    host.feed.ingest([Sample(2, (host.counter + jump) & 0xFFFF, 0, 0, 1024, 0)])
    snaps += list(rig.host.snapshots(duration_s=1.0))
    assert host.aggregator.stats.stray == 1
    assert sum(not s.complete for s in snaps) <= 1


# -- 4. one SYNC source --------------------------------------------------------------------------

def test_foreign_sync_stops_a_driving_host(rigs):
    rig = rigs("memory")
    rig.host.bring_up(0.2)
    list(rig.host.snapshots(duration_s=0.2))
    rig.host.receiver.on_event(0, Sync(counter=7))  # a SYNC this host did not send
    assert rig.host.sync_conflict and "another device drives SYNC" in rig.host.sync_conflict
    sent = rig.host.syncs_sent
    list(rig.host.snapshots(duration_s=0.2))
    assert rig.host.syncs_sent == sent


def test_a_gateway_sync_before_start_is_a_conflict_or_followed(rigs):
    rig = rigs("memory", gateway_sync_hz=50.0)
    rig.host.sync_policy, rig.host.sync_mode = "drive", "drive"  # as if the user forgot --sync follow
    rig.host.feed.set_trust("sent")
    # the gateway node said so itself (GATEWAY_INFO, docs/protocol.md §13.3): named in the error
    with pytest.raises(SyncConflictError, match=r"gateway 0x6A7E.* is its segment's SYNC source.*--sync follow"):
        rig.host.bring_up(0.2)
    rig2 = rigs("memory", gateway_sync_hz=50.0)
    rig2.host.sync_policy, rig2.host.sync_mode = "auto", "drive"
    rig2.host.feed.set_trust("sent")
    rig2.host.bring_up(0.2)
    assert rig2.host.sync_mode == "follow"
    snaps = rig2.stream(1.0)
    assert len(snaps) >= 40 and sum(s.complete for s in snaps) >= len(snaps) - 2


@pytest.mark.parametrize("listen_s, caught", [(0.25, True), (0.0, False)])
def test_a_slow_gateway_sync_is_heard_before_start(rigs, listen_s, caught):
    """A gateway that drives SYNC at 5 Hz: the bring-up after the drain is shorter than its period,
    so the host hears it before START only because it listens `sync_listen_s` (0.25 s) first —
    without the wait (0 s) the conflict surfaces only once streaming. A simulated clock."""
    rig = rigs("memory", gateway_sync_hz=5.0, gateway_node=False)  # a 1.0 gateway: it does not announce itself
    rig.host.sync_policy, rig.host.sync_mode = "drive", "drive"
    rig.host.feed.set_trust("sent")
    rig.host.sync_listen_s = listen_s
    if caught:
        with pytest.raises(SyncConflictError, match="another device drives SYNC on this sheet"):
            rig.host.bring_up(0.05, discover_rounds=1)
        assert rig.host.sync_conflict is None and rig.host.syncs_sent == 0
    else:
        rig.host.bring_up(0.05, discover_rounds=1)
        list(rig.host.snapshots(duration_s=0.5))
        assert rig.host.sync_conflict and "while this host does: stopped" in rig.host.sync_conflict


# -- 5. capacity ---------------------------------------------------------------------------------

def test_capacity_is_refused_over_100_percent_with_the_remedy(rigs):
    rig = rigs("memory", lattice="4x4")
    rig.host.bring_up(0.2, capacity="off")
    rig.host.stop()
    t = SerialTransport("loop://", baudrate=115200)
    host = Host([t], rig.sheet.lattice, rate_hz=100)
    host.chips = rig.host.chips  # 24 assigned chips on bus 0
    with pytest.raises(CapacityError, match=r"over capacity: .*24 chips at 100 Hz need 31\d % .*--packed"):
        host.check_capacity("refuse")
    # 24 x 100 x 150 bits (15 B per SAMPLE, 8N1) = 360 kbit/s: fits 3 Mbaud (12 %), no error
    host.transports[0].capabilities = type(t.capabilities)(kind="serial", mtu=1018, bitrate=3_000_000)
    assert host.check_capacity("refuse") == [{"bus": "loop://", "chips": 24, "load_pct": 12.0}]
    t.close()


# -- 6. mismatches -------------------------------------------------------------------------------

def test_layout_chips_that_never_answer_are_named(rigs):
    rig = rigs("memory")
    lay = dict(rig.sheet.layout)
    ghost = 0x0123456789ABCDEF
    lay[ghost] = 23
    del lay[next(u for u, k in lay.items() if k == 23)]
    rig.host.layout = Layout(lay)
    with pytest.raises(MismatchError, match=r"1 layout chip\(s\) never answered: link 23 \(uid 0x0123456789ABCDEF\)"):
        rig.host.bring_up(0.2, strict=True)


def test_a_layout_beyond_the_lattice_is_refused_at_once():
    t = SerialTransport("loop://")
    with pytest.raises(MismatchError, match="beyond lattice 2x2"):
        Host([t], "2x2", layout=Layout({1: 0, 2: 99}))
    t.close()


# -- 7. bounded under floods ---------------------------------------------------------------------

def test_an_announce_flood_is_bounded_and_counted(rigs, caplog):
    rig = rigs("memory")
    host = rig.host
    with caplog.at_level(logging.WARNING, logger="capsheet.host"):
        for uid in range(1, 200_001):
            host.receiver.on_event(0, Announce(0x8000 | (uid % 0x7FFF), uid=uid))
    assert len(host.chips) == host.max_chips and host.chips_dropped == 200_000 - host.max_chips
    assert len([r for r in caplog.records if "announce" in r.getMessage()]) == 1


def test_a_nack_storm_keeps_one_log_line_and_bounded_histories(rigs, caplog):
    rig = rigs("memory")
    rig.host.bring_up(0.2)
    host = rig.host
    uid = next(iter(host.chips))
    node = host.chips[uid].node
    with caplog.at_level(logging.WARNING, logger="capsheet.host"):
        for _ in range(5000):
            host.receiver.on_event(0, Nack(node, command=MsgType.ASSIGN, reason=NackReason.BAD_STATE))
    assert host.nack_counts[("ASSIGN", "BAD_STATE")] == 5000
    assert len(host.chips[uid].nacks) == 16
    assert len([r for r in caplog.records if "refused" in r.getMessage()]) == 1
    assert len(host.events) <= 10_000


def test_link_ranges_compacts_incidents():
    assert link_ranges(range(364)) == "0–363"
    # thousands of scattered links (a large sheet's incident): the first ranges, the rest counted
    assert link_ranges(range(0, 4000, 2)) == ("0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22 and 1988 more "
                                            "(2000 links in all)")
    assert link_ranges([5, 1, 2, 3, 9]) == "1–3, 5, 9"


def test_chips_falling_silent_together_are_one_log_line(rigs, caplog):
    rig = rigs("memory", faults="dead_chip=1:2:3:7,dead_after_s=0.4,seed=2", watchdog_s=0.2)
    rig.host.bring_up(0.2)
    with caplog.at_level(logging.WARNING, logger="capsheet.host"):
        rig.stream(1.5)
    silent_lines = [r.getMessage() for r in caplog.records if "silent" in r.getMessage()]
    assert silent_lines == [silent_lines[0]] and "links 1–3, 7 marked missing" in silent_lines[0]
    assert sorted(e.link for e in rig.host.events if e.kind == "silent") == [1, 2, 3, 7]  # events stay per link
    s = rig.host.summary()
    assert [d["link"] for d in s["missing_links"]] == [1, 2, 3, 7]
    assert s["missing_links"][0]["uid"] == f"0x{rig.sheet.uids[1]:016X}"


def test_the_bring_up_tells_calibrated_chips_from_nominal_ones(rigs):
    """A chip with no stored calibration reports the nominal values (docs/protocol.md §4.7): the host
    reads every chip's calibration, but only those with values of their own count as calibrated (the
    bring-up line said "364 calibrated" of chips that had none)."""
    def chip(uid, sensor, **kw):  # every chip with an odd uid carries a factory calibration of its own
        if uid % 2:
            kw["calibration"] = ((16, 1000.0), (-8, 1030.0), (0, 1024.0))
        return ChipModel(uid, sensor, **kw)

    rig = rigs("memory", chip_class=chip)
    up = rig.host.bring_up(0.2)
    n = rig.sheet.n_links
    odd = sum(c.uid % 2 for c in rig.sheet.chips)
    assert 0 < odd < n and up["calibrated"] == n  # every chip answered CAL_READ
    assert rig.host.calibration_summary() == {"own": odd, "nominal": n - odd}


def test_heartbeats_in_runs_reach_every_chip_record_and_the_watchdog(rigs):
    """A serial host takes STATUS runs at once (`StatusBatch`): each chip's last STATUS is its own
    (node, state STREAMING, its uptime), and the watchdog saw every link's heartbeat."""
    rig = rigs("memory")
    rig.host.heartbeat_ms = 100
    rig.host.bring_up(0.2)
    seen_batches = []
    rig.host.transports[0].begin_capture(
        lambda cap: seen_batches.extend(e for e in cap.events if type(e).__name__ == "StatusBatch"))
    t0 = rig.host.now()
    list(rig.host.snapshots(duration_s=0.5))
    assert seen_batches and sum(len(b) for b in seen_batches) >= rig.host.lattice.n_links
    chips = rig.host.registry.assigned()
    assert len(chips) == rig.host.lattice.n_links
    for rec in chips:
        st = rec.last_status
        assert st is not None and st.node == rec.node and st.state == ChipState.STREAMING
    seen = rig.host.watchdog._status_seen
    assert np.all(seen[[r.link for r in chips]] >= t0)


def test_every_control_event_goes_to_the_part_that_owns_it_and_the_rest_are_counted(rigs):
    """The receive path's one table (`Receiver.routes`): each control type reaches its part
    through `Receiver.on_event`; a frame no part owns (CONFIG from another host) is counted by
    type, not dropped silently."""
    from protocol.messages import Config
    rig = rigs("memory")
    host = rig.host
    rx = host.receiver
    seen = []
    for name in ("on_announce", "on_info", "on_status", "on_sync", "on_answer"):
        setattr(rx, name, lambda bus, msg, name=name: seen.append((name, type(msg).__name__)))
    rx.routes = {t: getattr(rx, fn.__name__) for t, fn in rx.routes.items()}  # rebuilt on the recorders
    for msg in (Announce(0x8001, uid=0x1234), Sync(counter=3),
                Nack(5, command=MsgType.ASSIGN, reason=NackReason.BAD_STATE),
                Config(0, 100, 1, 0, 1000), Config(0, 100, 1, 0, 1000)):
        rx.on_event(0, msg)
    assert seen == [("on_announce", "Announce"), ("on_sync", "Sync"), ("on_answer", "Nack")]
    assert rx.unrouted == {"Config": 2}
    assert host.summary()["unrouted"] == {"Config": 2}


def test_the_sync_thread_keeps_sending_while_a_receive_thread_holds_the_feed(rigs):
    """A receive thread holds the feed across a whole read (and the recorder's work on what the read
    completes); emitting what passed its deadline waits for it. That wait is the emitting thread's,
    never the SYNC thread's: with the feed held here as a read holds it, SYNCs keep going out (a
    SYNC thread that waited stopped within `POLL_WAIT_S`, two or three SYNCs in). Real clock, over
    a pty; what is checked is SYNCs sent, not when."""
    import time

    rig = rigs("pty", rate_hz=100.0)
    host = rig.host
    host.bring_up(0.3)
    host.start()
    end = time.monotonic() + 30
    while host.sync_driver.syncs_sent < 3 and time.monotonic() < end:
        time.sleep(0.01)
    with host.feed.one_read():
        before = host.sync_driver.syncs_sent
        end = time.monotonic() + 30
        while host.sync_driver.syncs_sent < before + 20 and time.monotonic() < end:
            time.sleep(0.01)
        sent = host.sync_driver.syncs_sent - before
    assert sent >= 20
    snaps = list(host.snapshots(duration_s=0.3))
    host.stop()
    assert snaps + host.drain()  # and the stream goes on once the feed is free
