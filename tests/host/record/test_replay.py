"""Replay as a transport (host/record/replay.py), and CAN logs written through python-can's loggers, read
by the ``cantools decode`` command line and replayed. The commands ``capsheet replay`` and
``capsheet estimate``: tests/host/cli/test_replay.py and test_estimate.py; the recorded sessions
(``pty_recording``, ``can_recording``): tests/host/conftest.py."""

from __future__ import annotations

from collections import Counter
import subprocess
import sys

import numpy as np
import pytest

from host.record.recording import read
from host.record.replay import Replay, ReplayTransport
from protocol.dbc import DBC_ID_MASK, DBC_PATH

def _by_counter(snaps):
    return {int(s.counter): s for s in snaps}


def test_replay_of_a_serial_recording_makes_the_recorded_snapshots(pty_recording):
    rec = read(pty_recording)
    # complete or not (a loaded machine misses deadlines and SYNCs): replayed alike. Enough
    # snapshots to mean something, not a rate: 150 SYNCs are due in 1.5 s at 100 Hz
    assert len(rec) >= 10
    cal = rec.attachments["calibration.json"]["links"]
    assert np.ptp([c["offset"] for c in cal]) > 1 and np.ptp([c["sensitivity"] for c in cal]) > 1
    rp = Replay(pty_recording)
    snaps = list(rp.snapshots())
    assert [s.counter for s in snaps] == rec.counter.tolist()
    for k, s in enumerate(snaps):
        np.testing.assert_array_equal(s.readings.astype(np.float32), rec.readings[k])
        np.testing.assert_array_equal(s.valid, rec.valid[k])
        np.testing.assert_array_equal(s.status, rec.status[k])
        assert s.timestamp == rec.timestamp[k]  # the counter opened where the host opened it
    live = rec.attachments["stats.json"]["aggregator"]
    assert rp.stats["aggregator"]["late"] >= live["late"], (rp.stats, live)  # late frames are late again
    assert rp.stats["aggregator"]["duplicates"] == live["duplicates"] and not rp.transports[0].stats.errors


def test_replay_at_real_speed_makes_the_same_snapshots(pty_recording):
    fast = [s.counter for s in Replay(pty_recording).snapshots()]
    real = [s.counter for s in Replay(pty_recording, speed=4.0).snapshots()]
    assert real == fast


def test_damaged_raw_input_is_counted_not_raised():
    # a serial chunk with a corrupt frame in the middle: the decoder's DecodeError, counted
    from protocol.framing import encode
    from protocol.messages import Sample
    good = encode(Sample(1, 7, 1, 2, 3, 0))
    bad = bytearray(good)
    bad[3] ^= 0xFF
    t = ReplayTransport([(0.0, "serial", good + bytes(bad) + good)], "damaged")
    events = t.recv(0)
    assert sum(1 for e in events if type(e).__name__ == "SampleBatch" or type(e).__name__ == "Sample") >= 1
    assert t.stats.error_count == 1


def test_replay_transport_refuses_a_bad_speed_and_mixed_input():
    with pytest.raises(ValueError, match="Invalid speed: 0"):
        ReplayTransport([], speed=0)
    with pytest.raises(ValueError, match="mixes"):
        ReplayTransport([(0.0, "serial", b""), (0.1, "can", [])], "x")


def test_a_can_session_is_logged_for_cantools_every_frame_decoded(can_recording):
    log = can_recording / "run.log"
    lines = [ln for ln in log.read_text().splitlines() if ln.strip()]
    assert len(lines) > 100
    proc = subprocess.run([sys.executable, "-m", "cantools", "decode", "--single-line",
                           "-m", hex(DBC_ID_MASK), str(DBC_PATH)],
                          input=log.read_text(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    out = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    assert len(out) == len(lines)
    assert not [ln for ln in out if "Unknown frame" in ln or "::" not in ln]
    assert sum(" SAMPLE(" in ln for ln in out) > 50


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_replay_of_a_can_log_makes_the_snapshots_the_host_made(can_recording, suffix):
    rec = read(can_recording / "run.mcap")
    assert len(rec) >= 10 and len(rec.raw) == 2
    # the log's frames of a counter lie within the live deadline (300 ms): wait longer than that
    snaps = _by_counter(Replay(can_recording / f"run{suffix}", lattice="4x4", deadline_s=0.5).snapshots())
    matched = 0
    for k, c in enumerate(rec.counter.tolist()):
        if not rec.complete[k]:
            continue
        s = snaps[c]  # a log has the frames, not the deadlines: what was complete live is complete here
        assert s.complete
        np.testing.assert_array_equal(s.valid, rec.valid[k])
        # the log's replay uses nominal calibration; the virtual chips' calibration is within 2 mm/s²
        np.testing.assert_allclose(s.readings.astype(np.float32), rec.readings[k], rtol=0, atol=2e-3)
        matched += 1
    assert matched >= 1


def test_a_can_log_holds_what_the_host_sent_as_tx(can_recording):
    """The log has both sides: every SYNC the host opened (the MCAP's sync channel, an independent
    record of it) is a Tx SYNC frame on each bus, with its bring-up commands before the first Rx
    SAMPLE; python-can's reader gives the direction back (candump's R / T)."""
    import can
    from protocol.can import split_id
    from protocol.messages import MsgType

    frames = list(can.LogReader(str(can_recording / "run.log")))
    tx = [m for m in frames if not m.is_rx]
    assert tx and len(tx) < len(frames)
    kinds = Counter((m.channel, MsgType(split_id(m.arbitration_id)[1]).name) for m in tx)
    for ch in ("can0", "can1"):
        assert kinds[(ch, "START")] >= 1 and kinds[(ch, "CONFIG")] >= 1 and kinds[(ch, "SYNC")] >= 1
    assert not [m for m in tx if split_id(m.arbitration_id)[1] == MsgType.SAMPLE]  # chips' frames are Rx
    rec = read(can_recording / "run.mcap")
    sent = sorted(int(c) for c in rec.sync[:, 0])
    for ch in ("can0", "can1"):
        logged = sorted(int.from_bytes(bytes(m.data[:2]), "little") for m in tx
                        if m.channel == ch and split_id(m.arbitration_id)[1] == MsgType.SYNC)
        assert logged == sent
    first_sample = next(i for i, m in enumerate(frames) if m.is_rx and split_id(m.arbitration_id)[1] == MsgType.SAMPLE)
    assert any(not m.is_rx and split_id(m.arbitration_id)[1] == MsgType.START for m in frames[:first_sample])


def test_replay_of_the_can_mcap_is_identical(can_recording):
    rec = read(can_recording / "run.mcap")
    snaps = list(Replay(can_recording / "run.mcap").snapshots())
    assert [s.counter for s in snaps] == rec.counter.tolist()
    for k, s in enumerate(snaps):
        np.testing.assert_array_equal(s.readings.astype(np.float32), rec.readings[k])


def test_a_host_calibration_is_recorded_and_replay_applies_it(tmp_path):
    """``capsheet host --calibration cal.json --record``: the snapshots are recorded corrected, the
    calibration is attached (``host_calibration.json``), and replay corrects its snapshots with it,
    so they equal the recorded ones; without the attachment they would not (the bias is 0.3 m/s²)."""
    from host.analysis.calibration import Calibration
    from host.cli import main
    from host.record.recording import HOST_CALIBRATION
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet

    sheet = VirtualSheet("gaussian", "4x4", seed=8)
    layout = sheet.write_layout(tmp_path / "sheet.csv")
    ident = Calibration.identity(4, 4)
    bias = np.tile([0.3, -0.2, 0.1], (ident.n_links, 1))
    cal = Calibration(4, 4, bias=bias, scale=ident.scale, misalignment=ident.misalignment)
    out = tmp_path / "run.mcap"
    with PtyDevice(sheet) as dev:
        assert main(["host", "--port", dev.path, "--lattice", "4x4", "--layout", str(layout), "--rate", "100",
                     "--calibration", str(cal.save(tmp_path / "cal.json")), "--record", str(out),
                     "--duration", "0.5", "-q"]) == 0
    rec = read(out)
    assert len(rec) >= 10
    attached = Calibration.from_dict(rec.attachments[HOST_CALIBRATION])
    np.testing.assert_allclose(attached.bias, bias, atol=1e-3)  # rebased to nominal chips: the file's bias
    rp = Replay(out)
    assert rp.host_calibration is not None
    snaps = list(rp.snapshots())
    assert [s.counter for s in snaps] == rec.counter.tolist()
    for k, s in enumerate(snaps):
        np.testing.assert_array_equal(s.readings.astype(np.float32), rec.readings[k])
    plain = Replay(out)
    plain.host_calibration = None  # the same replay without it: not the recorded snapshots
    # the first snapshot with a valid link (on a loaded machine the first SYNC's answers can all be late)
    k, raw = next((k, r) for k, r in enumerate(plain.snapshots()) if r.valid.any())
    assert np.abs(raw.readings.astype(np.float32) - rec.readings[k])[raw.valid].max() > 0.05




def test_a_counter_the_host_held_for_its_input_replays_complete(tmp_path):
    """The host's input watermark held counter 5 past its 50 ms deadline until its bus was read: the
    read that came 80 ms after the SYNC held all four links' 6-axis records (classic CAN: two frames
    a record, taken one record at a time), taken in whole, and the snapshot was complete. The replay
    follows the recorded emission: it must not emit the counter at a deadline of its own in the
    middle of that read (it did: link 0 in, links 1–3 late — 6-axis recordings under load)."""
    import can

    from host.snapshots.aggregator import Aggregator
    from host.snapshots.feed import SnapshotFeed
    from host.record.recording import Recorder
    from host.transport.ports import TransportStats, feed_can
    from protocol.can import CanDecoder, imu_can_frames
    from protocol.lattice import Lattice
    from protocol.messages import ImuSample

    lattice = Lattice(2, 2)  # 4 links: nodes 1..4
    clock = {"t": 10.0}
    live = SnapshotFeed(Aggregator(lattice.n_links, deadline_s=0.05, hold_for_input=True, trust="sent"),
                        clock=lambda: clock["t"])
    live.aggregator.gyro_range = 3
    path = tmp_path / "held.mcap"
    session = {"rate_hz": 100.0, "deadline_s": 0.05, "imu_config": [1, 3, 0, 0],
               "transports": [{"name": "virtual:held", "kind": "can", "fd": False}]}
    with Recorder(path, lattice, 0.01, session=session, layout={"chips": []}, calibration={"links": []}) as rec:
        live.add_open_listener(rec.sync)
        live.add_listener(rec.snapshot)
        live.open_counter(5)
        clock["t"] = 10.060
        live.poll()  # past the deadline, the bus not read past it: held
        assert live.pending == 0
        frames = [can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True)
                  for node in (1, 2, 3, 4)
                  for f in imu_can_frames(ImuSample(node, 5, 10 * node, 0, 1000, 0, 100, gz=50))]
        clock["t"] = 10.080
        rec.raw(0, "can", frames, "virtual:held", t=clock["t"])  # as `Recorder.tap` writes it, at its ingest
        events = feed_can(CanDecoder(), frames, TransportStats())
        assert len(events) == 4  # a record at a time
        live.ingest(events, 0)
        [snap] = live.drain()
    assert snap.complete and snap.latency_s == pytest.approx(0.080)
    rp = Replay(path)
    [again] = list(rp.snapshots())
    assert again.counter == 5 and again.complete and again.valid.all(), again.status
    assert rp.stats["aggregator"]["late"] == 0


def test_each_snapshot_replays_at_the_wall_time_the_host_gave_it(tmp_path):
    """The host measures its wall clock's offset (Unix minus monotonic) as it opens each counter; on
    a loaded machine a thread that waits between reading the two clocks moves the measurement by
    milliseconds. Each replayed snapshot keeps the wall time recorded for it (the ROS 2 messages a
    replay converts are stamped from it): one offset for the whole recording, as before, gave a
    loaded 9-axis demo's conversion 7 of 91 stamps that no live message had."""
    import can

    from host.snapshots.aggregator import Aggregator
    from host.snapshots.feed import SnapshotFeed
    from host.record.recording import Recorder
    from host.transport.ports import TransportStats, feed_can
    from protocol.can import CanDecoder, imu_can_frames
    from protocol.lattice import Lattice
    from protocol.messages import ImuSample

    lattice = Lattice(2, 2)
    rng = np.random.Generator(np.random.MT19937(7))
    jitter = iter(rng.uniform(-4e-3, 0.0, 200))  # a wait between the two clock reads: the offset falls
    clock = {"t": 10.0}
    unix0 = 1.7966e9
    live = SnapshotFeed(Aggregator(lattice.n_links, deadline_s=0.05), clock=lambda: clock["t"],
                        wall_clock=lambda: unix0 + clock["t"] + next(jitter))
    live.aggregator.gyro_range = 3
    path = tmp_path / "jitter.mcap"
    session = {"rate_hz": 100.0, "deadline_s": 0.05, "imu_config": [1, 3, 0, 0],
               "transports": [{"name": "virtual:jitter", "kind": "can", "fd": False}]}
    made = []
    with Recorder(path, lattice, 0.01, session=session, layout={"chips": []}, calibration={"links": []}) as rec:
        live.add_open_listener(rec.sync)
        live.add_listener(rec.snapshot)
        for c in range(1, 9):
            clock["t"] = 10.0 + 0.01 * c
            live.open_counter(c)
            clock["t"] += 0.004
            frames = [can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True)
                      for node in (1, 2, 3, 4)
                      for f in imu_can_frames(ImuSample(node, c, 10 * node, 0, 1000, 0, 100, gz=50))]
            rec.raw(0, "can", frames, "virtual:jitter", t=clock["t"])
            live.ingest(feed_can(CanDecoder(), frames, TransportStats()), 0)
            made += live.drain()
    assert [s.counter for s in made] == list(range(1, 9))
    wall = {s.counter: s.wall_time for s in made}
    assert np.ptp([s.wall_time - s.timestamp for s in made]) > 1e-3  # the offsets did move
    again = list(Replay(path).snapshots())
    assert [s.counter for s in again] == list(range(1, 9))
    for s in again:
        assert abs(s.wall_time - wall[s.counter]) < 1e-6, (s.counter, s.wall_time - wall[s.counter])
