"""Every injected fault is counted on the sending side and shows up as the matching counted event
on the receiving side (protocol.framing.StreamDecoder stats, decode_can). Sans-I/O gateways at
simulated time: fast and deterministic."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.can import decode_can, to_can
from protocol.constants import SampleStatus
from protocol.framing import DecodeError, ErrorReason, StreamDecoder, encode
from protocol.messages import Sample, Status, Sync
from virtual_sheet.faults import ERROR_FRAME, FaultSpec, FaultStats, FrameFaults
from virtual_sheet.gateway import Gateway
from virtual_sheet.sheet import VirtualSheet

N_SYNC = 60


def reset_stats(sheet):
    """Forget what the power-on frames went through: count from the first SYNC."""
    fresh = FaultStats()
    for name, value in fresh.as_dict().items():
        setattr(sheet.fault_stats, name, value)


def run_serial(faults: str, *, lattice="4x4", n_sync=N_SYNC, packed=False):
    sheet = VirtualSheet("tilted", lattice, seed=3, faults=faults)
    gw = Gateway(sheet, packed=packed)
    gw.power_on(0.0)
    gw.pop_output(1.0)
    gw.commission(0.0)
    reset_stats(sheet)
    dec = StreamDecoder()
    events = []
    for i in range(n_sync):
        now = 0.01 * i
        gw.feed(encode(Sync(counter=i)), now)
        events += dec.feed(gw.pop_bytes(now))
    events += dec.feed(gw.pop_bytes(10.0) + b"".join(p for _, p in gw.faults.flush(10.0, 0) if gw.faults)
                       if gw.faults else gw.pop_bytes(10.0))
    samples = [e for e in events if isinstance(e, Sample)]
    return sheet, gw, dec, samples, events


def test_no_faults_every_sample_arrives():
    sheet, gw, dec, samples, _ = run_serial("")
    assert len(samples) == N_SYNC * sheet.n_links and dec.stats.error_count == 0


@pytest.mark.parametrize("spec", ["bitflip=2e-3,seed=1", "drop_byte=5e-3,seed=2", "bitflip=1e-3,drop_byte=1e-3,seed=4"])
def test_byte_damage_loses_exactly_the_counted_frames(spec):
    sheet, gw, dec, samples, _ = run_serial(spec)
    st = sheet.fault_stats
    sent = N_SYNC * sheet.n_links
    assert st.frames_corrupted > 10
    assert len(samples) == sent - st.frames_corrupted
    assert dec.stats.error_count >= st.frames_corrupted // 2 > 0  # a merged pair can be one error
    assert st.bits_flipped + st.bytes_dropped >= st.frames_corrupted // 2


def test_dropped_and_duplicated_frames():
    sheet, _gw, dec, samples, _ = run_serial("drop_frame=0.05,seed=5")
    assert len(samples) == N_SYNC * sheet.n_links - sheet.fault_stats.frames_dropped > 0
    assert sheet.fault_stats.frames_dropped > 10 and dec.stats.error_count == 0
    sheet, _gw, dec, samples, _ = run_serial("dup_frame=0.05,seed=6")
    keys = [(s.node, s.counter) for s in samples]
    assert len(keys) - len(set(keys)) == sheet.fault_stats.frames_duplicated > 10


def test_reordered_frames_are_late_by_one():
    sheet, _gw, _dec, samples, _ = run_serial("reorder=0.05,seed=7", lattice="2x2")
    order = [(s.counter, s.node) for s in samples]
    late = sum(1 for a, b in zip(order, order[1:]) if b < a)
    assert sorted(order) == sorted(set(order)) and len(order) == N_SYNC * 4
    assert late == sheet.fault_stats.frames_reordered > 3


def test_delay_and_jitter_keep_order_and_bound_latency():
    spec = FaultSpec(delay_ms=5, jitter_ms=3, seed=1)
    ff = FrameFaults(spec, FaultStats())
    frames = [encode(Sample(1, i, 0, 0, 0)) for i in range(200)]
    out = ff.process(frames, 1.0)
    dues = [d for d, _ in out]
    assert [f for _, f in out] == frames and dues == sorted(dues)
    assert 1.005 <= dues[0] and dues[-1] <= 1.008 + 1e-9 and ff.stats.frames_delayed == 200


def test_dead_chip_never_heard_and_counted():
    sheet, gw, _dec, samples, _ = run_serial("dead_chip=3:5")
    dead_nodes = {4, 6}  # commission gives node link + 1
    assert not dead_nodes & {s.node for s in samples}
    assert len(samples) == N_SYNC * (sheet.n_links - 2)
    assert sheet.fault_stats.dead_syncs_ignored == 2 * N_SYNC


def test_dead_chip_in_packed_mode_is_invalid():
    sheet, gw, _dec, _s, events = run_serial("dead_chip=2", packed=True)
    snaps = [e for e in events if e.__class__.__name__ == "Snapshot"]
    assert len(snaps) == N_SYNC
    st = np.stack([s.status for s in snaps])
    assert (st[:, 2] == SampleStatus.INVALID).all() and (np.delete(st, 2, axis=1) == 0).all()


def test_babbling_chip_garbage_counted_as_errors():
    sheet, _gw, dec, samples, _ = run_serial("babble_chip=1,babble_rate=2,seed=9")
    st = sheet.fault_stats
    assert st.babble_frames > 50
    assert dec.stats.error_count == st.babble_frames
    assert len(samples) == N_SYNC * sheet.n_links


def test_babbling_chip_flood_is_valid_status_frames():
    sheet, _gw, dec, _samples, events = run_serial("babble_chip=1,babble_mode=flood,babble_rate=1,seed=2")
    flood = [e for e in events if isinstance(e, Status) and e.node == 2]
    assert len(flood) == sheet.fault_stats.babble_frames > 20 and dec.stats.error_count == 0


def test_drifting_chip_sends_stale_samples_late():
    sheet = VirtualSheet("tilted", "3x3", seed=3, faults="drift_chip=4,drift=0.1,drift_late_ms=5")
    gw = Gateway(sheet)
    gw.power_on(0.0)
    gw.pop_output(1.0)
    gw.commission(0.0)
    dec = StreamDecoder()
    on_time, late = [], []
    for i in range(100):
        now = 0.01 * i
        gw.feed(encode(Sync(counter=i)), now)
        on_time += [e for e in dec.feed(gw.pop_bytes(now)) if isinstance(e, Sample)]
        late += [e for e in dec.feed(gw.pop_bytes(now + 0.006)) if isinstance(e, Sample)]
    assert {s.node for s in late} == {5} and 5 not in {s.node for s in on_time}
    stale = [s for s in late if s.status & SampleStatus.STALE]
    assert len(stale) == sheet.fault_stats.stale_samples == pytest.approx(10, abs=1)
    assert sheet.fault_stats.late_replies == 100


def test_can_bitflip_becomes_error_frame_then_retransmission():
    sheet = VirtualSheet("tilted", "4x4", seed=3, transport="can", faults="bitflip=1e-3,seed=3")
    gw = Gateway(sheet)
    gw.power_on(0.0)
    gw.pop_output(1.0)
    gw.commission(0.0)
    reset_stats(sheet)
    out = []
    for i in range(N_SYNC):
        gw.receive(to_can(Sync(counter=i)), 0.01 * i)
        out += gw.pop_output(0.01 * i)
    errors = sum(1 for f in out if f is ERROR_FRAME)
    samples = [decode_can(f.arbitration_id, f.data) for f in out if f is not ERROR_FRAME]
    assert errors == sheet.fault_stats.error_frames > 5
    assert len(samples) == N_SYNC * sheet.n_links and all(isinstance(s, Sample) for s in samples)


def test_can_babble_is_unknown_types():
    sheet = VirtualSheet("tilted", "3x3", seed=3, transport="can", faults="babble_chip=0,babble_rate=1")
    gw = Gateway(sheet)
    gw.power_on(0.0)
    gw.pop_output(1.0)
    gw.commission(0.0)
    for i in range(50):
        gw.receive(to_can(Sync(counter=i)), 0.01 * i)
    ev = [decode_can(f.arbitration_id, f.data) for f in gw.pop_output(1.0)]
    unknown = [e for e in ev if isinstance(e, DecodeError) and e.reason == ErrorReason.UNKNOWN_TYPE]
    assert len(unknown) == sheet.fault_stats.babble_frames > 20


def test_fault_spec_parsing():
    s = FaultSpec.parse("bitflip=1e-4,drop_frame=0.01,dead_chip=5:9,seed=3,babble_mode=flood")
    assert s.bitflip == 1e-4 and s.drop_frame == 0.01 and s.dead_chip == (5, 9) and s.seed == 3
    assert FaultSpec.parse("") == FaultSpec() and not FaultSpec().any_stream
    assert list(FaultSpec.parse("outage_at_s=2,outage_s=1,outage_every_s=5").outage_windows().__iter__().__next__()) == [2, 3]
    for bad in ("bitflip=2", "nope=1", "bitflip", "babble_mode=loud", "outage_every_s=1,outage_s=2"):
        with pytest.raises(ValueError):
            FaultSpec.parse(bad)
