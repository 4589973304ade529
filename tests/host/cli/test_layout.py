"""``capsheet layout learn`` and ``check`` through the real command line, against ``capsheet virtual
--poses learn --shuffle-ids`` in another process over a real pty: the sheet runs the poses on its
timer, the command sees only uids and readings; the sheet's --layout-out (its truth) only scores."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import pytest

from protocol.layout import load_layout, save_layout
from tests.host.cli.test_bad_values import CLI, MAX_LINE, TIMEOUT_S
from tests.host.cli.cli_runs import ENV, Virtual

LATTICE = "5x5"
#: a whole pass of the poses is 4 x (hold + move) = 6.4 s: the learner needs at most two. It takes a
#: pose after SETTLE_S still (``--settle-s``; 1 s by default, for a person holding the sheet): the
#: virtual sheet holds each pose 0.7 s longer than that (it held 2 s for the default 1 s before)
HOLD_S, MOVE_S, SETTLE_S = "1.2", "0.4", "0.5"


@pytest.fixture(scope="module")
def sheet(tmp_path_factory):
    d = tmp_path_factory.mktemp("layout-sheet")
    truth = d / "truth.csv"
    v = Virtual("--lattice", LATTICE, "--poses", "learn", "--pose-hold-s", HOLD_S, "--pose-move-s", MOVE_S,
                "--shuffle-ids", "--noise", "1", "--seed", "6", "--layout-out", str(truth))
    port = v.host_cmd[v.host_cmd.index("--port") + 1]
    yield port, load_layout(truth).links
    v.stop()


def layout_cmd(action: str, port: str, *args: str, timeout: float = 120):
    return subprocess.run(CLI + ["layout", action, "--port", port, "--baud", "12000000", "--settle-s", SETTLE_S, *args],
                          capture_output=True, text=True, timeout=timeout, env=ENV, stdin=subprocess.DEVNULL)


def test_learn_over_a_pty_places_every_chip(sheet, tmp_path):
    port, truth = sheet
    out = tmp_path / "learned.json"
    r = layout_cmd("learn", port, "--lattice", LATTICE, "--out", str(out), "--json")
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    doc = load_layout(out)
    assert doc.links == truth and doc.lattice == LATTICE
    res = json.loads(r.stdout)
    assert res["placed"] == 40 and res["loop_closure_ok"] and res["missing_links"] == []
    # every step was prompted, in order
    steps = [ln.split("(")[1].split(")")[0] for ln in r.stderr.splitlines() if ln.startswith("step ")]
    assert steps == ["flat", "tilt", "hump_i", "hump_j"]
    assert sorted(os.listdir(tmp_path)) == ["learned.json"]  # no temporary file left


def test_check_over_a_pty_finds_two_swapped_chips(sheet, tmp_path):
    port, truth = sheet
    at = {k: u for u, k in truth.items()}
    bad = dict(truth)
    bad[at[7]], bad[at[8]] = 8, 7
    lay, fixed = tmp_path / "bad.csv", tmp_path / "fixed.csv"
    save_layout(lay, bad)
    r = layout_cmd("check", port, "--layout", str(lay), "--lattice", LATTICE, "--out", str(fixed))
    assert "links 7 and 8 look swapped" in r.stdout, r.stdout + r.stderr
    assert r.returncode == 0, r.stderr  # every finding fixed into --out
    assert load_layout(fixed).links == truth


def test_check_ids_only_gives_a_new_chip_the_dead_ones_link(sheet, tmp_path):
    port, truth = sheet
    new = next(u for u, k in truth.items() if k == 21)
    old = 0x0BADC0FFEE000042
    bad = {u: k for u, k in truth.items() if u != new}
    bad[old] = 21
    lay, fixed = tmp_path / "bad.csv", tmp_path / "fixed.csv"
    save_layout(lay, bad)
    r = layout_cmd("check", port, "--layout", str(lay), "--lattice", LATTICE, "--ids-only", "--out", str(fixed),
                   timeout=60)
    assert f"chip 0x{new:016X} replaces 0x{old:016X} on link 21" in r.stdout, r.stdout + r.stderr
    assert r.returncode == 0, r.stderr
    assert load_layout(fixed).links == truth
    r = layout_cmd("check", port, "--layout", str(fixed), "--lattice", LATTICE, "--ids-only", timeout=60)
    assert r.returncode == 0 and "fits the sheet" in r.stdout, r.stdout + r.stderr


def test_ctrl_c_leaves_nothing_half_written(sheet, tmp_path):
    port, _truth = sheet
    out = tmp_path / "sheet.csv"
    out.write_text("uid,link\n0x1,0\n")  # someone's file, replaced only when a whole layout is learned
    before = out.read_bytes()
    # Ctrl-C as in a terminal: a suite started in the background (`make test &`, a CI script) runs
    # with SIGINT ignored, and its children inherit that across exec (the learner then rightly ran
    # to its end); a handler installed here is reset to the default in the child at exec
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        p = subprocess.Popen(CLI + ["layout", "learn", "--port", port, "--baud", "12000000", "--settle-s", SETTLE_S,
                                    "--lattice", LATTICE, "--out", str(out), "--overwrite"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, env=ENV)
    finally:
        signal.signal(signal.SIGINT, old)
    try:
        end = time.monotonic() + 60
        err = ""
        while time.monotonic() < end:  # into the poses: the session is up and prompting
            line = p.stderr.readline()
            err += line
            if line.startswith("step 2/4") or not line:
                break
        p.send_signal(signal.SIGINT)
        _o, rest = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    err += rest
    assert p.returncode == 130, err
    assert "Traceback" not in err, err
    assert err.strip().splitlines()[-1] == "interrupted"
    assert out.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["sheet.csv"]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("layout-bad")
    mine = d / "mine.csv"
    mine.write_text("uid,link\n0x1,0\n")
    junk = d / "junk.csv"
    junk.write_text("uid,link\nzz,0\n")
    big = d / "big.csv"
    big.write_text("uid,link\n0x1,500\n")
    return {"mine": str(mine), "junk": str(junk), "big": str(big), "dir": str(d), "nodir": str(d / "no" / "x")}


BAD = [
    (["layout", "learn", "--port", "/dev/null", "--lattice", "1x5", "--out", "x.csv"], "--lattice"),
    (["layout", "learn", "--port", "/dev/null", "--lattice", "4x4"], "--out"),
    (["layout", "learn", "--port", "/dev/null", "--lattice", "4x4", "--out", "x.txt"], "--out"),
    (["layout", "learn", "--port", "/dev/null", "--lattice", "4x4", "--out", "{mine}"], "--out"),
    (["layout", "learn", "--port", "/dev/null", "--lattice", "4x4", "--out", "{nodir}.csv"], "--out"),
    (["layout", "learn", "--port", "/dev/null", "--lattice", "4x4", "--out", "x.csv", "--rate", "0"], "--rate"),
    (["layout", "learn", "--port", "/dev/null", "--lattice", "4x4", "--out", "x.csv", "--settle-s", "0.1"],
     "--settle-s"),
    (["layout", "learn", "--port", "/dev/null", "--lattice", "4x4", "--out", "x.csv", "--settle-deg", "nan"],
     "--settle-deg"),
    (["layout", "learn", "--port", "/dev/null", "--lattice", "4x4", "--out", "x.csv", "--pose-timeout-s", "-1"],
     "--pose-timeout-s"),
    (["layout", "learn", "--lattice", "4x4", "--out", "x.csv"], "--port"),
    (["layout", "check", "--port", "/dev/null"], "--layout"),
    (["layout", "check", "--port", "/dev/null", "--layout", "{nodir}.csv"], "--layout"),
    (["layout", "check", "--port", "/dev/null", "--layout", "{junk}", "--lattice", "4x4"], "invalid uid"),
    (["layout", "check", "--port", "/dev/null", "--layout", "{mine}"], "--lattice"),
    (["layout", "check", "--port", "/dev/null", "--layout", "{big}", "--lattice", "4x4"], "link 500"),
    (["layout", "check", "--port", "/dev/null", "--layout", "{mine}", "--lattice", "4x4", "--out", "{mine}"], "--out"),
    (["layout", "bogus"], "invalid choice"),
    (["virtual", "--poses", "shuffle"], "--poses"),
    (["virtual", "--poses", "learn", "--pose-hold-s", "0"], "--pose-hold-s"),
    (["virtual", "--poses", "learn", "--pose-move-s", "inf"], "--pose-move-s"),
    (["virtual", "--poses", "learn", "--sensors", "accel+gyro"], "--poses"),
    (["demo", "--learn-layout", "--sensors", "accel+gyro"], "--learn-layout"),
]


@pytest.mark.parametrize("argv, needle", [pytest.param(a, n, id=" ".join(a)) for a, n in BAD])
def test_a_bad_value_is_one_line_and_exit_2(argv, needle, files, tmp_path, cli_here):
    """Through the entry point in this process (tests/host/cli/conftest.py); the first case of each
    subcommand through a real process as well."""
    real = argv == next(a for a, _ in BAD if a[:2] == argv[:2])
    argv = [a.format(**files) for a in argv]
    before = open(files["mine"], "rb").read()
    runs = [cli_here(argv, cwd=tmp_path, timeout_s=TIMEOUT_S)]
    if real:
        r = subprocess.run(CLI + argv, capture_output=True, text=True, timeout=TIMEOUT_S, cwd=tmp_path,
                           stdin=subprocess.DEVNULL)
        runs.append((r.returncode, r.stdout, r.stderr))
    for code, _out, err in runs:
        assert "Traceback" not in err, err
        assert code == 2, f"exit {code}: {err}"
        lines = err.strip().splitlines()
        assert len(lines) == 1 and len(lines[0]) <= MAX_LINE, err
        assert needle in lines[0] and lines[0].startswith("capsheet"), lines[0]
        assert open(files["mine"], "rb").read() == before
        assert os.listdir(tmp_path) == []


def test_a_missing_port_is_one_line_exit_1(tmp_path):
    r = subprocess.run(CLI + ["layout", "learn", "--port", "/dev/ttyNOPE", "--lattice", "4x4", "--out", "x.csv"],
                       capture_output=True, text=True, timeout=TIMEOUT_S, cwd=tmp_path, stdin=subprocess.DEVNULL)
    assert "Traceback" not in r.stderr and r.returncode == 1, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "/dev/ttyNOPE" in lines[0], r.stderr
    assert os.listdir(tmp_path) == []


def test_learn_over_a_pty_with_a_dead_chip_leaves_its_link_empty(tmp_path):
    truth_path = tmp_path / "truth.csv"
    v = Virtual("--lattice", "4x5", "--poses", "learn", "--pose-hold-s", HOLD_S, "--pose-move-s", MOVE_S,
                "--shuffle-ids", "--noise", "1", "--seed", "8", "--faults", "dead_chip=9",
                "--layout-out", str(truth_path))
    try:
        port = v.host_cmd[v.host_cmd.index("--port") + 1]
        out = tmp_path / "learned.csv"
        r = layout_cmd("learn", port, "--lattice", "4x5", "--out", str(out), "--json")
    finally:
        v.stop()
    assert r.returncode == 0, r.stderr
    truth = load_layout(truth_path).links
    learned = load_layout(out).links
    res = json.loads(r.stdout)
    assert res["missing_links"] == [9] and res["placed"] == 30
    assert learned == {u: k for u, k in truth.items() if k != 9}
    assert "link 9: no chip placed" in r.stderr
