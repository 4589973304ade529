"""``capsheet replay`` (host/cli/replay.py): the summary as JSON, a replay recorded again, a recording
cut short, a CAN log with nothing to compare with; and the bad arguments of ``replay`` and
``estimate`` together (they share the recording argument). The replay transport itself:
tests/host/record/test_replay.py."""

from __future__ import annotations

import json

import pytest

from host.record.recording import read


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
