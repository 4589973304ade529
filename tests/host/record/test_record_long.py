"""Recordings for long runs: the compact format (chips' counts, protobuf) read back exactly
and by an independent reader, an old-format (capsheet-mcap-1) recording still read and replayed,
split sets (--split-size / --split-duration) read alone and as a whole, and the free-space check."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from host.snapshots.aggregator import Aggregator
from host.snapshots.snapshot import LatticeSnapshot
from host.record.recording import Recorder, iter_snapshots, read, recording_set, snapshot_count, split_path
from protocol.constants import counts_to_si
from protocol.lattice import Lattice

OLD = Path(__file__).parent / "data" / "recording_v1.mcap"  # written by capsheet 24038ed (JSON channels)


def _calibration(lat: Lattice, rng) -> dict:
    """A calibration.json as `Recorder.session_facts` writes it: node k+1 on link k, own offsets/sensitivities."""
    return {"range_code": 0, "links": [
        {"link": k, "uid": f"0x{k:016X}", "node": k + 1, "bus": 0,
         "offset": rng.normal(0, 20, 3).tolist(), "sensitivity": rng.uniform(980, 1060, 3).tolist(),
         "calibrated": True} for k in range(lat.n_links)]}


def _aggregated(lat: Lattice, cal: dict, rng, n: int) -> tuple[list[LatticeSnapshot], np.ndarray]:
    """``n`` snapshots an Aggregator makes of random counts (some links missing), and those counts."""
    L = lat.n_links
    agg = Aggregator(L, {c["node"]: c["link"] for c in cal["links"]}, deadline_s=0.01,
                     offset=[c["offset"] for c in cal["links"]], sensitivity=[c["sensitivity"] for c in cal["links"]])
    counts = rng.integers(-60, 60, size=(n, L, 3)).astype(np.int16)  # a sheet near rest: ~1 g on z
    counts[..., 2] += 1024
    snaps = []
    for k in range(n):
        here = rng.random(L) > 0.1
        nodes = np.arange(1, L + 1, dtype=np.int64)[here]
        agg.open_counter(k, k * 0.01)
        agg.ingest_batch(nodes, np.full(nodes.shape, k, np.uint16), counts[k][here], np.zeros(nodes.shape, np.uint8),
                         now=k * 0.01 + 0.001)
        agg.poll(k * 0.01 + 0.05)
        snaps += agg.drain()
    return snaps, counts


def test_snapshots_are_recorded_as_counts_and_read_back_as_the_aggregators_readings(tmp_path):
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    rng = np.random.Generator(np.random.MT19937(34))
    lat = Lattice(3, 4)
    cal = _calibration(lat, rng)
    snaps, counts = _aggregated(lat, cal, rng, 20)
    assert len(snaps) == 20 and not all(s.valid.all() for s in snaps)
    path, plain = tmp_path / "run.mcap", tmp_path / "plain.mcap"
    for p, compact in ((path, True), (plain, False)):  # counts against each link's average, or as they are
        with Recorder(p, lat, 0.01, calibration=cal, compact=compact) as rec:
            for s in snaps:
                rec.snapshot(s)
    np.testing.assert_array_equal(read(plain).readings, read(path).readings)
    back = read(path)
    for k, s in enumerate(snaps):  # exactly what the live consumers saw, as float32
        np.testing.assert_array_equal(back.readings[k], s.readings.astype(np.float32))
        np.testing.assert_array_equal(back.valid[k], s.valid)
    # ... and by hand from the counts ingested and the calibration (not capsheet's reader)
    off = np.array([c["offset"] for c in cal["links"]])
    sens = np.array([c["sensitivity"] for c in cal["links"]])
    expect = counts_to_si(counts[7].astype(float), off, sens)
    expect[~snaps[7].valid] = np.nan
    np.testing.assert_array_equal(back.readings[7], expect.astype(np.float32))
    # an independent reader (mcap-protobuf-support, from the schema in the file) sees the counts
    # recorded as they are
    with open(plain, "rb") as f:
        msgs = [d for _, c, _, d in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
                if c.topic == "/capsheet/snapshot"]
    got = np.array(msgs[7].counts).reshape(-1, 3)
    v = snaps[7].valid
    np.testing.assert_array_equal(got[v], counts[7][v])
    assert (got[~v] == 0).all()
    # the batched reader agrees
    batches = list(iter_snapshots(path, batch=6))
    assert [len(b) for b in batches] == [6, 6, 6, 2]
    np.testing.assert_array_equal(np.concatenate([b.readings for b in batches]), back.readings)


def test_an_old_format_recording_still_reads_and_replays():
    from host.record.replay import Replay

    rec = read(OLD)
    assert rec.session["format"] == "capsheet-mcap-1" and len(rec) == 77 and not rec.truncated
    assert np.all(np.diff(rec.counter.astype(int)) % 65536 == 1)
    g = np.linalg.norm(rec.readings[rec.valid], axis=1)
    assert np.all(np.abs(g - 9.81) < 0.5)  # a sheet at rest: gravity on every link
    assert rec.estimates["joints"].shape == (25, 3, 3, 3) and len(rec.raw[0]) == 92
    rp = Replay(OLD)
    replayed = list(rp.snapshots())
    by_key = {(int(c), float(t)): k for k, (c, t) in enumerate(zip(rec.counter, rec.timestamp))}
    same = 0
    for s in replayed:
        k = by_key[(int(s.counter), float(s.timestamp))]
        same += bool(np.array_equal(np.nan_to_num(s.readings.astype(np.float32), nan=1e30),
                                    np.nan_to_num(rec.readings[k], nan=1e30)) and np.array_equal(s.valid, rec.valid[k]))
    assert len(replayed) == 77 and same == 77


def _sample_recorder(path, lat, cal, **kw):
    return Recorder(path, lat, 0.01, calibration=cal, layout={"chips": []}, session={"rate_hz": 100.0}, **kw)


@pytest.mark.parametrize("how", [{"split_size": 1}, {"split_duration": 1e-9}])
def test_a_split_recording_is_files_in_sequence_each_readable_alone_and_read_as_a_set(tmp_path, how):
    from host.cli import main

    rng = np.random.Generator(np.random.MT19937(7))
    lat = Lattice(3, 4)
    cal = _calibration(lat, rng)
    snaps, _ = _aggregated(lat, cal, rng, 30)
    base = tmp_path / "run.mcap"
    with _sample_recorder(base, lat, cal, **how) as rec:
        for k, s in enumerate(snaps):
            rec.snapshot(s)
            rec.sync(s.counter, s.timestamp)
            if k % 10 == 9:
                rec.flush()  # each flush starts the next file (the split is due at once)
    files = [split_path(base, i) for i in range(4)]
    assert rec.paths == files and recording_set(base) == files and not base.exists()
    assert [f.name for f in files] == ["run_0000.mcap", "run_0001.mcap", "run_0002.mcap", "run_0003.mcap"]
    for i, f in enumerate(files):  # each alone: session facts, calibration, its own share of snapshots
        alone = read(f)
        assert not alone.truncated and alone.session["rate_hz"] == 100.0
        assert alone.attachments["calibration.json"] == cal
        assert alone.metadata["capsheet.split"]["index"] == i
        assert len(alone) == (10 if i < 3 else 0)
    whole = read(base)
    assert len(whole) == 30 and whole.counter.tolist() == list(range(30)) and whole.sync.shape == (30, 2)
    np.testing.assert_array_equal(whole.readings, np.stack([s.readings for s in snaps]).astype(np.float32))
    assert read([str(f) for f in files]).counter.tolist() == list(range(30))
    assert snapshot_count(base) == 30
    assert sum(len(b) for b in iter_snapshots(base, batch=8)) == 30
    npz = tmp_path / "j.npz"
    assert main(["estimate", str(base), "--out", str(npz), "--jobs", "1", "-q"]) == 0
    assert np.load(npz)["counter"].tolist() == list(range(30))


def test_free_space_is_checked_before_and_during_recording_and_stops_it_cleanly(tmp_path):
    rng = np.random.Generator(np.random.MT19937(8))
    lat = Lattice(3, 4)
    cal = _calibration(lat, rng)
    snaps, _ = _aggregated(lat, cal, rng, 30)
    free = [10_000]
    with pytest.raises(ValueError, match=r"only 0 MB free .* \(need 1 MB free to record\): nothing recorded"):
        _sample_recorder(tmp_path / "no.mcap", lat, cal, min_free=1_000_000, free_bytes=lambda d: free[0])
    assert not (tmp_path / "no.mcap").exists()
    free[0] = 5_000_000
    stops = []
    path = tmp_path / "run.mcap"
    with _sample_recorder(path, lat, cal, min_free=1_000_000, free_bytes=lambda d: free[0],
                          on_stop=stops.append) as rec:
        for k, s in enumerate(snaps):
            rec.snapshot(s)
            if k == 9:
                rec.flush()  # 5 MB free: goes on
            if k == 19:
                free[0] = 999_999
                rec.flush()  # below: stops, the file closed with its summary
    assert rec.stopped == stops[0] and len(stops) == 1 and "1 MB left free" in stops[0]
    assert rec.not_recorded == 10 and rec.counts["/capsheet/snapshot"] == 20
    back = read(path)
    assert not back.truncated and back.counter.tolist() == list(range(20))
    assert snapshot_count(path) == 20


def test_the_free_space_check_reads_the_real_disk(tmp_path):
    need = shutil.disk_usage(tmp_path).free + 10 ** 12
    with pytest.raises(ValueError, match="MB free on the disk of"):
        Recorder(tmp_path / "x.mcap", Lattice(3, 3), 0.01, min_free=need)
    with Recorder(tmp_path / "y.mcap", Lattice(3, 3), 0.01, min_free=1) as rec:
        rec.flush()
    assert rec.stopped is None and read(tmp_path / "y.mcap").session["rows"] == 3


def test_capsheet_host_splits_its_recording_and_replay_takes_the_set(tmp_path, capsys):
    """End to end over a real pty: --split-size makes numbered files, each readable alone;
    capsheet replay of the set by its name replays every snapshot identical."""
    from host.cli import main
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet
    sheet = VirtualSheet("gaussian", "4x4", seed=5)
    layout = sheet.write_layout(tmp_path / "sheet.csv")
    out = tmp_path / "run.mcap"
    with PtyDevice(sheet) as dev:
        rc = main(["host", "--port", dev.path, "--lattice", "4x4", "--layout", str(layout), "--rate", "100",
                   "--record", str(out), "--split-size", "0.001", "--duration", "3", "-q"])
    assert rc == 0
    files = recording_set(out)
    assert len(files) >= 2 and files[0].name == "run_0000.mcap"
    assert f"to {len(files)} files, {files[0]}" in capsys.readouterr().err
    assert all(read(f).attachments["calibration.json"]["links"] for f in files)
    whole = read(out)
    assert len(whole) == sum(len(read(f)) for f in files) >= 1
    assert main(["replay", str(out), "--json", "-q", "--no-estimate"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["snapshots_identical"] == len(whole)


def test_capsheet_host_refuses_to_record_without_the_free_space_it_needs(tmp_path, capsys):
    from host.cli import main
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet
    sheet = VirtualSheet("flat", "3x3", seed=5)
    layout = sheet.write_layout(tmp_path / "sheet.csv")
    huge_mb = shutil.disk_usage(tmp_path).free / 1e6 + 1e6
    with PtyDevice(sheet) as dev:
        with pytest.raises(SystemExit) as exc:
            main(["host", "--port", dev.path, "--lattice", "3x3", "--layout", str(layout), "--rate", "50",
                  "--record", str(tmp_path / "run.mcap"), "--min-free", f"{huge_mb:.0f}", "--duration", "1", "-q"])
    assert "MB free on the disk of" in str(exc.value) and "nothing recorded" in str(exc.value)
    assert not (tmp_path / "run.mcap").exists()
