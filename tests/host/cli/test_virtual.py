"""``capsheet virtual`` through the real CLI: it removes its symlinks on every exit it can
catch, replaces only a stale symlink of its own, prints the exact host command that works,
and checks its own traffic against the link's capacity."""

from __future__ import annotations

import os
import signal
import subprocess

import pytest

from tests.host.cli.cli_runs import CLI, ENV, Virtual


def _virtual_here(capsys, *args: str) -> tuple[int, str, str]:
    """``capsheet virtual ARGS`` through its entry point in this process, for the runs it refuses
    before it starts a sheet (the runs through a real process: `Virtual`, and the refusal of a
    running sheet's path below): (exit status, stdout, stderr)."""
    from host.cli import main
    capsys.readouterr()
    try:
        code = main(["virtual", *args])
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    got = capsys.readouterr()
    return code, got.out, got.err


@pytest.mark.parametrize("transport,sig", [("pty", signal.SIGTERM), ("pty", signal.SIGHUP),
                                           ("pty", signal.SIGINT), ("slcan", signal.SIGTERM)])
def test_the_symlink_goes_with_the_sheet(tmp_path, transport, sig):
    link = tmp_path / "port"
    # Ctrl-C as in a terminal: a suite started in the background (`make test &`, a CI script) runs
    # with SIGINT ignored, which its children inherit across exec — then the sheet rightly ignores
    # SIGINT (POSIX's convention for background jobs) and this test waited 30 s for nothing. A
    # handler installed here is reset to the default in the child at exec, as a terminal's would be.
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        v = Virtual("--lattice", "3x3", "--transport", transport, "--symlink", str(link))
    finally:
        signal.signal(signal.SIGINT, old)
    with open(f"/proc/{v.p.pid}/status") as f:
        ignored = int(next(ln for ln in f if ln.startswith("SigIgn:")).split()[1], 16)
    assert not ignored & (1 << (signal.SIGINT - 1)), "the sheet was started with SIGINT ignored"
    try:
        assert link.is_symlink()
        assert v.stop(sig) == 0
        assert not link.exists() and not link.is_symlink()
    finally:
        v.stop(signal.SIGKILL)


def test_only_a_stale_symlink_of_its_own_is_replaced(tmp_path, capsys):
    """A sheet killed with SIGKILL leaves its symlink: the next sheet on that path takes it over. A
    running sheet's symlink, someone's file, or a symlink no sheet made are not touched (exit 2, one
    line), unless --overwrite says so (never a folder)."""
    link = tmp_path / "port"
    a = Virtual("--lattice", "3x3", "--symlink", str(link))
    try:
        first = os.readlink(link)
        busy = subprocess.run(CLI + ["virtual", "--lattice", "3x3", "--symlink", str(link), "--duration", "1"],
                              capture_output=True, text=True, timeout=60, env=ENV)
        assert busy.returncode == 2 and "port of a running virtual sheet" in busy.stderr, busy.stderr
        assert os.readlink(link) == first
        a.stop(signal.SIGKILL)
        assert os.readlink(link) == first  # SIGKILL: nothing could clean up
        b = Virtual("--lattice", "3x3", "--symlink", str(link))  # ours and stale: replaced
        assert b.p.poll() is None and link.is_symlink()  # it started on the path the killed one left
        assert b.stop() == 0 and not link.is_symlink()
    finally:
        a.stop(signal.SIGKILL)
    os.symlink("/dev/null", link)  # a symlink nobody's sheet made
    mine = tmp_path / "notes.txt"
    mine.write_text("mine")
    for path, what in ((link, "a symlink to /dev/null that no capsheet sheet published"), (mine, "a file")):
        code, _out, err = _virtual_here(capsys, "--lattice", "3x3", "--symlink", str(path), "--duration", "1")
        assert code == 2 and what in err and len(err.strip().splitlines()) == 1, err
    assert os.readlink(link) == "/dev/null" and mine.read_text() == "mine"
    c = Virtual("--lattice", "3x3", "--symlink", str(mine), "--overwrite")  # said so: replaced
    try:
        assert mine.is_symlink()
    finally:
        assert c.stop() == 0
    assert not mine.exists()


def test_the_printed_host_command_carries_what_the_sheet_needs(tmp_path):
    v = Virtual("--lattice", "4x4", "--transport", "slcan", "--bus-count", "2", "--fd", "--packed",
                "--rate", "50", "--symlink", str(tmp_path / "can"), "--layout-out", str(tmp_path / "s.json"))
    try:
        cmd = v.host_cmd
        assert cmd.count("--can") == 2 and f"slcan:{tmp_path / 'can'}0" in cmd and f"slcan:{tmp_path / 'can'}1" in cmd
        assert "--fd" in cmd
        assert "--packed" not in cmd  # the gateway node says it packs (docs/protocol.md §13): the host learns it
        assert cmd[cmd.index("--sync") + 1] == "follow" and cmd[cmd.index("--layout") + 1] == str(tmp_path / "s.json")
        assert cmd[cmd.index("--lattice") + 1] == "4x4" and cmd[cmd.index("--bitrate") + 1] == "1000000"
        assert cmd[cmd.index("--rate") + 1] == "50"  # the sheet's own SYNC rate, which the host follows
    finally:
        v.stop()
    # without --rate the host drives SYNC: the command says at what rate (the paper's where it fits)
    v = Virtual("--lattice", "4x4", "--symlink", str(tmp_path / "serial"))
    try:
        cmd = v.host_cmd
        assert cmd[cmd.index("--rate") + 1] == "145" and "--sync" not in cmd
    finally:
        v.stop()


def test_its_own_traffic_over_capacity_is_refused(tmp_path, capsys):
    # 364 chips on one classic 1 Mbit/s bus at 100 Hz: 547 % (364 x 150 bits + SYNC, x 100 / 1e6)
    code, _out, err = _virtual_here(capsys, "--transport", "slcan", "--lattice", "14x14", "--rate", "100",
                                    "--symlink", str(tmp_path / "can"), "--duration", "1")
    assert code == 2, err
    assert "over capacity" in err and "547 %" in err and "--bus-count" in err
    assert not (tmp_path / "can").exists()
    # split over 8 buses: at most 46 chips per bus, 46 x 150 + 100 bits per SYNC: 70 % at 100 Hz, full at 143 Hz
    out = subprocess.run(CLI + ["virtual", "--transport", "slcan", "--lattice", "14x14", "--rate", "100",
                                "--bus-count", "8", "--symlink", str(tmp_path / "can"), "--duration", "0.5"],
                         capture_output=True, text=True, timeout=120, env=ENV)
    assert out.returncode == 0, out.stderr
    assert "capacity: this link carries this sheet's traffic up to 143 Hz" in out.stdout


@pytest.mark.parametrize("args,needle", [(("--rate", "0"), "--rate: invalid value '0'"),
                                         (("--rate", "nan"), "--rate: invalid value 'nan'"),
                                         (("--lattice", "14by14"), "--lattice: invalid value '14by14'"),
                                         (("--baud", "0"), "need an integer >= 1")])
def test_bad_values_are_one_line_errors(args, needle, capsys):
    code, _out, err = _virtual_here(capsys, "--transport", "memory", "--duration", "0.1", *args)
    assert code == 2 and needle in err and "Traceback" not in err, err
