"""``capsheet layout learn`` and ``check`` through the real command line, against ``capsheet virtual
--poses learn --shuffle-ids`` in another process over a real pty: the sheet runs the poses on its
timer, the command sees only uids and readings; the sheet's --layout-out (its truth) only scores.

The runs over the poses (`pose_runs`) are made at once, each chain on a sheet of its own: a run
mostly waits for the sheet's timer to come round to the poses (~12 s of wall for ~2 s of CPU)."""

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
from tests.shared_runs import result_of, session_root, shared_runs

LATTICE = "5x5"
#: a whole pass of the poses is 4 x (hold + move) = 6.4 s: the learner needs at most two. It takes a
#: pose after SETTLE_S still (``--settle-s``; 1 s by default, for a person holding the sheet): the
#: virtual sheet holds each pose 0.7 s longer than that (it held 2 s for the default 1 s before).
#: Not the demo's 0.5 s (`learn_hold_s`): with 1.0 s, four chains at once at load ~20 with two
#: busy loops beside them, the swapped-chips check took poses that did not tell links 7 and 8 apart
HOLD_S, MOVE_S, SETTLE_S = "1.2", "0.4", "0.5"
#: someone's file that ``layout learn --overwrite`` interrupted must leave as it was
THEIRS = "uid,link\n0x1,0\n"


def _sheet(*args: str) -> tuple[Virtual, str]:
    v = Virtual("--poses", "learn", "--pose-hold-s", HOLD_S, "--pose-move-s", MOVE_S, "--shuffle-ids", "--noise", "1",
                *args)
    return v, v.host_cmd[v.host_cmd.index("--port") + 1]


def layout_cmd(action: str, port: str, *args: str, timeout: float = 120):
    return subprocess.run(CLI + ["layout", action, "--port", port, "--baud", "12000000", "--settle-s", SETTLE_S, *args],
                          capture_output=True, text=True, timeout=timeout, env=ENV, stdin=subprocess.DEVNULL)


def _done(r: subprocess.CompletedProcess) -> dict:
    return {"returncode": r.returncode, "stdout": r.stdout, "stderr": r.stderr}


def _interrupted_learn(port: str, d) -> dict:
    """``layout learn --overwrite`` over someone's file, interrupted (SIGINT, as Ctrl-C in a
    terminal) once it prompts the second pose."""
    out = d / "sheet.csv"
    out.write_text(THEIRS)
    p = subprocess.Popen(CLI + ["layout", "learn", "--port", port, "--baud", "12000000", "--settle-s", SETTLE_S,
                                "--lattice", LATTICE, "--out", str(out), "--overwrite"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=ENV)
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
            p.wait(10)
    return {"returncode": p.returncode, "stderr": err + rest, "out": str(out), "dir": str(d)}


def _chain(root, name: str, make) -> dict:
    """One chain of runs on a sheet of its own (``make(port, directory) -> {run: result}``), its
    truth (the sheet's --layout-out) beside; a failure is the result ("error": `shared_runs`), for the
    test to say."""
    d = root / f"layout-{name}"
    d.mkdir(exist_ok=True)
    five = ("--lattice", LATTICE, "--seed", "6")  # the same seed: the same truth on every such sheet
    args = {"dead": ("--lattice", "4x5", "--seed", "8", "--faults", "dead_chip=9")}.get(name, five)
    v, port = _sheet(*args, "--layout-out", str(d / "truth.csv"))
    try:
        runs = make(port, d)
        runs["sheet_alive"] = v.p.poll() is None
    finally:
        v.stop()
    runs["truth"] = str(d / "truth.csv")
    return runs


def _learn(port, d) -> dict:
    learned = d / "learned" / "learned.json"
    learned.parent.mkdir()
    r = layout_cmd("learn", port, "--lattice", LATTICE, "--out", str(learned), "--json")
    return {"learn": {**_done(r), "out": str(learned), "dir": str(learned.parent)}}


def _check_swapped(port, d) -> dict:
    truth = load_layout(d / "truth.csv").links
    at = {k: u for u, k in truth.items()}
    bad = dict(truth)
    bad[at[7]], bad[at[8]] = 8, 7
    lay, fixed = d / "bad.csv", d / "fixed.csv"
    save_layout(lay, bad)
    swapped = layout_cmd("check", port, "--layout", str(lay), "--lattice", LATTICE, "--out", str(fixed))
    return {"swapped": {**_done(swapped), "out": str(fixed)}}


def _check_ids_then_interrupt(port, d) -> dict:
    truth = load_layout(d / "truth.csv").links
    # a new chip in place of a dead one: the layout names the dead chip on link 21
    new = next(u for u, k in truth.items() if k == 21)
    old = 0x0BADC0FFEE000042
    bad = {u: k for u, k in truth.items() if u != new}
    bad[old] = 21
    lay, fixed = d / "bad-ids.csv", d / "fixed-ids.csv"
    save_layout(lay, bad)
    ids = layout_cmd("check", port, "--layout", str(lay), "--lattice", LATTICE, "--ids-only", "--out", str(fixed),
                     timeout=60)
    again = layout_cmd("check", port, "--layout", str(fixed), "--lattice", LATTICE, "--ids-only", timeout=60)
    ctrl_c = d / "ctrl-c"
    ctrl_c.mkdir()
    return {"ids": {**_done(ids), "out": str(fixed), "new": new, "old": old}, "ids_again": _done(again),
            "ctrl_c": _interrupted_learn(port, ctrl_c)}


def _learn_with_a_dead_chip(port, d) -> dict:
    out = d / "learned.csv"
    return {"learn": {**_done(layout_cmd("learn", port, "--lattice", "4x5", "--out", str(out), "--json")),
                      "out": str(out)}}


#: the chains of runs, each on a sheet of its own (`_chain`): the three runs over the poses on
#: their own (the longest, ~12 s), the short ones after each other on the fourth sheet
CHAINS = {"learn": _learn, "check": _check_swapped, "ids": _check_ids_then_interrupt, "dead": _learn_with_a_dead_chip}


@pytest.fixture(scope="module")
def pose_runs(tmp_path_factory):
    """``{chain: {run: result}}``: every run on a sheet, the chains at once, each on a sheet of its
    own in its own process, made once per test session whichever workers need them
    (tests/shared_runs.py): the learn (5x5); the check of two swapped chips (5x5, the same seed:
    the same truth); the two ids-only checks and then the interrupted learn (5x5); the learn with a
    dead chip (4x5). SIGINT is caught here while they start: a suite started in the
    background (`make test &`, a CI script) runs with SIGINT ignored, and its children inherit that
    across exec (the interrupted learner then rightly ran to its end); a handler installed here is
    reset to the default in the child at exec."""
    root = session_root(tmp_path_factory)
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return shared_runs(root, "layout-poses", {n: (lambda _k, n=n: _chain(root, n, CHAINS[n])) for n in CHAINS},
                           at_once=len(CHAINS))
    finally:
        signal.signal(signal.SIGINT, old)


def _runs(pose_runs, chain: str) -> dict:
    return result_of(pose_runs, chain)


def test_learn_over_a_pty_places_every_chip(pose_runs):
    runs = _runs(pose_runs, "learn")
    r, truth = runs["learn"], load_layout(runs["truth"]).links
    assert r["returncode"] == 0, r["stderr"]
    assert "Traceback" not in r["stderr"]
    doc = load_layout(r["out"])
    assert doc.links == truth and doc.lattice == LATTICE
    res = json.loads(r["stdout"])
    assert res["placed"] == 40 and res["loop_closure_ok"] and res["missing_links"] == []
    # every step was prompted, in order
    steps = [ln.split("(")[1].split(")")[0] for ln in r["stderr"].splitlines() if ln.startswith("step ")]
    assert steps == ["flat", "tilt", "hump_i", "hump_j"]
    assert sorted(os.listdir(r["dir"])) == ["learned.json"]  # no temporary file left


def test_check_over_a_pty_finds_two_swapped_chips(pose_runs):
    runs = _runs(pose_runs, "check")
    r, truth = runs["swapped"], load_layout(runs["truth"]).links
    assert "links 7 and 8 look swapped" in r["stdout"], r["stdout"] + r["stderr"]
    assert r["returncode"] == 0, r["stderr"]  # every finding fixed into --out
    assert load_layout(r["out"]).links == truth


def test_check_ids_only_gives_a_new_chip_the_dead_ones_link(pose_runs):
    runs = _runs(pose_runs, "ids")
    r, truth = runs["ids"], load_layout(runs["truth"]).links
    new, old = r["new"], r["old"]
    assert f"chip 0x{new:016X} replaces 0x{old:016X} on link 21" in r["stdout"], r["stdout"] + r["stderr"]
    assert r["returncode"] == 0, r["stderr"]
    assert load_layout(r["out"]).links == truth
    r = runs["ids_again"]
    assert r["returncode"] == 0 and "fits the sheet" in r["stdout"], r["stdout"] + r["stderr"]


def test_ctrl_c_leaves_nothing_half_written(pose_runs):
    r = _runs(pose_runs, "ids")["ctrl_c"]
    err = r["stderr"]
    assert r["returncode"] == 130, err
    assert "Traceback" not in err, err
    assert err.strip().splitlines()[-1] == "interrupted"
    assert open(r["out"]).read() == THEIRS
    assert sorted(os.listdir(r["dir"])) == ["sheet.csv"]


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
    """Through the entry point in this process (tests/host/cli/conftest.py); the first case of
    `layout learn`, `layout check` and `virtual` through a real process as well (demo's refusals
    have theirs in test_demo.py; `layout bogus` is the parser's own refusal)."""
    real = argv[:2] in (["layout", "learn"], ["layout", "check"]) or argv[0] == "virtual"
    real = real and argv == next(a for a, _ in BAD if a[:2] == argv[:2])
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


def test_a_missing_port_is_one_line_exit_1(tmp_path, cli_here):
    """Through the entry point in this process: the port is refused when it is opened, before any
    session (the learner's runs through real processes are `pose_runs`')."""
    code, _out, err = cli_here(["layout", "learn", "--port", "/dev/ttyNOPE", "--lattice", "4x4", "--out", "x.csv"],
                               cwd=tmp_path, timeout_s=TIMEOUT_S)
    assert "Traceback" not in err and code == 1, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "/dev/ttyNOPE" in lines[0], err
    assert os.listdir(tmp_path) == []


def test_learn_over_a_pty_with_a_dead_chip_leaves_its_link_empty(pose_runs):
    runs = _runs(pose_runs, "dead")
    r = runs["learn"]
    assert runs["sheet_alive"]
    assert r["returncode"] == 0, r["stderr"]
    truth = load_layout(runs["truth"]).links
    learned = load_layout(r["out"]).links
    res = json.loads(r["stdout"])
    assert res["missing_links"] == [9] and res["placed"] == 30
    assert learned == {u: k for u, k in truth.items() if k != 9}
    assert "link 9: no chip placed" in r["stderr"]
