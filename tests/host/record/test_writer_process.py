"""A recording written by a process of its own (host/record/writer_process.py): the same file, message
for message, as a `Recorder` in the host's process writes from the same calls; its errors in one
line; a file closed whole when the host goes away."""

from __future__ import annotations

import numpy as np
import pytest
from mcap.reader import make_reader

from host.record.recording import Recorder, read
from host.record.writer_process import RecorderProcess
from host.snapshots.aggregator import Aggregator
from protocol.framing import StreamDecoder, encode
from protocol.lattice import Lattice
from protocol.messages import Snapshot, Sync


def _rng(seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.MT19937(seed))


def _session(seed: int = 3, n: int = 12):
    """A packed sheet's reads over three buses (SNAPSHOT frames of 9 links, a SYNC echoed now and
    then, noise bytes), and the snapshots an aggregator made of them."""
    r = _rng(seed)
    lat = Lattice.parse("5x4")
    L = lat.n_links
    dec = StreamDecoder(batch_samples=True, batch_snapshots=True)
    agg = Aggregator(L, deadline_s=1e9, queue_size=100, n_buses=3)
    reads = []
    for c in range(n):
        agg.open_counter(c, c / 145)
        for bus, first in enumerate(range(0, L, 11)):
            m = min(11, L - first)
            data = encode(Snapshot.from_arrays(0, c, first, r.integers(-2048, 2048, size=(m, 3)),
                                               r.integers(0, 16, size=m)))
            if r.random() < 0.3:
                data += encode(Sync(counter=c)) + bytes(r.integers(1, 256, size=5).astype(np.uint8)) + b"\x00"
            reads.append((bus, data, c / 145 + 0.001 * (bus + 1)))
            agg.ingest(dec.feed(data), bus, now=c / 145 + 0.001 * (bus + 1))
    return lat, reads, agg.drain()


def _record(cls, path, lat, reads, snaps):
    rec = cls(path, lat, 0.02)
    k = 0
    for c in range(len(snaps)):
        rec.sync(c, c / 145)
        while k < len(reads) and reads[k][2] < (c + 1) / 145:
            bus, data, t = reads[k]
            rec.raw(bus, "serial", data, t=t, log_time_ns=int(t * 1e9) + 7, t_rx=t - 0.0005)
            k += 1
        rec.snapshot(snaps[c])
    rec.contacts(3, 0.5, [{"id": 1, "index": [1.0, 2.0], "force_n": 0.5, "position": [0.0, 0.1, 0.2]}],
                 wall_time=1234.5)
    rec.close({"note": "stats"})
    return rec


def _messages(path):
    """(topic, log time, data) of every message in order; what either recorder stamps with the
    clock when it writes it (a SYNC's log time, the scene's frame transform) left out."""
    out = []
    with open(path, "rb") as f:
        for _, ch, m in make_reader(f).iter_messages(log_time_order=False):
            if ch.topic == "/tf":
                out.append((ch.topic, None, None))
            else:
                out.append((ch.topic, m.log_time if ch.topic != "/capsheet/sync" else None, m.data))
    return out


def test_the_writer_process_writes_what_a_recorder_in_the_hosts_process_writes(tmp_path):
    """Every message (topic, data and log time, but what is stamped when written), in order,
    and the same recording read back: raw input, SYNCs, snapshots, contacts, the counts reported."""
    lat, reads, snaps = _session()
    assert len(snaps) == 12
    here = _record(Recorder, tmp_path / "here.mcap", lat, reads, snaps)
    there = _record(RecorderProcess, tmp_path / "there.mcap", lat, reads, snaps)
    a, b = _messages(tmp_path / "here.mcap"), _messages(tmp_path / "there.mcap")
    assert len(a) == len(b) > 12 * 5
    assert a == b
    assert there.counts == here.counts and there.paths == [tmp_path / "there.mcap"]
    ra, rb = read(tmp_path / "here.mcap"), read(tmp_path / "there.mcap")
    assert np.array_equal(ra.readings, rb.readings, equal_nan=True) and ra.attachments.keys() == rb.attachments.keys()


def test_a_recording_the_writer_cannot_start_is_refused_in_one_line(tmp_path):
    lat, _, _ = _session(n=1)
    with pytest.raises(ValueError, match=r"^only \d+ MB free on the disk of .*need 1000000000 MB free"):
        RecorderProcess(tmp_path / "r.mcap", lat, 0.02, min_free=10**15)
    assert not (tmp_path / "r.mcap").exists()
    (tmp_path / "dir.mcap").mkdir()
    with pytest.raises(OSError):
        RecorderProcess(tmp_path / "dir.mcap", lat, 0.02)


def test_a_writer_whose_host_went_away_closes_its_file_whole(tmp_path):
    """No close message, the pipe shut (the host's process ended): the file has its summary and the
    input written so far."""
    lat, reads, snaps = _session(n=3)
    rec = RecorderProcess(tmp_path / "r.mcap", lat, 0.02)
    for bus, data, t in reads:
        rec.raw(bus, "serial", data, t=t)
    rec.snapshot(snaps[0])
    rec._proc.stdin.close()
    assert rec._proc.wait(60) == 0
    with open(tmp_path / "r.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None  # written at close: the file is whole
    topics = [t for t, _, _ in _messages(tmp_path / "r.mcap")]
    assert sum(t.startswith("/capsheet/raw/") for t in topics) == len(reads) and topics.count("/capsheet/snapshot") == 1


def test_a_live_session_recorded_by_the_writer_process_replays_to_its_snapshots(tmp_path, monkeypatch):
    """``capsheet host --record --record-process`` on a pty: the recording's snapshots are the
    host's, a replay of its raw input makes them again (counters, readings, validity, status and
    SYNC times), and the estimates made live are in it."""
    from host.cli import main
    from host.record import recording as R
    from host.record.replay import Replay
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet

    made = []
    real = R.open_recorder
    monkeypatch.setattr(R, "open_recorder", lambda *a, **k: made.append(real(*a, **k)) or made[-1])
    sheet = VirtualSheet("gaussian", "4x4", seed=5, noise=1.0)
    layout = sheet.write_layout(tmp_path / "sheet.csv")
    out = tmp_path / "run.mcap"
    with PtyDevice(sheet, packed=True) as dev:
        # a long deadline: at load 10 the default one left 30 % of the snapshots incomplete (exit 1),
        # and what is checked is that the replay makes what the host made, not how late it came
        assert main(["host", "--port", dev.path, "--lattice", "4x4", "--layout", str(layout), "--rate", "100",
                     "--deadline-ms", "300", "--record", str(out), "--record-process", "--live-rate", "20",
                     "--duration", "1.0", "-q"]) == 0
    assert [type(r).__name__ for r in made] == ["RecorderProcess"]
    assert made[0]._proc.poll() == 0  # the writer ended with the session
    rec = read(out)
    assert len(rec) >= 10 and rec.attachments["stats.json"] and rec.attachments["layout.json"]
    assert len(rec.estimates["counter"]) >= 1
    snaps = list(Replay(out).snapshots())
    assert [s.counter for s in snaps] == rec.counter.tolist()
    for k, s in enumerate(snaps):
        np.testing.assert_array_equal(s.readings.astype(np.float32), rec.readings[k])
        np.testing.assert_array_equal(s.valid, rec.valid[k])
        np.testing.assert_array_equal(s.status, rec.status[k])
        assert s.timestamp == rec.timestamp[k]


@pytest.mark.parametrize("lattice,live,process,expect", [
    ("64x64", False, None, "RecorderProcess"),  # a big sheet: its own process
    ("32x32", False, None, "Recorder"),  # 1,984 links: here
    ("64x64", False, False, "Recorder"),  # --no-record-process
    ("32x32", False, True, "RecorderProcess"),  # --record-process
    ("64x64", True, None, "Recorder"),  # a live view shares this process's writer
    ("64x64", True, True, "Recorder")])
def test_the_recorder_a_session_writes_with(tmp_path, lattice, live, process, expect):
    from host.record.recording import open_recorder
    from host.publish.live import LiveServer  # noqa: F401 - the live view's server is there

    kw = {"live_port": 0} if live else {}
    rec = open_recorder(tmp_path / "r.mcap", Lattice.parse(lattice), 0.02, process=process, **kw)
    try:
        assert type(rec).__name__ == expect
    finally:
        rec.close()
    assert read(tmp_path / "r.mcap").attachments is not None


@pytest.mark.parametrize("extra, says", [(["--record", "x.mcap", "--live", "0"], "live view shares"),
                                         ([], "give --record FILE")])
def test_a_writer_process_that_cannot_be_given_is_refused_in_one_line(tmp_path, capsys, extra, says):
    """Asked for by hand where it cannot write (a live view's recording, no recording at all): exit 2 and
    one line, before any port is opened — never silently the other way."""
    from host.cli import main
    with pytest.raises(SystemExit) as exc:
        main(["host", "--port", str(tmp_path / "no-such-port"), "--lattice", "2x2", "--record-process",
              *[str(tmp_path / e) if e.endswith(".mcap") else e for e in extra]])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and says in err[0], err
