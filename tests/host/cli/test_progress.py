"""Progress output (host/cli/progress.py) on a simulated clock, and in the commands that use it:
a terminal gets a bar or a line rewritten in place, a pipe or a log plain lines now and then,
``-q`` nothing."""

from __future__ import annotations

import io

import pytest

from host.cli.progress import LiveLine, Progress, is_terminal


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


class Tty(io.StringIO):
    def isatty(self):
        return True


def test_a_pipe_gets_a_line_every_period_and_a_final_one():
    clock, out = Clock(), io.StringIO()
    bar = Progress(100, "noise study", "trial", stream=out, every_s=10, clock=clock)
    for _ in range(100):
        clock.t += 1.0  # 100 trials of 1 s: a line at 10, 20, ..., 90 s, then the final one
        bar.update()
    bar.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 10 and bar.lines == 10
    assert lines[0] == "noise study: 10/100 trial (10 %), 10 s, ~90 s left"
    assert lines[-1] == "noise study: 100/100 trial (100 %), done in 100 s"
    assert "\r" not in out.getvalue()
    bar.close()  # twice: nothing more
    assert len(out.getvalue().splitlines()) == 10


def test_quiet_writes_nothing_and_an_unknown_total_counts_only():
    clock, out = Clock(), io.StringIO()
    with Progress(None, "replay", "chunk", stream=out, quiet=True, clock=clock) as bar:
        clock.t += 60
        bar.update(5)
    assert out.getvalue() == ""
    with Progress(None, "replay", "chunk", stream=out, every_s=10, clock=clock) as bar:
        clock.t += 30
        bar.update(7)
    assert out.getvalue().splitlines() == ["replay: 7 chunk, 30 s", "replay: 7 chunk, done in 30 s"]


def test_a_terminal_gets_tqdms_bar():
    out = Tty()
    assert is_terminal(out) and not is_terminal(io.StringIO())
    with Progress(3, "estimate", "snapshot", stream=out) as bar:
        bar.update(3)
        bar.write("a message")
    text = out.getvalue()
    assert "\r" in text and "3/3" in text and "a message" in text and bar.lines == 0


def test_a_live_line_is_redrawn_on_a_terminal_and_plain_in_a_log():
    clock = Clock()
    tty = LiveLine(Tty(), tty_every_s=0.25, every_s=2.0, clock=clock)
    log = LiveLine(io.StringIO(), tty_every_s=0.25, every_s=2.0, clock=clock)
    quiet = LiveLine(io.StringIO(), quiet=True, clock=clock)
    for k in range(32):  # 4 s in steps of 1/8 s (exact in binary)
        for line in (tty, log, quiet):
            line.show(f"status {k}")
        clock.t += 0.125
    assert tty.lines == 16 and log.lines == 2 and quiet.lines == 0  # every 0.25 s; 0 and 2 s
    assert log.stream.getvalue().splitlines() == ["status 0", "status 16"]
    assert tty.stream.getvalue().count("\r") == 16 and "\n" not in tty.stream.getvalue()
    tty.end()
    log.end()
    assert tty.stream.getvalue().endswith("\n") and log.stream.getvalue().count("\n") == 2
    # a new key is shown at once, however soon
    assert log.show("pose 2: hold still", key=(2, "holding"))
    assert not log.show("pose 2: hold still 50 %", key=(2, "holding"))
    assert log.show("pose 2: moving", key=(2, "moving"))


def test_paper_noise_in_a_pipe_writes_plain_progress_lines_or_none_with_q(tmp_path, capsys):
    from host.cli import main

    assert main(["paper", "noise", "--quick", "--trials", "1", "--target", "fig9",
                 "--out", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err  # no tqdm redraws in a pipe
    done = [ln for ln in err.splitlines() if ln.startswith("noise study:")]
    assert done == [done[-1]] and done[-1].startswith("noise study: 3/3 trial (100 %), done in")
    assert sum(ln.startswith("fig9 ") for ln in err.splitlines()) == 3  # one result line per level
    assert main(["paper", "noise", "--quick", "--trials", "1", "--target", "fig9", "-q",
                 "--out", str(tmp_path)]) == 0
    assert "noise study" not in capsys.readouterr().err


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A small recording written by capsheet's own recorder (real MCAP), 40 snapshots."""
    import numpy as np

    from host.snapshots.snapshot import LatticeSnapshot
    from host.record.recording import Recorder
    from protocol.lattice import Lattice
    from virtual_sheet.geometry import ideal_readings
    from virtual_sheet.shapes import make_sheet

    lat = Lattice(5, 5)
    r = ideal_readings(make_sheet("gaussian", 5, 5, 0.01))
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    rec = Recorder(path, lat, 0.01, session={"mode": "test", "rate_hz": 100.0})
    for k in range(40):
        rec.snapshot(LatticeSnapshot(k, k / 100, k / 100, r.astype(np.float32), np.ones(lat.n_links, bool),
                                     np.zeros(lat.n_links, np.uint8), True, 0.0))
    rec.close()
    return path


@pytest.mark.parametrize("quiet", [False, True])
def test_capsheet_estimate_progress_in_a_pipe(recording, tmp_path, capsys, quiet):
    from host.cli import main

    out = tmp_path / "shapes.mcap"
    assert main(["estimate", str(recording), "--out", str(out), "--jobs", "1", "--batch", "8"]
                + (["-q"] if quiet else [])) == 0
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith(("estimate:", "write:"))]
    if quiet:
        assert lines == []
    else:  # fast: no periodic line, just the final one of each stage
        assert [ln.split(" (")[0] for ln in lines] == ["estimate: 40/40 snapshot", "write: 40/40 snapshot"]
