"""MCAP recordings (host/record/recording.py): written by capsheet (foxglove-sdk's writer), read back by two
independent readers (the ``mcap`` package's, and a minimal record parser here), a killed writer,
the ``capsheet host`` command end to end; layout files."""

from __future__ import annotations

import base64
import json
import os
import signal
import struct
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from host.snapshots.snapshot import LatticeSnapshot
from host.record.recording import Recorder, read, tap_transport
from host.session.core import Layout
from protocol.lattice import Lattice


def snap(counter, n, rng):
    r = rng.normal(size=(n, 3))
    valid = rng.random(n) > 0.2
    r[~valid] = np.nan
    return LatticeSnapshot(counter, 1.0 + counter, 1.7e9 + counter, r, valid, (~valid).astype(np.uint8) * 0x10,
                           bool(valid.all()), 0.003)


class FakeEstimate:
    def __init__(self, joints, valid, yaw_std=None):
        self.joints, self.valid, self.method, self.residual, self.iterations = joints, valid, "global", 0.5, 3
        if yaw_std is not None:
            self.yaw_std = yaw_std


def write_sample(path, rng, n_snap=12, lattice=Lattice(3, 4)):
    n = lattice.n_links
    snaps = [snap(c, n, rng) for c in range(n_snap)]
    raws = [bytes(rng.integers(0, 256, size=int(rng.integers(1, 50)), dtype=np.uint8)) for _ in range(7)]
    joints = rng.normal(size=(3, lattice.rows, lattice.cols, 3))
    yaw_std = rng.random(size=(3, n))
    with Recorder(path, lattice, 0.02, session={"rate_hz": 145.0}, layout={"chips": []},
                  calibration={"links": []}) as rec:
        for s in snaps:
            rec.snapshot(s)
            rec.sync(s.counter, s.timestamp)
        for k, b in enumerate(raws):
            rec.raw(k % 2, "serial", b, f"port{k % 2}", t=10.0 + k)
        for k in range(3):
            rec.estimate(FakeEstimate(joints[k], np.ones(n, bool), yaw_std[k]), k, 1.0 + k, 1.7e9 + k,
                         error_joint=np.full((lattice.rows, lattice.cols), 0.5), error_pct_side=0.5)
        rec.contacts(2, 3.0, [{"id": 1, "index": [1.0, 2.0], "position": [0.01, 0.02, 0.0], "force_n": 1.25,
                               "radius_m": 0.004}])
    return snaps, raws, joints, yaw_std


def test_capsheet_reads_back_what_it_recorded(tmp_path):
    rng = np.random.Generator(np.random.MT19937(1))
    path = tmp_path / "run.mcap"
    snaps, raws, joints, yaw_std = write_sample(path, rng)
    rec = read(path)
    assert not rec.truncated and len(rec) == 12
    assert rec.counter.tolist() == list(range(12))
    np.testing.assert_array_equal(rec.valid[5], snaps[5].valid)
    np.testing.assert_array_equal(rec.status[5], snaps[5].status)
    np.testing.assert_array_equal(rec.readings[5], snaps[5].readings.astype(np.float32))  # NaN where invalid
    assert rec.timestamp.tolist() == [s.timestamp for s in snaps]
    assert [c[2] for c in rec.raw[0]] == raws[0::2] and [c[2] for c in rec.raw[1]] == raws[1::2]
    np.testing.assert_array_equal(rec.estimates["joints"], joints.astype(np.float32))
    np.testing.assert_array_equal(rec.estimates["yaw_std"], yaw_std.astype(np.float32))
    assert rec.estimates["error_pct_side"].tolist() == [0.5] * 3
    assert rec.sync.shape == (12, 2) and rec.sync[3].tolist() == [3, 4.0]
    assert rec.contacts[0][2][0]["force_n"] == 1.25
    assert rec.session["link_length_m"] == 0.02 and rec.session["rate_hz"] == 145.0
    assert rec.session["rows"] == 3 and rec.session["versions"]["capsheet"]
    assert set(rec.attachments) == {"layout.json", "calibration.json"}


class _JsonDecoders:
    """The contacts channel stays JSON: json.loads as its decoder (mcap's DecoderFactory interface)."""

    def decoder_for(self, message_encoding, schema):
        return json.loads if message_encoding == "json" else None


def test_the_mcap_packages_reader_sees_the_same_messages_and_foxglove_schemas(tmp_path):
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    rng = np.random.Generator(np.random.MT19937(2))
    path = tmp_path / "run.mcap"
    snaps, raws, joints, _ = write_sample(path, rng)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory(), _JsonDecoders()])
        summary = reader.get_summary()
        by_topic = {}
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            by_topic.setdefault(channel.topic, []).append((schema, channel, message, decoded))
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    counts = {t: len(v) for t, v in by_topic.items()}
    assert counts["/capsheet/snapshot"] == 12 and counts["/capsheet/sync"] == 12
    assert counts["/capsheet/raw/bus0"] == 4 and counts["/capsheet/raw/bus1"] == 3
    assert counts["/capsheet/estimate"] == 3 and counts["/capsheet/contacts"] == 1
    assert counts["/sheet/joints"] == 3 and counts["/sheet/scene"] == 4 and counts["/tf"] == 1
    assert summary.statistics.message_count == sum(counts.values())
    schema, channel, _, _ = by_topic["/sheet/scene"][0]
    assert (schema.name, schema.encoding, channel.message_encoding) == ("foxglove.SceneUpdate", "protobuf", "protobuf")
    assert by_topic["/sheet/joints"][0][0].name == "foxglove.PointCloud"
    assert by_topic["/tf"][0][0].name == "foxglove.FrameTransform"
    s, c, m, d = by_topic["/capsheet/snapshot"][7]
    assert (s.name, s.encoding, c.message_encoding) == ("capsheet.v2.Snapshot", "protobuf", "protobuf")
    # made without an aggregator: no counts, so its readings as float32 (decoded by mcap-protobuf-support
    # from the schema the file holds)
    assert len(d.counts) == 0 and d.n_links == 3 * 3 + 2 * 4
    r = np.array(d.readings, dtype=np.float32).reshape(-1, 3)
    np.testing.assert_array_equal(r, snaps[7].readings.astype(np.float32))
    v = np.unpackbits(np.frombuffer(d.valid, np.uint8), count=d.n_links, bitorder="little").astype(bool)
    np.testing.assert_array_equal(v, snaps[7].valid)
    assert m.log_time == int(round(snaps[7].wall_time * 1e9))
    # random bytes hold no SAMPLE frame: the compact serial channel keeps every byte in ``raw``
    assert by_topic["/capsheet/raw/bus0"][0][0].name == "capsheet.v2.RawSerialFrames"
    assert [d.raw for _, _, _, d in by_topic["/capsheet/raw/bus0"]] == raws[0::2]
    e = by_topic["/capsheet/estimate"][1][3]
    np.testing.assert_array_equal(np.array(e.joints, np.float32).reshape(joints[1].shape), joints[1].astype(np.float32))
    assert e.error_pct_side == 0.5 and e.method == "global"
    assert json.loads(meta["capsheet.session"]["link_length_m"]) == 0.02


# a second, minimal MCAP reader: records (opcode u8, length u64), chunks decompressed with zstd
def _records(buf: bytes):
    pos = 8
    while pos + 9 <= len(buf):
        op, length = struct.unpack_from("<BQ", buf, pos)
        body = buf[pos + 9:pos + 9 + length]
        if len(body) < length:
            return
        yield op, body
        pos += 9 + length


def _string(b: bytes, p: int):
    n = struct.unpack_from("<I", b, p)[0]
    return b[p + 4:p + 4 + n].decode(), p + 4 + n


def _decode(schema, data: bytes):
    """A message decoded with the schema its file holds (protobuf: a FileDescriptorSet), not capsheet's."""
    if schema is None or schema[1] != "protobuf":
        return data
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(schema[2]).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema[0])).FromString(data)


def _minimal_read(path):
    import zstandard

    buf = open(path, "rb").read()
    assert buf[:8] == b"\x89MCAP0\r\n"
    channels, messages, schemas = {}, [], {}

    def handle(op, body):
        if op == 0x03:  # Schema: id u16, name, encoding, data (u32 length)
            sid = struct.unpack_from("<H", body, 0)[0]
            name, p = _string(body, 2)
            enc, p = _string(body, p)
            n = struct.unpack_from("<I", body, p)[0]
            schemas[sid] = (name, enc, body[p + 4:p + 4 + n])
        elif op == 0x04:  # Channel: id u16, schema_id u16, topic
            cid, sid = struct.unpack_from("<HH", body, 0)
            channels[cid] = _string(body, 4)[0]
            schemas[("channel", cid)] = schemas.get(sid)
        elif op == 0x05:  # Message: channel u16, sequence u32, log_time u64, publish_time u64, data
            cid, _, log_time = struct.unpack_from("<HIQ", body, 0)
            messages.append((channels[cid], log_time, _decode(schemas[("channel", cid)], body[22:])))
        elif op == 0x06:  # Chunk: start u64, end u64, uncompressed size u64, crc u32, compression, records
            size = struct.unpack_from("<Q", body, 16)[0]
            comp, p = _string(body, 28)
            n = struct.unpack_from("<Q", body, p)[0]
            data = body[p + 8:p + 8 + n]
            if comp == "zstd":
                data = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
            elif comp == "lz4":
                import lz4.frame
                data = lz4.frame.decompress(data)
            for op2, body2 in _records(b"\0" * 8 + data):
                handle(op2, body2)

    for op, body in _records(buf):
        handle(op, body)
    return messages


def test_a_second_reader_written_from_the_mcap_spec_agrees(tmp_path):
    rng = np.random.Generator(np.random.MT19937(3))
    path = tmp_path / "run.mcap"
    snaps, raws, joints, _ = write_sample(path, rng)
    msgs = _minimal_read(path)
    snap_docs = [d for t, _, d in msgs if t == "/capsheet/snapshot"]
    assert [d.counter for d in snap_docs] == list(range(12))
    v = np.unpackbits(np.frombuffer(snap_docs[4].valid, np.uint8), count=snap_docs[4].n_links,
                      bitorder="little").astype(bool)
    np.testing.assert_array_equal(v, snaps[4].valid)
    np.testing.assert_array_equal(np.frombuffer(snap_docs[4].status, np.uint8), snaps[4].status)
    est = [d for t, _, d in msgs if t == "/capsheet/estimate"]
    np.testing.assert_array_equal(np.array(est[1].joints, np.float32).reshape(joints[1].shape),
                                  joints[1].astype(np.float32))
    assert [d.raw for t, _, d in msgs if t == "/capsheet/raw/bus1"] == raws[1::2]  # no SAMPLE frame in them


KILLED_WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    from host.snapshots.snapshot import LatticeSnapshot
    from host.record.recording import Recorder
    from protocol.lattice import Lattice
    lat = Lattice(3, 4)
    rec = Recorder(sys.argv[1], lat, 0.01, flush_interval_s=1e9, chunk_size=1 << 30)
    c = 0
    while True:
        r = np.full((lat.n_links, 3), float(c))
        rec.snapshot(LatticeSnapshot(c, float(c), 1.7e9 + c, r, np.ones(lat.n_links, bool),
                                     np.zeros(lat.n_links, np.uint8), True, 0.0))
        c += 1
        if c % 10 == 0:
            rec.flush()
            print(c, flush=True)
        if c >= 35:
            time.sleep(60)   # killed here: 30 snapshots in finished chunks, 5 after the last flush
""")


def test_a_killed_writer_leaves_a_file_read_up_to_its_last_chunk(tmp_path):
    from mcap.stream_reader import StreamReader
    from mcap.records import Channel, Message

    path = tmp_path / "killed.mcap"
    script = KILLED_WRITER
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    proc = subprocess.Popen([sys.executable, "-c", script, str(path)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        lines = [proc.stdout.readline().strip() for _ in range(3)]
        assert lines == ["10", "20", "30"]
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    rec = read(path)
    assert rec.truncated
    assert len(rec) == 30  # the three finished chunks; the 5 snapshots after the last flush are lost
    assert rec.counter.tolist() == list(range(30))
    assert float(rec.readings[29, 0, 0]) == 29.0
    # the mcap package's stream reader reads the same 30 messages before the cut
    n, topics = 0, {}
    with open(path, "rb") as f:
        with pytest.raises(Exception):  # noqa: B017 - it reports the cut in its own way
            for r in StreamReader(f).records:
                if isinstance(r, Channel):
                    topics[r.id] = r.topic
                n += isinstance(r, Message) and topics[r.channel_id] == "/capsheet/snapshot"
    assert n == 30


def test_read_names_a_file_that_is_not_a_capsheet_recording(tmp_path):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"not an mcap file at all")
    with pytest.raises(ValueError, match="is not an MCAP file"):
        read(bad)
    import foxglove
    other = tmp_path / "other.mcap"
    ctx = foxglove.Context()
    w = foxglove.open_mcap(str(other), context=ctx)
    foxglove.Channel("/x", context=ctx, message_encoding="json").log(b"{}")
    w.close()
    with pytest.raises(ValueError, match="not a capsheet recording"):
        read(other)


def test_tap_refuses_a_transport_it_cannot_see_into():
    class Other:
        name = "other"
    with pytest.raises(TypeError, match="Cannot record raw input of Other 'other'"):
        tap_transport(Other(), lambda kind, payload: None)


def test_layout_csv_and_json_round_trip_and_match_the_virtual_sheet(tmp_path):
    from virtual_sheet.sheet import VirtualSheet
    sheet = VirtualSheet("flat", "3x3", seed=4)
    for name in ("l.csv", "l.json"):
        sheet.write_layout(tmp_path / name)
        lay = Layout.load(tmp_path / name)
        assert lay.links == sheet.layout
        lay.save(tmp_path / ("again_" + name))
        assert Layout.load(tmp_path / ("again_" + name)).links == sheet.layout
    (tmp_path / "bad.csv").write_text("uid,link\n0x1,0\n0x2,0\n")
    with pytest.raises(ValueError, match="Link 0 is given to two chips"):
        Layout.load(tmp_path / "bad.csv")
    auto = Layout.auto([5, 3, 9], Lattice(2, 3))
    assert auto.links == {3: 0, 5: 1, 9: 2} and auto.is_auto


def test_capsheet_host_command_discovers_streams_and_records(tmp_path, capsys):
    from host.cli import main
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet
    sheet = VirtualSheet("gaussian", "5x5", seed=3)
    layout = sheet.write_layout(tmp_path / "sheet.csv")
    out = tmp_path / "run.mcap"
    with PtyDevice(sheet) as dev:
        rc = main(["host", "--port", dev.path, "--lattice", "5x5", "--layout", str(layout), "--rate", "100",
                   "--record", str(out), "--duration", "0.5", "--json", "-q", "--link-length", "0.015"])
    assert rc == 0
    captured = capsys.readouterr()
    assert "40 chips found, 40 assigned" in captured.err
    stats = json.loads(captured.out)
    rec = read(out)
    assert len(rec) == stats["aggregator"]["emitted"] >= 1  # how many depends on the load
    assert rec.complete.sum() == stats["aggregator"]["complete"]  # every emitted snapshot, as emitted
    assert not rec.truncated
    # every byte the transport counted was recorded, as received (and a few that came after the
    # statistics were taken, before the port closed); decoded again they are frames, not damage
    from protocol.framing import DecodeError, SampleBatch, StreamDecoder
    wire = b"".join(c[2] for c in rec.raw[0])
    assert len(wire) >= stats["buses"][0]["bytes_in"]
    events = StreamDecoder(batch_samples=True).feed(wire)
    assert not [e for e in events if isinstance(e, DecodeError)]
    assert sum(len(e) if isinstance(e, SampleBatch) else 1 for e in events) >= stats["buses"][0]["frames_in"]
    assert rec.session["link_length_m"] == 0.015 and rec.session["rate_hz"] == 100.0
    assert rec.session["transports"][0]["kind"] == "serial"
    assert {c["uid"] for c in rec.attachments["layout.json"]["chips"]} == {f"0x{u:016X}" for u in sheet.layout}
    cal = rec.attachments["calibration.json"]["links"]
    assert len(cal) == 40 and all(c["calibrated"] for c in cal)
    assert rec.attachments["stats.json"]["aggregator"]["emitted"] == len(rec)
    assert rec.sync.shape[0] >= len(rec)
    assert len(rec.estimates["counter"]) >= 1 and rec.estimates["joints"].shape[1:] == (5, 5, 3)


@pytest.mark.parametrize("argv, message", [
    (["--record", "run.npy"], "--record: invalid value 'run.npy': need an MCAP recording named *.mcap"),
    (["--can-log", "run.txt"], "--can-log: invalid value 'run.txt': need a CAN log (.log, .asc, .blf)"),
    (["--live", "70000"], "--live: invalid value '70000': need a TCP port >= 0 and <= 65535"),
    (["--link-length", "-1"], "--link-length: invalid value '-1': need a length"),
])
def test_capsheet_host_refuses_bad_recording_flags(argv, message, capsys):
    from host.cli import main
    with pytest.raises(SystemExit) as exc:
        main(["host", "--port", "loop://"] + argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_capsheet_host_names_the_port_it_cannot_open(tmp_path, capsys):
    from host.cli import main
    missing = str(tmp_path / "nope")
    assert main(["host", "--port", missing, "--duration", "0.1"]) == 1
    assert f"Cannot open serial port {missing!r}" in capsys.readouterr().err


def test_a_loaded_layout_is_not_marked_auto_assigned(tmp_path):
    path = tmp_path / "layout.csv"
    Layout({0x0123456789ABCDEF: 0, 0x42: 1}).save(path)
    loaded = Layout.load(path)
    assert loaded.links == {0x0123456789ABCDEF: 0, 0x42: 1}
    assert loaded.is_auto is False


def test_version(capsys):
    from host.cli import main
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("capsheet ") and out.split()[1][0].isdigit()


def test_capsheet_demo_records_snapshots_and_estimates_with_their_error(tmp_path):
    out = tmp_path / "demo.mcap"
    proc = subprocess.run([sys.executable, "-m", "host.cli", "demo", "--lattice", "6x6", "--duration", "1.5",
                           "--rate", "20", "--record", str(out), "--out", str(tmp_path / "demo.png"), "--json"],
                          capture_output=True, text=True, timeout=300)
    doc = json.loads(proc.stdout)  # --json: the summary alone on stdout, whatever the verdict
    rec = read(out)
    assert rec.session["mode"] == "demo" and rec.session["shape"] == "grow"
    # every snapshot the sheet made, also those the busy estimator skipped (newest wins) and
    # those before the measured window ("snapshots" counts the window's SYNCs only)
    assert len(rec) == doc["snapshots_emitted"] >= doc["snapshots"]
    assert len(rec.estimates["counter"]) == doc["compared_with_truth"]
    if doc["compared_with_truth"]:
        assert np.mean(rec.estimates["error_pct_side"]) == pytest.approx(doc["mean_error_pct_side"], abs=1e-3)


def test_a_file_cut_anywhere_reads_what_it_holds_or_says_why_not(tmp_path):
    rng = np.random.Generator(np.random.MT19937(4))
    path = tmp_path / "run.mcap"
    with Recorder(path, Lattice(3, 4), 0.01, flush_interval_s=0.0) as rec:  # a chunk per message
        for c in range(20):
            rec.snapshot(snap(c, 17, rng))
    data = path.read_bytes()
    counts = []
    for cut in (60, len(data) // 3, len(data) // 2, len(data) - 5):
        (tmp_path / "cut.mcap").write_bytes(data[:cut])
        try:
            r = read(tmp_path / "cut.mcap")
        except ValueError as exc:
            assert "cut short before its 'capsheet.session' metadata" in str(exc)
            counts.append(None)
            continue
        assert r.truncated and r.counter.tolist() == list(range(len(r)))
        counts.append(len(r))
    assert counts[0] is None and 0 < counts[1] < counts[2] <= 20 and counts[3] == 20


def test_an_unwritable_recording_is_one_line_not_a_traceback(tmp_path, capsys):
    from host.cli import main
    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit) as exc:  # checked with the other values, before the port is opened
        main(["host", "--port", "loop://", "--record", str(tmp_path / "file" / "run.mcap"), "--duration", "0.1"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("capsheet host: argument --record: ") and "is a file, not a folder" in err, err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("batch", [1, 5, 12, 100])
def test_iter_snapshots_gives_the_recorded_snapshots_in_batches_in_order(tmp_path, batch):
    from host.record.recording import iter_snapshots, snapshot_count
    rng = np.random.Generator(np.random.MT19937(7))
    path = tmp_path / "run.mcap"
    snaps, *_ = write_sample(path, rng)
    parts = list(iter_snapshots(path, batch))
    assert [len(p) for p in parts] == [min(batch, 12 - k) for k in range(0, 12, batch)]
    assert all(p.session["rows"] == 3 and p.session["link_length_m"] == 0.02 for p in parts)
    cat = {f: np.concatenate([getattr(p, f) for p in parts])
           for f in ("counter", "timestamp", "wall_time", "readings", "valid", "status")}
    assert cat["counter"].tolist() == [s.counter for s in snaps]
    assert cat["timestamp"].tolist() == [s.timestamp for s in snaps]
    assert cat["wall_time"].tolist() == [s.wall_time for s in snaps]
    np.testing.assert_array_equal(cat["readings"], np.stack([s.readings for s in snaps]).astype(np.float32))
    np.testing.assert_array_equal(cat["valid"], np.stack([s.valid for s in snaps]))
    np.testing.assert_array_equal(cat["status"], np.stack([s.status for s in snaps]))
    # the count from the summary is the number of snapshot messages a reader written from the spec sees
    assert snapshot_count(path) == sum(t == "/capsheet/snapshot" for t, _, _ in _minimal_read(path)) == 12


def test_iter_snapshots_reads_a_cut_file_as_far_as_read_does(tmp_path):
    from host.record.recording import iter_snapshots, snapshot_count
    rng = np.random.Generator(np.random.MT19937(8))
    path = tmp_path / "run.mcap"
    with Recorder(path, Lattice(3, 4), 0.01, flush_interval_s=0.0) as rec:  # a chunk per message
        for c in range(20):
            rec.snapshot(snap(c, 17, rng))
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) // 2])
    whole = read(cut)
    got = np.concatenate([p.counter for p in iter_snapshots(cut, 3)])
    assert 0 < len(whole) < 20 and got.tolist() == whole.counter.tolist()
    assert snapshot_count(cut) is None  # no summary: the count is not known beforehand
    cut.write_bytes(data[:60])
    with pytest.raises(ValueError, match="capsheet.session"):
        list(iter_snapshots(cut))
    with pytest.raises(ValueError, match="batch must be >= 1"):
        list(iter_snapshots(path, 0))


def test_a_large_sheet_is_compressed_at_the_cheaper_level_and_a_small_one_at_the_tighter(tmp_path):
    """`host.record.recording.compression_level_for`: every writer call holds the interpreter lock, so a
    sheet of more than LARGE_SHEET_LINKS links (64x64: ~14 MB/s) is written at zstd level 1, a
    smaller one at 9 (benchmarks/bench_record_compression.py). The same raw input recorded for a
    64x64 and a 14x14 sheet: the first file is larger (the level reached the writer); each one
    reads back whole with the mcap library."""
    from mcap.reader import make_reader

    from host.record.recording import COMPRESSION_LEVEL, COMPRESSION_LEVEL_LARGE

    rng = np.random.default_rng(3)
    reads = [np.cumsum(rng.integers(-3, 4, 6000)).astype("<i2").tobytes() for _ in range(24)]
    sizes = {}
    for name in ("64x64", "14x14"):
        path = tmp_path / f"{name}.mcap"
        rec = Recorder(path, Lattice.parse(name), 0.01)
        assert rec.compression_level == (COMPRESSION_LEVEL_LARGE if name == "64x64" else COMPRESSION_LEVEL)
        for i, data in enumerate(reads * 4):
            rec.raw(i % 5, "serial", data)
        rec.close()
        sizes[name] = path.stat().st_size
        with open(path, "rb") as f:
            got = [m.data for _, ch, m in make_reader(f).iter_messages() if ch.topic.startswith("/capsheet/raw/")]
        assert len(got) == 96
    assert sizes["64x64"] > 1.01 * sizes["14x14"]


def test_documents_are_encoded_before_the_writers_lock_is_taken(tmp_path, monkeypatch):
    """The receive threads record snapshots under the writer's lock while they hold the feed's; a
    64x64 layout's JSON (~0.1 s) encoded under it stalled a following host's first second. Every attachment is encoded with the lock free (a split set's next file writes
    the bytes kept), and the file still holds it."""
    import host.record.writer as record  # the writer encodes its JSON attachments
    from mcap.reader import make_reader

    seen = []
    real = record._json_attachment

    def encode(doc):
        owner = sys._getframe(1).f_locals["self"]  # the Recorder encoding it (also during __init__)
        seen.append(owner._io._is_owned())  # the writer's lock held by this thread?
        return real(doc)

    monkeypatch.setattr(record, "_json_attachment", encode)
    path = tmp_path / "r.mcap"
    rec = Recorder(path, Lattice(3, 3), 0.01, session={"rate_hz": 10.0}, layout={"chips": [1, 2, 3]})
    rec._document("attachment", "extra.json", {"a": [1, 2]})
    rec.close()
    assert seen and not any(seen), seen
    with open(path, "rb") as f:
        names = {a.name for a in make_reader(f).iter_attachments()}
    assert {"layout.json", "extra.json"} <= names


def test_a_json_attachment_keeps_its_document_and_a_key_a_line():
    """Compact values through json's C encoder (its indenting encoder is pure Python: 0.3 s of the
    interpreter for a 64x64 sheet's documents at a following host's start), the top-level keys one
    a line for whoever opens the file; read back by json itself, the same document."""
    import json

    import host.record.writer as record  # the writer encodes its JSON attachments
    doc = {"rows": 64, "links": [{"link": k, "uid": f"0x{k:016X}", "xyz": [0.5 * k, -1e-3, 2.0]}
                                 for k in range(50)], "calibration": None, 7: "seven",
           "np": np.arange(3, dtype=np.int16), "f": np.float32(0.25)}
    text = record._json_attachment(doc).decode()
    back = json.loads(text)
    assert back == json.loads(json.dumps(doc, default=record._jsonable))
    assert back["np"] == [0, 1, 2] and back["f"] == 0.25 and back["7"] == "seven"
    lines = text.strip().splitlines()
    assert lines[0] == "{" and lines[-1] == "}" and len(lines) == len(doc) + 2
    assert lines[1] == ' "rows": 64,' and lines[2].startswith(' "links": [{"link": 0, ')
    assert json.loads(record._json_attachment([1, 2])) == [1, 2] and json.loads(record._json_attachment({})) == {}
