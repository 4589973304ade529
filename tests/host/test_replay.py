"""Replay as a transport (host/replay.py), ``capsheet replay`` / ``capsheet estimate``, and CAN logs
written through python-can's loggers, read by the ``cantools decode`` command line and replayed."""

from __future__ import annotations

from collections import Counter
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from host.record import read
from host.replay import Replay, ReplayTransport
from protocol.dbc import DBC_ID_MASK, DBC_PATH

_can_channel = iter(range(10_000))


@pytest.fixture(scope="module")
def pty_recording(tmp_path_factory):
    """A real session: the virtual 5x5 sheet on a pty, ``capsheet host --record``."""
    from host.cli import main
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet

    from virtual_sheet.sensor import SensorModel

    d = tmp_path_factory.mktemp("pty")
    # chips with their own offsets and sensitivities: the replay must use the recorded calibration
    sheet = VirtualSheet("gaussian", "5x5", seed=5,
                         sensor=SensorModel(noise_pct_g=0.5, bias_counts=6.0, scale_error=0.02, chip_seed=3))
    layout = sheet.write_layout(d / "sheet.csv")
    out = d / "run.mcap"
    with PtyDevice(sheet) as dev:
        assert main(["host", "--port", dev.path, "--lattice", "5x5", "--layout", str(layout), "--rate", "100",
                     "--record", str(out), "--duration", "0.6", "-q"]) == 0
    return out


@pytest.fixture(scope="module")
def can_recording(tmp_path_factory):
    """A real session on two python-can virtual buses, recorded to MCAP and to three CAN logs."""
    from host.cli import main
    from virtual_sheet.devices import CanDevice
    from virtual_sheet.sheet import VirtualSheet

    d = tmp_path_factory.mktemp("can")
    sheet = VirtualSheet("gaussian", "4x4", seed=6, transport="can")
    layout = sheet.write_layout(d / "sheet.csv")
    n = next(_can_channel)
    chans = [f"rp_{n}_a", f"rp_{n}_b"]
    with CanDevice(sheet, n_buses=2, channels=chans) as dev:  # noqa: F841
        # a long deadline: counters complete even on a loaded machine (the test compares complete ones)
        argv = ["host", "--lattice", "4x4", "--layout", str(layout), "--rate", "50", "--duration", "0.8", "-q",
                "--deadline-ms", "300",
                "--record", str(d / "run.mcap"), "--can-log", str(d / "run.log")]
        for c in chans:
            argv += ["--can", f"virtual:{c}"]
        assert main(argv) == 0
    # the same frames through python-can's ASC and BLF writers
    import can
    frames = list(can.LogReader(str(d / "run.log")))
    for suffix in (".asc", ".blf"):
        with can.Logger(str(d / f"run{suffix}")) as w:
            for m in frames:
                w.on_message_received(can.Message(timestamp=m.timestamp, arbitration_id=m.arbitration_id,
                                                  is_extended_id=m.is_extended_id, data=m.data, is_fd=m.is_fd,
                                                  is_rx=m.is_rx, channel=int(m.channel.removeprefix("can"))))
    return d


def _by_counter(snaps):
    return {int(s.counter): s for s in snaps}


def test_replay_of_a_serial_recording_makes_the_recorded_snapshots(pty_recording):
    rec = read(pty_recording)
    assert len(rec) >= 40  # complete or not (a loaded machine misses deadlines): replayed alike
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


def test_capsheet_replay_command_json_is_pure_and_compares(pty_recording, capsys):
    from host.cli import main
    assert main(["replay", str(pty_recording), "--json"]) == 0
    cap = capsys.readouterr()
    doc = json.loads(cap.out)
    rec = read(pty_recording)
    assert doc["snapshots"] == doc["snapshots_compared"] == doc["snapshots_identical"] == len(rec)
    assert doc["estimates"] == int(rec.valid.any(axis=1).sum())
    assert doc["estimates_compared"] == len(rec.estimates["counter"]) >= 1
    assert doc["estimate_change_pct_side_max"] < 0.5  # today's estimator on the same data
    assert "replay" in cap.err  # the progress bar goes to stderr


@pytest.mark.parametrize("argv, code, message", [
    (["replay", "nope.mcap"], 2, "recording: invalid value 'nope.mcap': no such file"),
    (["replay", "x.log"], 2, "give the lattice"),
    (["replay", "run.mcap", "--speed", "0"], 2, "invalid speed '0'"),
    (["replay", "run.mcap", "--speed", "fast"], 2, "invalid speed 'fast'"),
    (["replay", "bad.mcap"], 1, "is not an MCAP file"),
    (["estimate", "bad.mcap", "--out", "x.npz"], 1, "is not an MCAP file"),
    (["replay", "x.log", "--lattice", "3"], 2, "--lattice: invalid value '3'"),
    (["estimate", "run.mcap", "--out", "x.npz", "--link-length", "-2"], 2, "need a length >= 0.0001"),
    (["estimate", "run.mcap", "--out", "x.csv"], 2, "--out: invalid value 'x.csv': need an output file"),
    (["estimate", "run.mcap", "--out", "x.npz", "--jobs", "0"], 2, "need an integer >= 1"),
    (["estimate", "run.mcap", "--out", "run.mcap", "--overwrite"], 2, "is also an input of this command"),
    (["replay", "run.mcap", "--record", "bad.mcap"], 2, "bad.mcap exists: add --overwrite"),
])
def test_bad_replay_and_estimate_arguments_get_one_line(argv, code, message, tmp_path, capsys, monkeypatch):
    from host.cli import main
    monkeypatch.chdir(tmp_path)
    (tmp_path / "x.log").write_text("(1.0) can0 00000001#00 R\n")
    (tmp_path / "bad.mcap").write_bytes(b"\x00garbage" * 10)
    (tmp_path / "run.mcap").write_bytes(b"\x00garbage" * 10)
    try:
        rc = main(argv)
    except SystemExit as exc:
        rc = exc.code
    assert rc == code
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_capsheet_estimate_writes_npz_and_mcap_with_the_estimators_joints(pty_recording, tmp_path, capsys):
    from host.analysis.estimator import estimate
    from host.cli import main

    rec = read(pty_recording, raw=False)
    npz = tmp_path / "joints.npz"
    assert main(["estimate", str(pty_recording), "--out", str(npz), "--jobs", "2", "--batch", "16",
                 "--json", "-q"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["snapshots"] == len(rec) and doc["estimated"] == int(rec.valid.any(axis=1).sum())
    z = np.load(npz)
    assert z["joints"].shape == (len(rec), 5, 5, 3)
    assert z["counter"].tolist() == rec.counter.tolist()
    # each --batch of 16 starts cold at its own first snapshot and is solved one at a time (the
    # compiled kernel built) or by estimate_batch (numpy alone), as here
    from host.analysis.estimator import estimate_batch
    from host.cli.estimate import GROUP, batched
    side = 0.01 * 4
    for s0 in range(0, len(rec), 16):
        ks = [k for k in range(s0, min(s0 + 16, len(rec))) if rec.valid[k].any()]
        for k in range(s0, min(s0 + 16, len(rec))):
            if k not in ks:  # nothing to estimate: NaN
                assert np.isnan(z["joints"][k]).all()
        if not ks:
            continue
        ests = estimate_batch(rec.readings[ks].astype(float), 5, 5, 0.01, valid=rec.valid[ks], batch=GROUP,
                              bad_readings="mask")
        prev = None
        for k, e in zip(ks, ests):
            prev = estimate(rec.readings[k].astype(float), 5, 5, 0.01, valid=rec.valid[k], previous=prev,
                            bad_readings="mask")
            exact, other = (e, prev) if batched() else (prev, e)
            np.testing.assert_allclose(z["joints"][k], exact.joints, rtol=0, atol=1e-12)
            # and the other way agrees to the solver's tolerance (0.03 % of side)
            assert np.abs(z["joints"][k] - other.joints).max() / side * 100 <= 0.03
    out = tmp_path / "shapes.mcap"
    assert main(["estimate", str(pty_recording), "--out", str(out), "--png", "-q", "--batch", "16"]) == 0
    again = read(out)
    ok = np.isfinite(z["residual"])
    assert len(again) == len(rec) and len(again.estimates["counter"]) == int(ok.sum())
    np.testing.assert_allclose(again.estimates["joints"], z["joints"][ok].astype(np.float32), atol=1e-6)
    assert Path(out.with_suffix(".png")).stat().st_size > 10_000
    assert "yaw_std" not in z.files and "yaw_std" not in again.estimates  # sampled: only when asked


def test_capsheet_estimate_uncertainty_is_the_estimators_when_asked_for(pty_recording, tmp_path, capsys):
    from host.analysis.estimator import estimate
    from host.cli import main

    rec = read(pty_recording, raw=False)
    npz = tmp_path / "joints.npz"
    assert main(["estimate", str(pty_recording), "--out", str(npz), "--jobs", "1", "--batch", "8",
                 "--uncertainty", "--json", "-q"]) == 0
    assert json.loads(capsys.readouterr().out)["uncertainty"] is True
    z = np.load(npz)
    ks = [k for k in range(8) if rec.valid[k].any()]  # the first batch
    from host.analysis.estimator import estimate_batch
    from host.cli.estimate import GROUP, batched
    last = estimate_batch(rec.readings[ks].astype(float), 5, 5, 0.01, valid=rec.valid[ks], batch=GROUP,
                          bad_readings="mask")[-1]
    prev = None  # one at a time
    for k in ks:
        prev = estimate(rec.readings[k].astype(float), 5, 5, 0.01, valid=rec.valid[k], previous=prev,
                        bad_readings="mask")
    exact, other = (last, prev) if batched() else (prev, last)
    np.testing.assert_allclose(z["yaw_std"][ks[-1]], exact.yaw_std, rtol=1e-9, equal_nan=True)
    np.testing.assert_allclose(z["joint_std"][ks[-1]], exact.joint_std, rtol=1e-9)
    # the other way: the same uncertainty, to the yaws' tolerance
    np.testing.assert_allclose(z["yaw_std"][ks[-1]], other.yaw_std, rtol=0.02, equal_nan=True)
    assert np.all(z["yaw_std"][ks][:, rec.valid[ks[-1]]] > 0)
    out = tmp_path / "shapes.mcap"
    assert main(["estimate", str(pty_recording), "--out", str(out), "-q", "--uncertainty"]) == 0
    again = read(out)
    assert again.estimates["yaw_std"].shape == (len(again.estimates["counter"]), rec.valid.shape[1])


def test_capsheet_estimate_of_a_can_log_replays_it_first(can_recording, tmp_path, capsys):
    from host.cli import main
    npz = tmp_path / "j.npz"
    assert main(["estimate", str(can_recording / "run.log"), "--lattice", "4x4", "--out", str(npz),
                 "--jobs", "1", "-q", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    replayed = list(Replay(can_recording / "run.log", lattice="4x4").snapshots())
    assert doc["snapshots"] == len(replayed) >= 10 and np.load(npz)["joints"].shape[1:] == (4, 4, 3)


def test_a_replay_recorded_again_replays_to_the_same_snapshots(can_recording, tmp_path, capsys):
    from host.cli import main
    again = tmp_path / "again.mcap"
    assert main(["replay", str(can_recording / "run.mcap"), "--record", str(again), "-q"]) == 0
    first, second = read(can_recording / "run.mcap"), read(again)
    assert second.attachments["calibration.json"] == first.attachments["calibration.json"]
    assert [len(v) for v in second.raw.values()] == [len(v) for v in first.raw.values()]
    assert main(["replay", str(again), "--json", "-q"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["snapshots"] == doc["snapshots_identical"] == len(first)


def test_a_host_calibration_is_recorded_and_replay_applies_it(tmp_path):
    """``capsheet host --calibration cal.json --record``: the snapshots are recorded corrected, the
    calibration is attached (``host_calibration.json``), and replay corrects its snapshots with it,
    so they equal the recorded ones; without the attachment they would not (the bias is 0.3 m/s²)."""
    from host.analysis.calibration import Calibration
    from host.cli import main
    from host.record import HOST_CALIBRATION
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
    raw = next(iter(plain.snapshots()))
    assert np.abs(raw.readings.astype(np.float32) - rec.readings[0])[raw.valid].max() > 0.05


def _rechunked(src, dst, chunk_size: int) -> None:
    """``src`` written again by the mcap package's own writer in chunks of ``chunk_size`` bytes (the
    recorder's are 1 MiB: a short recording is one chunk, which any cut loses whole)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f, open(dst, "wb") as g:
        r = make_reader(f)
        w = Writer(g, chunk_size=chunk_size)
        w.start(profile="", library="test")
        summary = r.get_summary()
        sid = {s.id: w.register_schema(s.name, s.encoding, s.data) for s in summary.schemas.values()}
        cid = {c.id: w.register_channel(c.topic, c.message_encoding, sid.get(c.schema_id, 0), c.metadata)
               for c in summary.channels.values()}
        for m in r.iter_metadata():
            w.add_metadata(m.name, m.metadata)
        for a in r.iter_attachments():
            w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        for _schema, channel, msg in r.iter_messages(log_time_order=False):
            w.add_message(cid[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
        w.finish()


def test_a_recording_cut_short_says_so_and_exits_1_unless_allowed(pty_recording, tmp_path, capsys):
    """A recording whose writer was killed (or half copied) has no MCAP summary: replay and estimate
    say so in one line and exit 1; with --allow-truncated they work on what it holds and say so
    (they replayed 5 of 10 MB with exit 0 and no word)."""
    from host.cli import main

    small = tmp_path / "small-chunks.mcap"  # the recording in 4 kB chunks: a cut keeps the ones before it
    _rechunked(pty_recording, small, 4096)
    data = small.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    whole = read(pty_recording, raw=False)
    for argv in (["replay", str(cut), "-q"], ["estimate", str(cut), "--out", str(tmp_path / "j.npz"), "-q"]):
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert "was cut short" in err and "--allow-truncated" in err, err
        assert not (tmp_path / "j.npz").exists()
    assert main(["replay", str(cut), "-q", "--json", "--allow-truncated", "--no-estimate"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["truncated"] is True and 0 < doc["recorded_snapshots"] < len(whole)
    assert main(["estimate", str(cut), "--out", str(tmp_path / "j.npz"), "-q", "--json", "--allow-truncated"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["truncated"] is True and 0 < doc["snapshots"] < len(whole)
    assert main(["replay", str(pty_recording), "-q", "--json", "--no-estimate"]) == 0  # a whole one: no word
    cap = capsys.readouterr()
    assert json.loads(cap.out)["truncated"] is False and "cut short" not in cap.err


def test_a_can_log_replay_says_there_is_nothing_to_compare_with(can_recording, capsys):
    """A CAN log holds frames, not snapshots: the summary says so (it said "0 of 0 identical")."""
    from host.cli import main

    assert main(["replay", str(can_recording / "run.log"), "--lattice", "4x4", "-q", "--no-estimate"]) == 0
    err = capsys.readouterr().err
    assert "no recorded snapshots to compare with (a CAN log)" in err and "0 of 0" not in err, err
