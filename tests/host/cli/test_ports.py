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

import pytest

from tests.host.cli.cli_runs import CLI, ENV, drain, finish, popen_host, wait_line


def ports(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + ["ports", *args], capture_output=True, text=True, timeout=timeout_s, env=ENV)


def _uids(layout) -> list[str]:
    with open(layout) as f:
        return sorted(f"0x{int(r['uid'], 16):016X}" for r in csv.DictReader(f))



def test_probe_names_what_answers_on_each_path(virtuals, tmp_path):
    a = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "a"), "--layout-out", str(tmp_path / "a.csv"))
    virtuals("--lattice", "4x4", "--packed", "--gateways", "2", "--rate", "50", "--symlink", str(tmp_path / "g"),
             "--layout-out", str(tmp_path / "g.csv"))
    virtuals("--lattice", "3x3", "--transport", "slcan", "--symlink", str(tmp_path / "c"),
             "--layout-out", str(tmp_path / "c.csv"))
    m, s = os.openpty()  # nothing answers here
    try:
        paths = [str(tmp_path / n) for n in ("a", "g0", "g1", "c")] + [os.ttyname(s), f"slcan:{tmp_path / 'c'}"]
        # a listening budget a loaded machine's sheets answer in (the default 2 s once missed one of 5 at load 6)
        out = ports("--probe", "--json", "--timeout", "8", *paths)
        assert out.returncode == 0, out.stderr
        doc = json.loads(out.stdout)
        by = {p["name"]: p for p in doc["ports"]}
        assert [p["name"] for p in doc["ports"]] == paths and doc["answered"] == 5
        assert by[paths[5]]["kind"] == "can" and by[paths[5]]["probe"]["chip_uids"] == _uids(tmp_path / "c.csv")
        pa = by[paths[0]]["probe"]
        assert pa["status"] == "answered" and pa["chip_uids"] == _uids(tmp_path / "a.csv") and not pa["gateways"]
        assert by[paths[0]]["target"] == os.readlink(tmp_path / "a")
        g_uids = _uids(tmp_path / "g.csv")  # 24 links: 0..11 behind gateway 0, 12..23 behind gateway 1
        g0, g1 = by[paths[1]]["probe"], by[paths[2]]["probe"]
        assert g0["chips"] + g1["chips"] == 24 and sorted(g0["chip_uids"] + g1["chip_uids"]) == g_uids
        assert [g["links"] for g in g0["gateways"]] == ["0-11"] and [g["links"] for g in g1["gateways"]] == ["12-23"]
        assert "PACKING" in g0["gateways"][0]["flags"] and "SYNC_SOURCE" in g0["gateways"][0]["flags"]
        assert g0["gateways"][0]["sync_rate_hz"] == 50
        pc = by[paths[3]]["probe"]
        assert pc["status"] == "answered" and pc["as_slcan"] and pc["chip_uids"] == _uids(tmp_path / "c.csv")
        assert by[paths[4]]["probe"]["status"] == "silent"
        # the same in lines: one per port
        out = ports("--probe", "--timeout", "8", *paths[:1], paths[4])
        lines = out.stdout.splitlines()
        assert out.returncode == 0 and len(lines) == 2, out
        assert "12 chips" in lines[0] and "nothing answered" in lines[1]
    finally:
        os.close(m)
        os.close(s)
    assert a.p.poll() is None  # the sheet was only asked who it is: still running


def test_a_port_a_host_streams_from_is_in_use_and_not_probed(virtuals, tmp_path):
    v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "a"), "--layout-out", str(tmp_path / "a.csv"))
    p = popen_host(*v.host_cmd, "--duration", "60", "--json", "-q")
    err: list = []
    try:
        wait_line(p, "started on", 60, err)
        out = ports("--probe", str(tmp_path / "a"))
        assert out.returncode == 1, out  # nothing answered (the one port is busy)
        [line] = out.stdout.splitlines()
        assert f"is in use by process {p.pid} (" in line and "not probed" in line, line
    finally:
        p.send_signal(signal.SIGTERM)
        finish(p, drain(p, err))
    assert p.returncode == 0  # the host was not disturbed


def test_only_silent_ports_is_exit_1():
    m, s = os.openpty()
    try:
        out = ports("--probe", "--timeout", "0.5", os.ttyname(s))
        assert out.returncode == 1 and "nothing answered" in out.stdout, out
    finally:
        os.close(m)
        os.close(s)


@pytest.mark.parametrize("args, says", [
    (["/no/such/port"], "/no/such/port: no such file or device"),
    (["--timeout", "0"], "--timeout"),
    (["--timeout", "x"], "--timeout"),
])
def test_bad_values_are_one_line_and_exit_2(args, says):
    out = ports(*args)
    assert out.returncode == 2, out
    [line] = out.stderr.splitlines()
    assert says in line and "Traceback" not in out.stderr
