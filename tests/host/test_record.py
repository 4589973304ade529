"""Recordings (.npy written incrementally, loadable by plain numpy), layout files, and the
``capsheet host`` command end to end on a virtual pty sheet."""

from __future__ import annotations

import json

import numpy as np
import pytest

from host.aggregator import LatticeSnapshot
from host.session import Layout
from host.record import RecordWriter, read_recording
from protocol.lattice import Lattice


def snap(counter, n, rng):
    r = rng.normal(size=(n, 3))
    valid = rng.random(n) > 0.2
    r[~valid] = np.nan
    return LatticeSnapshot(counter, 1.0 + counter, 1e9 + counter, r, valid, (~valid).astype(np.uint8) * 0x10,
                           bool(valid.all()), 0.003)


def test_recording_loads_with_plain_numpy_while_and_after_writing(tmp_path):
    rng = np.random.Generator(np.random.MT19937(1))
    path = tmp_path / "out.cap"
    snaps = [snap(c, 17, rng) for c in range(30)]
    w = RecordWriter(path, 17, {"rows": 3, "cols": 4, "rate_hz": 100})
    for s in snaps[:10]:
        w.write(s)
    w.flush()
    assert np.load(path).shape == (10,)  # readable mid-recording
    for s in snaps[10:]:
        w.write(s)
    w.close(stats={"emitted": 30})
    rec = np.load(path, mmap_mode="r")
    assert rec.shape == (30,)
    assert rec["counter"].tolist() == list(range(30))
    np.testing.assert_allclose(rec["readings"][7], snaps[7].readings.astype(np.float32))
    assert (rec["valid"][3] == snaps[3].valid).all() and (rec["status"][3] == snaps[3].status).all()
    meta = json.loads((tmp_path / "out.cap.json").read_text())
    assert meta["rows"] == 3 and meta["count"] == 30 and meta["stats"] == {"emitted": 30}


def test_a_recording_cut_short_is_read_from_its_size(tmp_path):
    rng = np.random.Generator(np.random.MT19937(2))
    path = tmp_path / "cut.cap"
    w = RecordWriter(path, 5, flush_interval_s=1e9)
    for c in range(8):
        w.write(snap(c, 5, rng))
    w._f.flush()  # a crash: the header still says 0 records, the last record half written
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.truncate(size - 10)
    rec = read_recording(path)
    assert len(rec) == 7 and rec.data["counter"].tolist() == list(range(7))
    w._f.close()


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
    out = tmp_path / "run.cap"
    with PtyDevice(sheet) as dev:
        rc = main(["host", "--port", dev.path, "--lattice", "5x5", "--layout", str(layout), "--rate", "100",
                   "--record", str(out), "--duration", "0.5", "--json"])
    assert rc == 0
    captured = capsys.readouterr()
    assert "40 chips found, 40 assigned" in captured.err
    stats = json.loads(captured.out)
    assert stats["aggregator"]["emitted"] >= 1  # how many in 0.5 s depends on the machine's load
    rec = np.load(out)
    assert rec.shape[0] == stats["aggregator"]["emitted"]  # every snapshot recorded
    assert int(rec["complete"].sum()) == stats["aggregator"]["complete"]


def test_capsheet_host_names_the_port_it_cannot_open(tmp_path, capsys):
    from host.cli import main
    missing = str(tmp_path / "nope")
    assert main(["host", "--port", missing, "--duration", "0.1"]) == 1
    assert f"Cannot open serial port {missing!r}" in capsys.readouterr().err


def test_a_loaded_layout_is_not_marked_auto_assigned(tmp_path):
    from host.session import Layout
    path = tmp_path / "layout.csv"
    Layout({0x0123456789ABCDEF: 0, 0x42: 1}).save(path)
    loaded = Layout.load(path)
    assert loaded.links == {0x0123456789ABCDEF: 0, 0x42: 1}
    assert loaded.is_auto is False
