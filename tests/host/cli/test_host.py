"""``capsheet host`` through the real CLI, in subprocesses, against ``capsheet virtual`` over real ptys,
SLCAN-on-pty and udp_multicast on loopback: hosts killed and restarted, sheets restarted on
the same path, second sessions, two SYNC sources, over-capacity buses, mismatches, malformed input.

Assertions are on what is delivered and reported (exit status, the summary, the recording), never on
rates or latencies: the machine may be slow.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.host.cli.cli_runs import (CLI, DELIVERY, ENV, FOLLOWING, drain, finish, host, host_here, host_json,
                                     host_json_here, modest_rate, popen_host, wait_line)


# -- bad values: one line, exit 2, no traceback (no sheet needed: checked before any port opens) --

def _bad_layouts(tmp: Path) -> dict:
    files = {
        "truncated.json": b'{"rows": 2, "cols": 2, "chips": [{"uid": "0x1", ',
        "types.json": b'{"chips": [{"uid": 7, "link": "x"}]}',
        "binary.csv": bytes(range(256)),
        "beyond.csv": b"uid,link\n0x1,0\n0x2,400\n",
        "small.json": b'{"format": "capsheet-layout", "version": 1, "rows": 2, "cols": 2, "chips": []}',
    }
    for name, data in files.items():
        (tmp / name).write_bytes(data)
    return {
        ("--layout", str(tmp / "truncated.json")): "not valid JSON",
        ("--layout", str(tmp / "types.json")): "uid must be a hex string",
        ("--layout", str(tmp / "binary.csv")): "binary data",
        ("--layout", str(tmp / "missing.csv")): "--layout: invalid value",
        ("--layout", str(tmp / "beyond.csv"), "--lattice", "14x14"): "beyond lattice 14x14 (364 links), e.g. uid 0x0000000000000002 on link 400",
        # without --lattice a CSV layout's links are the sheet's table: 401 links fit 6x37 and 37x6 alone
        ("--layout", str(tmp / "beyond.csv")): "the layout names links 0-400 (401 links), which fits the lattices 6x37, 37x6; give --lattice",
        ("--layout", str(tmp / "small.json"), "--lattice", "14x14"): "the layout",
    }


def test_every_bad_value_is_one_line_and_exit_2(tmp_path, cli_here):
    """Through the entry point in this process (tests/host/cli/conftest.py), the first case through a
    real process as well: each refused before any port opens."""
    cases = {("--lattice", "14by14"): "--lattice: invalid value '14by14'",
             ("--rate", "0"): "--rate: invalid value '0'", ("--rate", "nan"): "--rate: invalid value 'nan'",
             ("--rate", "-3"): "--rate: invalid value '-3'", ("--rate", "inf"): "--rate: invalid value 'inf'",
             ("--duration", "0"): "need a number > 0", ("--min-complete", "101"): "need a number >= 0 and <= 100 %",
             ("--sync", "sometimes"): "invalid choice", ("--discover-s", "x"): "--discover-s: invalid value 'x'",
             ("--baud", "-1"): "invalid value '-1': need an integer >= 1", ("--bitrate", "abc"): "need an integer",
             ("--lattice", "300x300"): "a sheet has at most 32,767"}
    cases.update(_bad_layouts(tmp_path))
    for k, (args, needle) in enumerate(cases.items()):
        argv = ["host", "--port", str(tmp_path / "no-such-port"), *args]
        runs = [cli_here(modest_rate(argv))]
        if k == 0:
            out = host(*argv[1:])
            runs.append((out.returncode, out.stdout, out.stderr))
        for code, _out, err in runs:
            assert code == 2, (args, code, err)
            assert needle in err, (args, err)
            assert "Traceback" not in err, (args, err)
    # a JSON layout's lattice is taken when --lattice is not given; given and different: an error
    _code, _out, err = cli_here(modest_rate(["host", "--port", str(tmp_path / "no-such-port"), "--layout",
                                       str(tmp_path / "small.json"), "--lattice", "14x14"]))
    assert "--lattice 14x14 but the layout" in err and "is for 2x2" in err


@pytest.mark.parametrize("layout", [False, True])
def test_no_chip_is_exit_1(tmp_path, layout, cli_here):
    """A port where nothing answers: 'no chip answered', exit 1 (was 0 % complete and exit 0). With a
    layout too: the port is named, not the layout (was "12 layout chip(s) never answered ... check
    the layout file", exit 2). Without a layout through a real process; with one through the entry
    point in this process (the same bring-up, refusal, line and status)."""
    lay = tmp_path / "sheet.csv"
    lay.write_text("uid,link\n" + "".join(f"0x{0x1000 + k:X},{k}\n" for k in range(12)))
    master, slave = os.openpty()
    try:
        argv = ["--port", os.ttyname(slave), *(["--layout", str(lay)] if layout else ["--auto-assign"]),
                "--discover-s", "0.2", "--lattice", "3x3"]
        if layout:
            code, _out, err = cli_here(["host", *modest_rate(argv)])
        else:
            out = host(*argv)
            code, err = out.returncode, out.stderr
    finally:
        os.close(master)
        os.close(slave)
    assert code == 1 and "no chip answered" in err, err
    assert "never answered" not in err and "check the layout" not in err, err


# -- bring-up from any state ---------------------------------------------------------------------

def test_host_killed_mid_stream_and_restarted_gets_every_chip(virtuals, tmp_path, cli_here):
    """A host killed (SIGKILL: the sheet left streaming) or stopped (SIGTERM) mid-stream: the next
    host finds every chip. The host started again after SIGKILL is a real process, after SIGTERM it
    runs through the entry point in this process (the same session and bring-up)."""
    lay = tmp_path / "sheet.csv"
    v = virtuals("--lattice", "6x6", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(lay))
    err: list = []
    for sig in (signal.SIGKILL, signal.SIGTERM):
        p = popen_host(*v.host_cmd, "--duration", "60")
        wait_line(p, "started on", 60, err)
        time.sleep(0.5)  # streaming since "started on": mid-stream
        p.send_signal(sig)  # the sheet is left streaming (SIGKILL) or stopped (SIGTERM)
        p.wait(30)
        p.stderr.close()
        p.stdout.close()
        # bring-up is under test: 0.5 s at 50 Hz is ~25 snapshots, where the checks below need some
        # (it ran 1.5 s at the sheet's 145 Hz)
        args = (*v.host_cmd, "--duration", "0.5", *DELIVERY)
        out, doc = host_json(*args) if sig == signal.SIGKILL else host_json_here(cli_here, *args)
        assert out.returncode == 0, out.stderr
        assert "60 chips found, 60 assigned, 60 configured, 0 calibrated (60 nominal: no calibration of their own), 60 started" in out.stderr
        s = doc["summary"]
        assert s["valid_links_pct"] >= 95.0 and s["snapshots"] > 0 and not s["errors"], s
    assert v.p.poll() is None  # the sheet kept running through both


@pytest.mark.parametrize("transport", ["pty", "slcan"])
def test_three_sessions_in_a_row(virtuals, tmp_path, transport, cli_here):
    """Three host sessions in a row on one sheet, each bringing it up from the state the last one
    left: the first through a real process, the next two through the entry point in this process
    (a session is the `Host` the command makes, whichever process it is in: the sheet sees the port
    closed and opened again either way)."""
    lay = tmp_path / "sheet.csv"
    v = virtuals("--lattice", "4x4", "--transport", transport, "--symlink", str(tmp_path / "port"),
                 "--layout-out", str(lay))
    for session in range(3):
        # bring-up is under test here, not how fast python-can's slcan reads on a busy machine:
        # --min-complete 0, and the data must merely flow (half a second: ~70 snapshots at the
        # sheet's 145 Hz, where one complete snapshot is asked)
        args = (*v.host_cmd, "--duration", "0.5", "--min-complete", "0")
        out, doc = host_json(*args) if session == 0 else host_json_here(cli_here, *args)
        assert out.returncode == 0, (session, out.stderr)
        assert "24 chips found, 24 assigned, 24 configured, 0 calibrated (24 nominal: no calibration of their own), 24 started" in out.stderr, (session, out.stderr)
        s = doc["summary"]
        assert s["snapshots"] > 0 and s["valid_links_pct"] > 0 and s["complete_snapshots"] > 0, (session, s)
        assert not s["errors"], (session, s)


# -- recovery without a person --------------------------------------------------------------------

def test_a_sheet_restarted_on_another_pty_at_the_same_path_is_refused(virtuals, tmp_path):
    """The sheet's process restarted under the same symlink, but on another pty (another device
    number): the host does not reconnect to it (one session, one device: a reopen goes only to the
    device the port was), says so in one line and exits 1; the restarted sheet was never opened."""
    from host.transport.portlock import holders
    from virtual_sheet.devices import open_pty

    lay, port = tmp_path / "sheet.csv", tmp_path / "sheet"
    a = virtuals("--lattice", "4x4", "--symlink", str(port), "--layout-out", str(lay))
    first = os.readlink(port)
    p = popen_host(*a.host_cmd, "--duration", "300", "--json", "-q")
    err: list = []
    wait_line(p, "started on", 60, err)
    time.sleep(0.5)  # streaming since "started on": mid-stream
    assert a.stop(signal.SIGTERM) == 0
    wait_line(p, "went away", 60, err)  # the host closed the old pty: its number is free
    m, s, name = open_pty(first, wait_s=10.0)  # held here, so the restarted sheet gets another
    try:
        assert name == first, "another process took the pty number"
        b = virtuals("--lattice", "4x4", "--symlink", str(port), "--layout-out", str(lay))
        second = os.readlink(port)
        assert second != first
        wait_line(p, "came back as another device", 60, err)
        time.sleep(1.0)
        assert holders(second) == []  # the host never opened it (a session's port is locked)
        p.send_signal(signal.SIGTERM)
        out = finish(p, drain(p, err))
    finally:
        os.close(m)
        os.close(s)
    s_ = json.loads(out)["summary"]
    assert p.returncode == 1
    assert s_["reconnects"] == 0 and any("came back as another device" in w for w in s_["not_a_sheet"]), s_
    assert len([ln for ln in err if "WARNING" in ln and "came back as another device" in ln]) == 1, err  # once
    assert b.p.poll() is None


def test_a_reconnect_to_another_device_is_refused_never_written_to(virtuals, tmp_path):
    """The sheet dies without cleaning up (SIGKILL) and its path now leads to another device (a pty
    that babbles text): refused, exit 1, and nothing at all written into that device, nor its
    terminal settings changed (was: GET_INFO written into it and the port switched to raw mode)."""
    import select
    import termios

    lay, port = tmp_path / "sheet.csv", tmp_path / "sheet"
    master, slave = os.openpty()  # made while the sheet lives: another device number than its pty
    attrs = termios.tcgetattr(slave)
    attrs[3] &= ~(termios.ECHO | termios.ECHONL)  # no echo of its own babble; still cooked, not raw
    termios.tcsetattr(slave, termios.TCSANOW, attrs)
    attrs = termios.tcgetattr(slave)
    a = virtuals("--lattice", "3x3", "--symlink", str(port), "--layout-out", str(lay))
    p = popen_host(*a.host_cmd, "--duration", "300", "--json", "-q")
    err: list = []
    wait_line(p, "started on", 60, err)
    a.stop(signal.SIGKILL)
    assert port.is_symlink()  # SIGKILL cannot be caught: the stale symlink stays
    stop = threading.Event()
    written = bytearray()  # what the host wrote into that other device

    def babble():
        while not stop.is_set():
            try:
                os.write(master, b"AT OK\r\n")
                while select.select([master], [], [], 0)[0]:
                    written.extend(os.read(master, 4096))
            except OSError:
                pass
            time.sleep(0.05)
    th = threading.Thread(target=babble, daemon=True)
    th.start()
    tmp = str(port) + ".x"
    os.symlink(os.ttyname(slave), tmp)
    os.replace(tmp, port)
    try:
        # refused, and it keeps trying the path (only the device it was will do): a second more of
        # that with the other device there, then stopped (it ran to a --duration of 8 s before)
        wait_line(p, "came back as another device", 60, err)
        time.sleep(1.0)
        p.send_signal(signal.SIGTERM)
        out = finish(p, drain(p, err))
        settings = termios.tcgetattr(slave)
    finally:
        stop.set()
        th.join(2)
        os.close(master)
        os.close(slave)
    s = json.loads(out)["summary"]
    assert p.returncode == 1
    assert s["not_a_sheet"] and "came back as another device" in s["not_a_sheet"][0], s
    assert bytes(written) == b"" and settings == attrs
    assert s["reconnects"] == 0


# -- without --lattice: what answered decides, or is said ---------------------------------------------

def test_without_lattice_the_host_says_what_answered_and_which_lattices_fit(virtuals, tmp_path, cli_here):
    """A 6x6 sheet and no --lattice: 60 chips answer, no gateway says how many links there are; the
    count alone never decides (one silent chip would make it 59, which fits 4x9), so the host says
    what it heard and what fits, exit 2, one line (was: 14x14 assumed, "complete 100 %" with 16.5 %
    of the link samples valid, 6x6 never named)."""
    v = virtuals("--lattice", "6x6", "--symlink", str(tmp_path / "sheet"))
    cmd = [a for a in v.host_cmd]
    i = cmd.index("--lattice")
    del cmd[i:i + 2]
    out = host_here(cli_here, *cmd, "--duration", "1")  # refused after discovery: in this process
    assert out.returncode == 2, out.stderr
    [line] = out.stderr.splitlines()
    assert "60 chips answered" in line and "lattices with 60 links: 6x6" in line and "give --lattice" in line, line
    assert v.p.poll() is None


def test_without_lattice_the_gateways_tables_or_a_layout_decide(virtuals, tmp_path, cli_here):
    """Two gateway nodes serving links 0-11 and 12-23: 24 links, 4x4 the one lattice with that many:
    used, and said. A CSV layout's links decide in the same way."""
    g = virtuals("--lattice", "4x4", "--packed", "--gateways", "2", "--rate", "50", "--symlink", str(tmp_path / "g"))
    cmd = list(g.host_cmd)
    i = cmd.index("--lattice")
    del cmd[i:i + 2]
    out, doc = host_json(*cmd, "--duration", "1.5", *FOLLOWING)
    assert out.returncode == 0, out.stderr
    assert "no --lattice: the gateways serve links 0-23 (24 links): 4x4 is the one lattice with that many" in out.stderr
    assert doc["summary"]["links"] == 24 and doc["summary"]["valid_links_pct"] >= 90.0, doc["summary"]
    lay = tmp_path / "a.csv"
    a = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "a"), "--layout-out", str(lay))
    cmd = list(a.host_cmd)
    i = cmd.index("--lattice")
    del cmd[i:i + 2]
    out, doc = host_json_here(cli_here, *cmd, "--duration", "0.5")  # the gateways' case ran as a process
    assert out.returncode == 0 and "the layout names links 0-11 (12 links): 3x3" in out.stderr, out.stderr
    assert doc["summary"]["links"] == 12


def test_the_waits_follow_the_rate_and_the_deadline_unless_the_user_gives_them(virtuals, tmp_path, cli_here):
    """``--json``'s "waits": by default a command's ACK is waited for 250 ms, and a link is marked
    missing after 500 ms, 20 SYNC periods or ``--deadline-ms``, whichever is longest (a host told to
    wait 1.5 s for a link's frame does not give the link up after 0.5 s); ``--ack-timeout-ms`` and
    ``--watchdog-ms`` are the user's word. Each run streams: the waits are the session's own."""
    a = virtuals("--lattice", "2x2", "--symlink", str(tmp_path / "a"))
    runs = {  # arguments -> the waits expected
        ("--rate", "20", "--deadline-ms", "300"): {"ack_timeout_ms": 250.0, "watchdog_ms": 1000.0},
        ("--rate", "100", "--deadline-ms", "1500"): {"ack_timeout_ms": 250.0, "watchdog_ms": 1500.0},
        ("--rate", "100", "--deadline-ms", "100"): {"ack_timeout_ms": 250.0, "watchdog_ms": 500.0},
        ("--rate", "100", "--deadline-ms", "1500", "--ack-timeout-ms", "400", "--watchdog-ms", "3000"):
            {"ack_timeout_ms": 400.0, "watchdog_ms": 3000.0},
    }
    for extra, waits in runs.items():
        out, doc = host_json_here(cli_here, *a.host_cmd, "--duration", "0.3", *extra)
        assert out.returncode == 0, out.stderr
        assert doc["waits"] == waits, (extra, doc["waits"])
        assert doc["summary"]["snapshots"] > 0


# -- one SYNC source ------------------------------------------------------------------------------

def test_two_sync_sources(virtuals, tmp_path, cli_here):
    lay = tmp_path / "sheet.csv"
    v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(lay), "--rate", "50")
    assert "--sync" in v.host_cmd and "follow" in v.host_cmd  # the printed command follows the gateway
    base = [a for a in v.host_cmd]
    i = base.index("--sync")
    del base[i:i + 2]
    # drive mode against a gateway that drives SYNC: it said so itself (refused at bring-up: here)
    out = host_here(cli_here, *base, "--duration", "1")
    assert out.returncode == 2 and "is its segment's SYNC source" in out.stderr and "--sync follow" in out.stderr
    out, doc = host_json(*base, "--sync", "auto", "--duration", "1", *FOLLOWING)
    assert out.returncode == 0, out.stderr
    assert doc["summary"]["sync_mode"] == "follow" and doc["summary"]["valid_links_pct"] >= 95.0


# -- capacity and mismatches before streaming ------------------------------------------------------

def test_over_capacity_is_refused_with_the_remedy(virtuals, tmp_path, cli_here):
    lay = tmp_path / "sheet.csv"
    v = virtuals("--lattice", "6x6", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(lay))
    cmd = list(v.host_cmd)
    cmd[cmd.index("--baud") + 1] = "115200"
    out = host_here(cli_here, *cmd, "--duration", "1", "--rate", "100")  # refused before streaming: here
    # 60 chips x 100 Hz x 150 bits = 900 kbit/s on a 115.2 kbaud UART: 781 %
    assert out.returncode == 2 and "over capacity" in out.stderr and "781 %" in out.stderr, out.stderr
    assert "--packed" in out.stderr and "--rate" in out.stderr
    out = host_here(cli_here, *cmd, "--duration", "0.5", "--rate", "10")  # 10 Hz: 78 % -- fits
    assert out.returncode == 0, out.stderr


def test_layout_chips_that_never_answer_are_named(virtuals, tmp_path, cli_here):
    other = tmp_path / "other.csv"  # another sheet's layout, written by `capsheet virtual` in this process
    code, _out, err = cli_here(["virtual", "--lattice", "3x3", "--seed", "5", "--layout-out", str(other),
                                "--transport", "memory", "--duration", "0.01"])
    assert code == 0 and other.exists(), err
    v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "sheet"), "--seed", "1")
    cmd = [a for a in v.host_cmd if a != "--auto-assign"]
    out = host(*cmd, "--layout", str(other), "--duration", "1")
    assert out.returncode == 2 and "12 layout chip(s) never answered: link 0 (uid 0x" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr
    out = host_here(cli_here, *cmd, "--layout", str(other), "--duration", "0.5", "--allow-missing")
    assert out.returncode == 1 and "announcing chip(s) are not in the layout" in out.stderr  # and nothing streamed


def test_each_run_in_one_process_warns_on_its_own_stream(virtuals, tmp_path):
    """A program calling the entry point twice (here, straight: no fixture puts the logging back): the
    second run's warnings reach the second run's stderr, not the first's, and no handler is left."""
    import contextlib
    import io
    import logging

    from host.cli import main
    from host.cli.host import _StatusAwareHandler
    other = tmp_path / "other.csv"
    assert main(["virtual", "--lattice", "3x3", "--seed", "5", "--layout-out", str(other), "--transport", "memory",
                 "--duration", "0.01"]) == 0
    v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "sheet"), "--seed", "1")
    cmd = [a for a in v.host_cmd if a != "--auto-assign"]
    streams = []
    for _ in range(2):
        streams.append(io.StringIO())
        with contextlib.redirect_stderr(streams[-1]):
            assert main(["host", *cmd, "--layout", str(other), "--duration", "0.5", "--allow-missing"]) == 1
        assert not [h for h in logging.getLogger().handlers if isinstance(h, _StatusAwareHandler)]
    for err in (s.getvalue() for s in streams):
        assert err.count("announcing chip(s) are not in the layout") == 1, err


def test_fd_frames_on_a_classic_bus_say_add_fd(virtuals, tmp_path, cli_here):
    """A packing FD gateway: its SNAPSHOT frames (FD only) reach a host that forgot --fd. Refused at
    discovery, before streaming: through the entry point in this process (the same bring-up, line
    and status; `capsheet host` over SLCAN runs as a real process in the busy-port refusal and the
    first of three sessions)."""
    v = virtuals("--lattice", "3x3", "--transport", "slcan", "--fd", "--packed", "--symlink", str(tmp_path / "can"),
                 "--layout-out", str(tmp_path / "sheet.csv"))
    cmd = [a for a in v.host_cmd if a != "--fd"]
    out = host_here(cli_here, *cmd, "--duration", "1", "--rate", "20")
    assert out.returncode == 2 and "carries CAN FD frames" in out.stderr and "add --fd" in out.stderr, out.stderr


# -- cross-process CAN without hardware -------------------------------------------------------------

# python-can's udp_multicast buses share one UDP port, and on Linux a plain one hears every group
# joined on the machine (capsheet's own are isolated, host/transport/udp_multicast.py, but these tests inject
# with plain buses, and another checkout's suite may run an older capsheet on the default group): two
# of these tests at once could hear each other. One xdist worker runs them all (`--dist loadgroup`).
ONE_MULTICAST_BUS = pytest.mark.xdist_group("udp_multicast")
# A udp_multicast host judged on what it delivered runs at `DELIVERY` too: at 50 Hz a socket's
# receive buffer also holds the datagrams (a sample each) of ~0.4 s of a host not scheduled.


@ONE_MULTICAST_BUS
def test_udp_multicast_between_two_processes(udp_bus_lock, virtuals, tmp_path):
    try:
        import can
        b = can.Bus(interface="udp_multicast", channel="239.74.163.2")
        b.shutdown()
    except Exception as exc:  # noqa: BLE001 - no multicast route on this machine
        pytest.skip(f"udp_multicast not available here: {exc}")
    v = virtuals("--lattice", "3x3", "--transport", "can", "--can-interface", "udp_multicast",
                 "--layout-out", str(tmp_path / "sheet.csv"))
    assert v.host_cmd[:2] == ["--can", "udp_multicast:239.74.163.2"]
    out, doc = host_json(*v.host_cmd, "--duration", "1.5", *DELIVERY)
    assert out.returncode == 0, out.stderr
    assert "12 chips found, 12 assigned" in out.stderr
    assert doc["summary"]["valid_links_pct"] >= 95.0 and doc["summary"]["foreign_syncs"] == 0


@ONE_MULTICAST_BUS
def test_two_udp_multicast_sheets_on_one_machine_do_not_hear_each_other(udp_bus_lock, virtuals, tmp_path):
    """Two sheets side by side on distinct groups, a host on each, at once: each host finds
    exactly its own chips (3x3: 12, 4x4: 24), no unknown node or chip, no stray frame, no foreign
    SYNC (the other host's), and streams complete (host/transport/udp_multicast.py)."""
    _udp_or_skip()
    sheets = {}
    for name, lattice, group in (("a", "3x3", "239.74.163.40"), ("b", "4x4", "239.74.163.41")):
        v = virtuals("--lattice", lattice, "--transport", "can", "--can-interface", "udp_multicast",
                     "--channel", group, "--layout-out", str(tmp_path / f"{name}.csv"))
        assert v.host_cmd[:2] == ["--can", f"udp_multicast:{group}"]
        sheets[name] = v
    procs = {n: subprocess.Popen(CLI + ["host", *modest_rate([*v.host_cmd, "--duration", "2", *DELIVERY, "--json", "-q"])],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
             for n, v in sheets.items()}
    for name, chips in (("a", 12), ("b", 24)):
        out, err = procs[name].communicate(timeout=120)
        assert procs[name].returncode == 0 and "Traceback" not in err, err
        assert f"{chips} chips found, {chips} assigned" in err, err
        doc = json.loads(out)
        assert doc["unknown_nodes"] in ([], {}, 0) and doc["unknown_chips"] in ([], {}, 0), doc
        s = doc["summary"]
        assert (s["links"], s["assigned"], s["stray_frames"], s["foreign_syncs"]) == (chips, chips, 0, 0), s
        assert s["valid_links_pct"] >= 95.0, s


@ONE_MULTICAST_BUS
def test_a_sheet_on_two_udp_multicast_buses(udp_bus_lock, virtuals, tmp_path):
    """Two buses of one sheet on two groups (refused once: their traffic crossed): the
    host finds each block of chips on its own bus and streams them all."""
    _udp_or_skip()
    v = virtuals("--lattice", "4x4", "--transport", "can", "--can-interface", "udp_multicast",
                 "--bus-count", "2", "--channel", "239.74.163.42", "--channel", "239.74.163.43",
                 "--layout-out", str(tmp_path / "sheet.csv"))
    assert v.host_cmd[:4] == ["--can", "udp_multicast:239.74.163.42", "--can", "udp_multicast:239.74.163.43"]
    out, doc = host_json(*v.host_cmd, "--duration", "2", *DELIVERY)
    assert out.returncode == 0, out.stderr
    assert "24 chips found, 24 assigned" in out.stderr, out.stderr
    s = doc["summary"]
    assert (s["stray_frames"], s["foreign_syncs"], s["recoveries"]) == (0, 0, 0), s
    assert s["valid_links_pct"] >= 95.0, s


# -- summary and exit codes ----------------------------------------------------------------------

def test_summary_names_the_missing_link_and_min_complete_decides(virtuals, tmp_path, cli_here):
    lay = tmp_path / "sheet.csv"
    v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(lay),
                 "--faults", "dead_chip=4,seed=2")
    uid = [ln.split(",")[0] for ln in lay.read_text().splitlines()[1:] if ln.endswith(",4")][0]
    out = host(*v.host_cmd, "--duration", "1.5", *DELIVERY, "--allow-missing", "--status-every", "0.2")
    # 11 of 12 links: 91.7 % >= 90 %: exit 0, link 4 named with its uid
    assert out.returncode == 0, out.stderr
    assert f"4 (uid {uid})" in out.stderr, out.stderr
    assert "\r" not in out.stderr  # not a terminal: plain periodic lines
    assert out.stderr.count("snapshots") >= 3
    out = host_here(cli_here, *v.host_cmd, "--duration", "1.0", "--allow-missing", "--min-complete", "99")
    assert out.returncode == 1 and "below --min-complete 99 %" in out.stderr, out.stderr


def test_log_lines_never_glue_onto_the_status_line(virtuals, tmp_path):
    """On a terminal the status is one \\r line; a log line (here: a chip that falls silent) starts
    on a line of its own."""
    lay = tmp_path / "sheet.csv"
    v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(lay),
                 "--faults", "dead_chip=4,dead_after_s=3,seed=2")
    master, slave = os.openpty()
    p = subprocess.Popen(CLI + ["host", *v.host_cmd, "--duration", "4", "--allow-missing", "--status-every", "0.1"],
                         stdout=subprocess.DEVNULL, stderr=slave, env=ENV)
    os.close(slave)
    buf = b""
    while True:
        try:
            chunk = os.read(master, 65536)
        except OSError:
            break
        if not chunk:
            break
        buf += chunk
    p.wait(30)
    os.close(master)
    text = buf.decode(errors="replace").replace("\r\n", "\n")
    assert "silent" in text and "\r" in text
    for k in [i for i in range(len(text)) if text.startswith("WARNING", i)]:
        assert k == 0 or text[k - 1] == "\n", repr(text[max(0, k - 80):k + 20])


def _udp_or_skip():
    try:
        import can
        b = can.Bus(interface="udp_multicast", channel="239.74.163.2")
        b.shutdown()
    except Exception as exc:  # noqa: BLE001 - no multicast route on this machine
        pytest.skip(f"udp_multicast not available here: {exc}")


@ONE_MULTICAST_BUS
@pytest.mark.parametrize("what", ["reset", "stray"])
def test_a_third_process_on_the_bus_reset_broadcast_or_stray_frame(udp_bus_lock, virtuals, tmp_path, what):
    """udp_multicast lets a third process speak on the sheet's bus: a RESET broadcast mid-stream is
    recovered (>= 99 % complete after the report); a SAMPLE with a counter the host never sent costs
    nothing but itself (counted as stray)."""
    _udp_or_skip()
    import can
    from protocol.can import to_can
    from protocol.messages import Reset, Sample
    from host.record.recording import read_recording
    rec = tmp_path / "run.mcap"
    v = virtuals("--lattice", "3x3", "--transport", "can", "--can-interface", "udp_multicast",
                 "--layout-out", str(tmp_path / "sheet.csv"))
    # 4.5 s at 50 Hz: ~150 snapshots after the frame, where the checks need 50-100
    p = popen_host(*v.host_cmd, "--duration", "4.5", *DELIVERY, "--json", "-q", "--record", str(rec))
    err: list = []
    wait_line(p, "started on", 60, err)
    drainer = drain(p, err)
    time.sleep(1.5)
    msg = Reset(0) if what == "reset" else Sample(2, 40000, 0, 0, 1024, 0)
    f = to_can(msg)
    bus = can.Bus(interface="udp_multicast", channel="239.74.163.2")
    try:
        bus.send(can.Message(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True))
    finally:
        bus.shutdown()
    out = finish(p, drainer)
    s = json.loads(out)["summary"]
    assert p.returncode == 0, "".join(err)
    r = read_recording(rec)
    ts, complete = np.asarray(r.timestamp), np.asarray(r.complete)
    if what == "reset":
        # every chip recovered, each wave reported (the host gathers the chips that announced into a
        # wave: on a loaded machine their announcements came late enough to make two, 3 then 9)
        t_recs = [i["t"] for i in s["incidents"] if i["kind"] == "recovery"]
        assert s["recovered_chips"] == 12 and s["recoveries"] == len(t_recs) >= 1, s
        t_rec = max(t_recs)
        after = complete[ts > t_rec]
        assert after.size >= 50 and after.mean() >= 0.99, (after.size, after.mean())
    else:
        assert s["stray_frames"] == 1 and s["recoveries"] == 0, s
        assert complete.size >= 100 and int((~complete).sum()) <= 1 + 2  # its own, and at most the two cut by STOP


# -- completeness by snapshot and by valid link --------------------------------

def test_status_line_and_json_show_completeness_by_snapshot_and_by_valid_link(virtuals, tmp_path):
    """A 3x3 sheet (12 links) with link 4's chip dead from the start and 3 % of the gateway's frames
    lost: the three figures differ — complete snapshots, valid link samples of the lattice (what
    --min-complete judges) and of the assigned links. Each is checked against the recording (every
    snapshot the host emitted, recomputed here from its valid flags), in the JSON and on the last
    plain status line."""
    import re
    from host.record.recording import read
    lay, rec_path = tmp_path / "sheet.csv", tmp_path / "run.mcap"
    v = virtuals("--lattice", "3x3", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(lay),
                 "--faults", "dead_chip=4,drop_frame=0.03,seed=5")
    out = host(*v.host_cmd, "--rate", "10", "--duration", "4", "--allow-missing", "--min-complete", "0",
               "--status-every", "0.5", "--record", str(rec_path), "--live-rate", "1", "--json")
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr, out.stderr
    doc = json.loads(out.stdout)
    s, live = doc["summary"], doc["live"]
    r = read(rec_path)
    n = len(r.complete)
    # the recording holds every snapshot (10 Hz: the 64 queued snapshots cover a 6 s stall)
    assert doc["aggregator"]["dropped"] == 0 and n == s["snapshots"] > 20, (n, s["snapshots"])
    valid = np.asarray(r.valid, dtype=bool)
    assert valid.shape == (n, 12)
    others = [k for k in range(12) if k != 4]
    assert not valid[:, 4].any()  # the dead chip's link never carries a sample
    complete = valid[:, others].all(axis=1)  # every assigned link valid
    arrived = (np.asarray(r.status).astype(np.int64) & 0x10) == 0  # LinkFlag.MISSING not set
    assert np.array_equal(complete, arrived[:, others].all(axis=1))  # per-chip frames: arrived = valid
    assert np.array_equal(complete, np.asarray(r.complete, dtype=bool))
    want_snap = 100.0 * complete.sum() / n
    want_lattice = 100.0 * valid.sum() / (n * 12)
    want_assigned = 100.0 * valid[:, others].sum() / (n * 11)
    assert want_snap < 100.0 and want_assigned < 100.0  # the lost frames show (else the test shows nothing)
    assert s["complete_snapshots"] == int(complete.sum())
    assert s["complete_snapshots_pct"] == pytest.approx(want_snap, abs=0.006)
    assert s["valid_links_pct"] == pytest.approx(want_lattice, abs=0.006)
    assert live["complete_snapshots_pct"] == pytest.approx(want_snap, abs=0.0006)
    assert live["valid_links_pct"] == pytest.approx(want_assigned, abs=0.0006)
    # not a terminal: plain status lines; the last one is printed after the stream stopped
    lines = [ln for ln in out.stderr.splitlines() if " snapshots " in ln and "of link samples valid" in ln]
    assert len(lines) >= 2, out.stderr
    m = re.search(r"(\d+) snapshots .* complete\s+([\d.]+)% of snapshots,\s+([\d.]+)% of link samples valid",
                  lines[-1])
    assert m, lines[-1]
    assert int(m.group(1)) == n
    assert float(m.group(2)) == pytest.approx(want_snap, abs=0.051)
    assert float(m.group(3)) == pytest.approx(want_lattice, abs=0.051)
    assert f"{s['complete_snapshots']} complete ({want_snap:.1f} %)" in out.stderr


# -- a sheet behind two serial gateways, merged into one lattice ---------------

@pytest.mark.parametrize("mode", ["drive", "follow-packed"])
def test_two_serial_gateways_merge_into_one_lattice(virtuals, tmp_path, mode):
    """``capsheet virtual --gateways 2``: two ptys, each with its own symlink and half the links;
    ``capsheet host --port A --port B`` (the command it prints) merges them: every chip found, each
    link's chip known on the port of its half, the snapshots complete. Driving: the host sends SYNC
    on both ports. Following: gateway 0 leads SYNC and passes it to gateway 1 (packed frames)."""
    from host.record.recording import read
    lay, rec_path, link = tmp_path / "sheet.json", tmp_path / "run.mcap", tmp_path / "gw"
    extra = ["--rate", "30", "--packed"] if mode == "follow-packed" else []
    delivery = FOLLOWING if mode == "follow-packed" else DELIVERY
    v = virtuals("--lattice", "6x6", "--gateways", "2", "--symlink", str(link), "--layout-out", str(lay), *extra)
    paths = [str(link) + "0", str(link) + "1"]
    assert [a for i, a in enumerate(v.host_cmd) if i and v.host_cmd[i - 1] == "--port"] == paths, v.host_cmd
    assert os.path.realpath(paths[0]) != os.path.realpath(paths[1])  # two ptys
    if mode == "follow-packed":
        assert "--sync" in v.host_cmd and "follow" in v.host_cmd  # packing: the gateway nodes say so
    # 1.5 s: ~45-75 snapshots at 30-50 Hz, where the checks below need 10
    out, doc = host_json(*v.host_cmd, "--duration", "1.5", *delivery, "--record", str(rec_path), "--live-rate", "1")
    assert out.returncode == 0, out.stderr
    assert "60 chips found, 60 assigned, 60 configured, 0 calibrated (60 nominal: no calibration of their own), 60 started" in out.stderr, out.stderr
    assert [b["name"] for b in doc["buses"]] == paths
    # 6x6 joints: 60 links; gateway 0 holds links 0..29, gateway 1 links 30..59
    uids = {c["link"]: c["uid"].lower() for c in json.loads(lay.read_text())["chips"]}
    chips = doc["chips"]
    assert sorted(int(k) for k in chips) == list(range(60))
    for k, c in chips.items():
        assert c["bus"] == (0 if int(k) < 30 else 1), (k, c)
        assert int(c["uid"], 16) == int(uids[int(k)], 16)
        assert c["frames"] > 0
    s = doc["summary"]
    assert not s["errors"] and s["stray_frames"] == 0 and s["resyncs"] == 0, s
    r = read(rec_path)
    valid = np.asarray(r.valid, dtype=bool)
    # every snapshot recorded or counted as dropped (newest wins when the recorder falls behind)
    assert valid.shape[1] == 60 and valid.shape[0] + doc["aggregator"]["dropped"] == s["snapshots"]
    assert valid.shape[0] >= 10
    # both halves in the same snapshots: at most the last two cut by STOP are incomplete
    # (packed: the first SNAPSHOT can carry chips that had not answered yet as INVALID)
    both = valid[:, :30].all(axis=1) & valid[:, 30:].all(axis=1)
    assert int((~both).sum()) <= 2, np.flatnonzero(~both)
    arrived = (np.asarray(r.status).astype(np.int64) & 0x10) == 0  # LinkFlag.MISSING not set
    assert np.array_equal(arrived.all(axis=1), np.asarray(r.complete, dtype=bool))
    counters = np.asarray(r.counter).astype(np.int64)
    assert np.all((np.diff(counters) % 65536) >= 1), counters[:20]  # one snapshot per counter, in order
    if mode == "drive":
        assert doc["syncs_seen"] == 0  # no SYNC source but the host
    else:  # gateway 0 leads, gateway 1 takes its SYNC over the SYNC line: both ports carry every SYNC
        assert doc["syncs_seen"] >= 2 * s["snapshots"] - 4, (doc["syncs_seen"], s["snapshots"])


def test_a_port_given_twice_and_gateways_usage_are_exit_2(virtuals, tmp_path, cli_here):
    """The first refusal of each command through a real process, the others through the entry point
    in this process (refused before any port opens or any sheet starts)."""
    v = virtuals("--lattice", "3x3", "--gateways", "2", "--symlink", str(tmp_path / "gw"))
    a = str(tmp_path / "gw0")
    for k, ports in enumerate(([a, a], [a, os.path.realpath(a)])):
        argv = ("--port", ports[0], "--port", ports[1], "--lattice", "3x3", "--auto-assign", "--duration", "1")
        out = host(*argv) if k == 0 else host_here(cli_here, *argv)
        assert out.returncode == 2 and "given twice" in out.stderr and "Traceback" not in out.stderr, out.stderr
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr
    out = host_here(cli_here, "--port", a, "--can", "virtual:x", "--lattice", "3x3", "--duration", "1")
    assert out.returncode == 2 and "not both" in out.stderr, out.stderr
    for k, (args, needle) in enumerate(((["--transport", "slcan", "--gateways", "2"], "--gateways is for --transport pty"),
                                        (["--lattice", "2x2", "--gateways", "5"], "need 1..4"),
                                        (["--gateways", "0"], "--gateways: invalid value '0': need an integer >= 1"))):
        if k == 0:
            p = subprocess.run(CLI + ["virtual", *args, "--duration", "1"], capture_output=True, text=True,
                               timeout=60, env=ENV)
            code, err = p.returncode, p.stderr
        else:
            code, _out, err = cli_here(["virtual", *args, "--duration", "1"])
        assert code == 2 and needle in err and "Traceback" not in err, (args, err)
    assert v.p.poll() is None


def test_a_second_port_that_is_not_this_sheet_is_a_mismatch(virtuals, tmp_path, cli_here):
    """Two ports must be two halves of one sheet: a port whose chips are all foreign to the layout
    (another sheet's gateway) is named; the same chips on both ports (two sheets with colliding
    uids, as one gateway opened twice would be) are refused. Exit 2, one line, before streaming."""
    lay = tmp_path / "sheet.json"
    a = virtuals("--lattice", "3x3", "--gateways", "2", "--symlink", str(tmp_path / "a"), "--layout-out", str(lay))
    b = virtuals("--lattice", "3x3", "--seed", "7", "--symlink", str(tmp_path / "b"))
    out = host("--port", str(tmp_path / "a0"), "--port", str(tmp_path / "b"), "--layout", str(lay), "--duration", "2")
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert f"none of the chips on {tmp_path / 'b'} is in the layout" in out.stderr, out.stderr
    c = virtuals("--lattice", "3x3", "--seed", "7", "--symlink", str(tmp_path / "c"))  # b's uids again
    out = host_here(cli_here, "--port", str(tmp_path / "b"), "--port", str(tmp_path / "c"), "--lattice", "3x3",
                    "--auto-assign", "--duration", "2")  # refused after discovery: in this process
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert "answer on more than one port" in out.stderr and str(tmp_path / "c") in out.stderr, out.stderr
    assert a.p.poll() is None and b.p.poll() is None and c.p.poll() is None


def test_a_record_logged_while_the_status_line_is_written_starts_on_its_own_line():
    """The race the end-to-end test above once lost under load: a host thread logs while the main
    thread is writing the status line, after its text and before it is marked open."""
    import io
    import logging

    from host.cli.host import StatusLine, _StatusAwareHandler

    class Terminal(io.StringIO):
        def __init__(self):
            super().__init__()
            self.logger = None

        def isatty(self):
            return True

        def write(self, s):
            n = super().write(s)
            if s.startswith("\r") and self.logger is not None:  # a status line just went out
                log, self.logger = self.logger, None
                t = threading.Thread(target=log.warning, args=("chip 4 silent",))
                t.start()
                t.join(0.3)  # without the lock it writes now, glued; with it, it waits
                self.pending = t
            return n

    term = Terminal()
    status = StatusLine(term)
    log = logging.getLogger("capsheet.test.status_race")
    log.propagate = False
    handler = _StatusAwareHandler(status)
    handler.setFormatter(logging.Formatter("WARNING %(message)s"))
    log.addHandler(handler)
    try:
        term.logger = log
        status.show("   10 snapshots")
        term.pending.join(10)
        status.show("   20 snapshots")
    finally:
        log.removeHandler(handler)
    text = term.getvalue()
    k = text.index("WARNING")
    assert k > 0 and text[k - 1] == "\n", repr(text)


def test_discovery_window_lasts_while_chips_are_still_answering(virtuals, tmp_path):
    """1,984 chips answer GET_INFO with ~4,000 frames over a real pty: every chip is found and
    started (before, 913 layout chips "never answered" in three 50 ms windows; at 64x64 under load,
    1-2 of 8,064 with the default 0.5 s). A round's window lasts until no new chip has been heard
    for `DISCOVER_QUIET_S`. That the window outlasts the one asked for while answers still arrive
    is held on a simulated clock (tests/host/test_back2back.py,
    `test_discovery_lasts_while_answers_are_still_arriving`, a 50 ms window against 0.5 s of
    answers): here, the whole path of the command, with a window of 5 s (a layout given: it ends
    once every chip answered, so it costs nothing on a machine that keeps up). With 50 ms, and even
    with the default 0.5 s, a loaded machine (three test workers, two busy loops, load ~15) left the
    sheet's process unscheduled past the window's end and chips "never answered" (1,503 of 1,984)."""
    lay = tmp_path / "sheet.json"
    v = virtuals("--lattice", "32x32", "--packed", "--layout-out", str(lay))
    assert "--layout" in v.host_cmd  # the window ends as soon as every chip of it answered
    cmd = list(v.host_cmd)
    k = cmd.index("--rate") + 1
    cmd[k] = str(min(float(cmd[k]), 50.0))  # at most 50 Hz: the open counters hold the 2 s deadline
    # every chip streams (no link missing): at load ~15 a 0.5 s stream at the 0.5 s deadline
    # delivered too little of 1,984 chips' frames, and every link was "missing"
    out, doc = host_json(*cmd, "--discover-s", "5", "--duration", "1.5", "--deadline-ms", "2000",
                         "--min-complete", "0")
    assert out.returncode == 0, out.stderr
    assert "1984 chips found, 1984 assigned, 1984 configured" in out.stderr, out.stderr
    assert "1984 started" in out.stderr, out.stderr
    assert doc["summary"]["missing_links"] == [], doc["summary"]["missing_links"]


def test_the_hosts_snapshot_queue_holds_two_seconds_at_the_sync_rate():
    """A following host's chips stream ~1 s before `capsheet host`'s loop takes snapshots: a
    64-deep queue lost 91-112 snapshots of a 64x64 sheet at 145 Hz (recorded, never estimated)."""
    from host.cli.host import queue_size_for
    assert queue_size_for(145) == 291 and queue_size_for(145.0) >= 2 * 145
    assert queue_size_for(10) == 64 and queue_size_for(None) == 64  # the library's default at least


# -- the host's own design for the sheet it has -----------------------------------------------------

@pytest.mark.parametrize("argv, lattice, readers, estimator", [
    # 64x64 on five gateways at 145 Hz, recorded, every snapshot due an estimate: both, unasked
    (["--port", "/tmp/g0", "--port", "/tmp/g1", "--rate", "145", "--record", "x.mcap", "--live-rate", "145"],
     "64x64", True, True),
    # the same sheet at 60 Hz: 0.48 M link samples a second, under the bound: in this process
    (["--port", "/tmp/g0", "--rate", "60", "--record", "x.mcap"], "64x64", False, False),
    # 32x32 at 145 Hz (0.29 M): in this process
    (["--port", "/tmp/g0", "--rate", "145", "--record", "x.mcap"], "32x32", False, False),
    # big, but no estimates wanted: readers only
    (["--port", "/tmp/g0", "--rate", "145"], "64x64", True, False),
    # big, on CAN: no reader (python-can reads its buses); estimates in their process
    (["--can", "socketcan:can0", "--rate", "145", "--record", "x.mcap"], "64x64", False, True),
    # a URL has no file descriptor to hand a reader
    (["--port", "loop://", "--rate", "145", "--record", "x.mcap"], "64x64", False, True),
    # 6/9-axis chips keep their fused estimator in this process
    (["--port", "/tmp/g0", "--rate", "145", "--record", "x.mcap", "--sensors", "accel+gyro"], "64x64", True, False),
    # what the command line says stands
    (["--port", "/tmp/g0", "--rate", "145", "--record", "x.mcap", "--no-reader-processes", "--no-estimate-process"],
     "64x64", False, False),
    (["--port", "/tmp/g0", "--rate", "10", "--record", "x.mcap", "--reader-processes", "--estimate-process"],
     "3x3", True, True),
])
def test_the_host_chooses_its_design_for_the_sheet(tmp_path, argv, lattice, readers, estimator):
    from host.cli import build_parser
    from host.cli.host import choose_design
    from protocol.lattice import Lattice
    argv = [a.replace("x.mcap", str(tmp_path / "x.mcap")) for a in argv]
    args = build_parser().parse_args(["host", *argv])
    line = choose_design(args, Lattice.parse(lattice))
    assert (bool(args.reader_processes), bool(args.estimate_process)) == (readers, estimator)
    given = "--reader-processes" in argv or "--no-reader-processes" in argv
    if (readers or estimator) and not given:
        n = Lattice.parse(lattice).n_links
        assert line is not None and f"{n} links x 145 Hz" in line and "\n" not in line, line
    else:
        assert line is None


def test_the_natural_command_says_the_design_it_chose(tmp_path, cli_here):
    """Through the real command line (a port where nothing answers: the choice is made and said
    before bring-up): a 64x64 sheet at 145 Hz, recorded, gets both processes and one line saying
    so; with the flags turned off, nothing is chosen and nothing said."""
    master, slave = os.openpty()
    try:
        base = ["--port", os.ttyname(slave), "--lattice", "64x64", "--auto-assign", "--rate", "145",
                "--live-rate", "145", "--discover-s", "0.2", "--record", str(tmp_path / "run.mcap")]
        out = host(*base, "--overwrite")
        assert out.returncode == 1 and "no chip answered" in out.stderr, out.stderr
        [line] = [ln for ln in out.stderr.splitlines() if "big sheet" in ln]
        assert ("8064 links x 145 Hz" in line and "each port read by a process of its own" in line
                and "estimates made in a process of their own" in line), line
        out = host_here(cli_here, *base, "--overwrite", "--no-reader-processes", "--no-estimate-process")
        assert out.returncode == 1 and "big sheet" not in out.stderr, out.stderr
    finally:
        os.close(master)
        os.close(slave)
