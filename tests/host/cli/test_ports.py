"""``capsheet ports`` through the real CLI on ptys given by path: virtual sheets in other processes
(a sheet on one pty, a packed sheet behind two gateway nodes, an SLCAN adapter), a pty where
nothing answers, a port another session holds; bad values. What the probe reports is checked
against the virtual sheets' own layout files (their uids), never against the probe's code."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
from concurrent.futures import ThreadPoolExecutor

import pytest

from tests.host.cli.cli_runs import CLI, ENV, Virtual, drain, finish, popen_host, wait_line
from tests.shared_runs import result_of, session_root, shared_runs


def ports(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + ["ports", *args], capture_output=True, text=True, timeout=timeout_s, env=ENV)


def _uids(layout) -> list[str]:
    with open(layout) as f:
        return sorted(f"0x{int(r['uid'], 16):016X}" for r in csv.DictReader(f))


def _done(r: subprocess.CompletedProcess) -> dict:
    return {"returncode": r.returncode, "stdout": r.stdout, "stderr": r.stderr}


def _sheets(*arg_lists) -> list[Virtual]:
    """`Virtual` sheets started at once (each its own process), in order."""
    with ThreadPoolExecutor(len(arg_lists)) as pool:
        return list(pool.map(lambda a: Virtual(*a), arg_lists))


def _stop(sheets) -> None:
    for v in sheets:
        v.stop(signal.SIGKILL)


def _probe_json(d) -> dict:
    """Six paths probed in one command, as JSON: a sheet on one pty (by a symlink), a packed sheet
    behind two gateway nodes, an SLCAN adapter (as a serial path and as ``slcan:``), a pty where
    nothing answers."""
    sheets = _sheets(("--lattice", "3x3", "--symlink", str(d / "a"), "--layout-out", str(d / "a.csv")),
                     ("--lattice", "4x4", "--packed", "--gateways", "2", "--rate", "50", "--symlink", str(d / "g"),
                      "--layout-out", str(d / "g.csv")),
                     ("--lattice", "3x3", "--transport", "slcan", "--symlink", str(d / "c"),
                      "--layout-out", str(d / "c.csv")))
    m, s = os.openpty()  # nothing answers here
    try:
        paths = [str(d / n) for n in ("a", "g0", "g1", "c")] + [os.ttyname(s), f"slcan:{d / 'c'}"]
        # a listening budget a loaded machine's sheets answer in (the default 2 s once missed one of 5 at load 6)
        out = ports("--probe", "--json", "--timeout", "8", *paths)
        return {**_done(out), "paths": paths, "a_target": os.readlink(d / "a"),
                "a_alive": sheets[0].p.poll() is None}
    finally:
        os.close(m)
        os.close(s)
        _stop(sheets)


def _probe_lines(d) -> dict:
    """The same in lines: a sheet and a pty where nothing answers."""
    sheets = _sheets(("--lattice", "3x3", "--symlink", str(d / "b"), "--layout-out", str(d / "b.csv")))
    m, s = os.openpty()
    try:
        out = ports("--probe", "--timeout", "8", str(d / "b"), os.ttyname(s))
        return {**_done(out), "b_alive": sheets[0].p.poll() is None}
    finally:
        os.close(m)
        os.close(s)
        _stop(sheets)


def _probe_in_use(d) -> dict:
    """A port a host streams from, probed."""
    sheets = _sheets(("--lattice", "3x3", "--symlink", str(d / "a"), "--layout-out", str(d / "a.csv")))
    try:
        p = popen_host(*sheets[0].host_cmd, "--duration", "60", "--json", "-q")
        err: list = []
        try:
            wait_line(p, "started on", 60, err)
            out = ports("--probe", str(d / "a"))
        finally:
            p.send_signal(signal.SIGTERM)
            finish(p, drain(p, err))
        return {**_done(out), "host_pid": p.pid, "host_returncode": p.returncode}
    finally:
        _stop(sheets)


PROBES = {"json": _probe_json, "lines": _probe_lines, "in_use": _probe_in_use}


@pytest.fixture(scope="module")
def probes(tmp_path_factory):
    """``{name: result}`` of every `PROBES` run, at once, each with sheets of its own in other
    processes, made once per test session whichever workers need them (tests/shared_runs.py). A
    probe mostly waits: for the sheets to start, and one ``--timeout`` for a pty where nothing
    answers; one after another they took ~25 s."""
    root = session_root(tmp_path_factory)

    def job(name):
        d = root / f"ports-{name}"
        d.mkdir(exist_ok=True)
        return {**PROBES[name](d), "dir": str(d)}

    return shared_runs(root, "ports-probes", {n: (lambda _k, n=n: job(n)) for n in PROBES}, at_once=len(PROBES))


def _probe(probes, name: str) -> dict:
    return result_of(probes, name)


def test_probe_names_what_answers_on_each_path(probes):
    r = _probe(probes, "json")
    d, paths = r["dir"], r["paths"]
    assert r["returncode"] == 0, r["stderr"]
    doc = json.loads(r["stdout"])
    by = {p["name"]: p for p in doc["ports"]}
    assert [p["name"] for p in doc["ports"]] == paths and doc["answered"] == 5
    assert by[paths[5]]["kind"] == "can" and by[paths[5]]["probe"]["chip_uids"] == _uids(os.path.join(d, "c.csv"))
    pa = by[paths[0]]["probe"]
    assert pa["status"] == "answered" and pa["chip_uids"] == _uids(os.path.join(d, "a.csv")) and not pa["gateways"]
    assert by[paths[0]]["target"] == r["a_target"]
    g_uids = _uids(os.path.join(d, "g.csv"))  # 24 links: 0..11 behind gateway 0, 12..23 behind gateway 1
    g0, g1 = by[paths[1]]["probe"], by[paths[2]]["probe"]
    assert g0["chips"] + g1["chips"] == 24 and sorted(g0["chip_uids"] + g1["chip_uids"]) == g_uids
    assert [g["links"] for g in g0["gateways"]] == ["0-11"] and [g["links"] for g in g1["gateways"]] == ["12-23"]
    assert "PACKING" in g0["gateways"][0]["flags"] and "SYNC_SOURCE" in g0["gateways"][0]["flags"]
    assert g0["gateways"][0]["sync_rate_hz"] == 50
    pc = by[paths[3]]["probe"]
    assert pc["status"] == "answered" and pc["as_slcan"] and pc["chip_uids"] == _uids(os.path.join(d, "c.csv"))
    assert by[paths[4]]["probe"]["status"] == "silent"
    assert r["a_alive"]  # the sheet was only asked who it is: still running


def test_probe_says_it_in_one_line_per_port(probes):
    r = _probe(probes, "lines")
    lines = r["stdout"].splitlines()
    assert r["returncode"] == 0 and len(lines) == 2, r
    assert "12 chips" in lines[0] and "nothing answered" in lines[1]
    assert r["b_alive"]  # the sheet was only asked who it is: still running


def test_a_port_a_host_streams_from_is_in_use_and_not_probed(probes):
    r = _probe(probes, "in_use")
    assert r["returncode"] == 1, r  # nothing answered (the one port is busy)
    [line] = r["stdout"].splitlines()
    assert f"is in use by process {r['host_pid']} (" in line and "not probed" in line, line
    assert r["host_returncode"] == 0  # the host was not disturbed


def test_only_silent_ports_is_exit_1(cli_here):
    """Through the entry point in this process (the command's runs through real processes are
    `probes`')."""
    m, s = os.openpty()
    try:
        code, out, err = cli_here(["ports", "--probe", "--timeout", "0.5", os.ttyname(s)])
        assert code == 1 and "nothing answered" in out, (code, out, err)
    finally:
        os.close(m)
        os.close(s)


BAD = [(["/no/such/port"], "/no/such/port: no such file or device"),
       (["--timeout", "0"], "--timeout"),
       (["--timeout", "x"], "--timeout")]


@pytest.mark.parametrize("args, says", BAD)
def test_bad_values_are_one_line_and_exit_2(args, says, cli_here):
    """The first through a real process, the others through the entry point in this process."""
    if args == BAD[0][0]:
        out = ports(*args)
        code, err = out.returncode, out.stderr
    else:
        code, _out, err = cli_here(["ports", *args])
    assert code == 2, (code, err)
    [line] = err.splitlines()
    assert says in line and "Traceback" not in err
