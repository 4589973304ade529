"""One session per port: a second ``capsheet host``, and every other command that opens a port, is
refused while a host streams from it — exit 1, one line naming the holder's process, and the holder
streams on (was: the second took over and the first fell to 37 % complete with framing errors)."""

from __future__ import annotations

import json
import signal
import subprocess

import pytest

from tests.host.cli.cli_runs import CLI, DELIVERY, ENV, Virtual, drain, finish, host_here, popen_host, wait_line


def test_a_second_host_on_a_busy_port_is_refused_at_once(virtuals, tmp_path, cli_here):
    """A second ``capsheet host`` on the port a first one streams from: refused before it opens the
    port, exit 1, one line naming the first host's process; the first ends exit 0, >= 99 % complete
    (was: the second took over and the first fell to 37 % with framing errors). The second runs
    in this process (another process than the first's all the same: the lock is between processes),
    so it is refused while the first streams without waiting for an interpreter to start."""
    lay = tmp_path / "sheet.csv"
    v = virtuals("--lattice", "6x6", "--symlink", str(tmp_path / "sheet"), "--layout-out", str(lay))
    p = popen_host(*v.host_cmd, "--duration", "4", *DELIVERY, "--json", "-q")
    err: list = []
    wait_line(p, "started on", 60, err)
    drainer = drain(p, err)
    second = host_here(cli_here, *v.host_cmd, "--duration", "3", timeout_s=60)
    assert p.poll() is None, "the first host ended before the second was refused: no proof"
    out = finish(p, drainer)
    assert second.returncode == 1, second.stderr
    [line] = second.stderr.splitlines()
    assert "is in use by process" in line and f"process {p.pid} (" in line and "one session per port" in line, line
    assert p.returncode == 0, "".join(err)
    s = json.loads(out)["summary"]
    assert s["complete_snapshots_pct"] >= 99.0 and not s["errors"], s


@pytest.fixture(scope="module")
def busy_port(tmp_path_factory):
    """``make(transport) -> (port, host process, sheet's host command)``: a 3x3 sheet on ``pty`` or
    ``slcan`` and a ``capsheet host`` streaming from it, made once per module and transport and
    shared by the refusals below (a refused command never opens the port: nothing a test does
    changes what the next one finds). The hosts are stopped at the module's end."""
    made: dict = {}
    stops: list = []

    def make(transport: str):
        if transport not in made:
            tmp = tmp_path_factory.mktemp(f"busy-{transport}")
            v = Virtual("--lattice", "3x3", "--transport", transport, "--symlink", str(tmp / "sheet"),
                        "--layout-out", str(tmp / "sheet.csv"))
            stops.append(lambda: v.stop(signal.SIGKILL))
            # a SYNC a second: the port is held all the same, and the module's minutes cost little
            p = popen_host(*v.host_cmd, "--duration", "600", "--rate", "1", "--json", "-q")
            err: list = []
            drainer: list = []

            def stop_host():
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
                try:
                    finish(p, drainer[0] if drainer else drain(p, err))
                finally:
                    if p.poll() is None:
                        p.kill()
            stops.append(stop_host)
            wait_line(p, "started on", 60, err)
            drainer.append(drain(p, err))
            made[transport] = (str(tmp / "sheet"), p, v.host_cmd)
        return made[transport]
    try:
        yield make
    finally:
        for stop in reversed(stops):
            stop()


#: the commands refused through a real process (one of each transport's, the other commands'
#: refusals through the entry point in this process: the same check, line and exit status; each of
#: them runs through a real process in its own tests)
REFUSED_IN_A_PROCESS = ("calibrate", "host-slcan")


@pytest.mark.parametrize("command", ["calibrate", "tactile", "conformance", "layout", "ports", "host-slcan"])
def test_every_command_that_opens_a_port_is_refused_on_a_busy_one(busy_port, tmp_path, command, cli_here):
    """What ``capsheet host`` holds, no other command opens: exit 1, one line naming the holder,
    and the holder streams on."""
    port, p, host_cmd = busy_port("slcan" if command == "host-slcan" else "pty")
    args = {"calibrate": ["calibrate", "--port", port, "--lattice", "3x3", "--out", str(tmp_path / "c.json")],
            "tactile": ["tactile", "--port", port, "--lattice", "3x3", "--duration", "1"],
            "conformance": ["conformance", "--port", port],
            "layout": ["layout", "learn", "--port", port, "--lattice", "3x3", "--out", str(tmp_path / "l.csv")],
            "ports": ["ports", "--probe", port],
            "host-slcan": ["host", *host_cmd, "--duration", "1"]}[command]
    if command in REFUSED_IN_A_PROCESS:
        out = subprocess.run(CLI + args, capture_output=True, text=True, timeout=60, env=ENV)
        code, stdout, stderr = out.returncode, out.stdout, out.stderr
    else:
        code, stdout, stderr = cli_here(args)
    assert code == 1, (code, stderr)
    [line] = (stdout if command == "ports" else stderr).splitlines()  # ports: its report
    assert f"is in use by process {p.pid} (" in line, line
    assert p.poll() is None  # the holder streams on
