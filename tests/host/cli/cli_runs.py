"""Running ``capsheet`` commands as real processes for the CLI's tests: ``capsheet virtual`` in a
subprocess (`Virtual`), ``capsheet host`` run to its end (`host`, `host_json`) or started and read
line by line (`popen_host`, `wait_line`, `drain`, `finish`). ``udp_bus_lock`` is the
fixture that keeps udp_multicast tests apart; tests/host/cli/conftest.py has it and ``virtuals``."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

CLI = [sys.executable, "-m", "host.cli"]
ENV = dict(os.environ, PYTHONUNBUFFERED="1")


class Virtual:
    """``capsheet virtual ...`` in a subprocess; its stdout is read in a thread (never blocks)."""

    def __init__(self, *args: str) -> None:
        self.args = list(args)
        self.lines: list[str] = []
        self.p = subprocess.Popen(CLI + ["virtual", *self.args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True, env=ENV)
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()
        self.host_cmd = self.wait_for("capsheet host ", 60).strip().split()[2:]

    def _read(self) -> None:
        for line in self.p.stdout:
            self.lines.append(line)

    def wait_for(self, needle: str, timeout_s: float) -> str:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            for line in self.lines:
                if needle in line:
                    return line
            if self.p.poll() is not None and not self._t.is_alive():
                break
            time.sleep(0.05)
        raise AssertionError(f"capsheet virtual did not print {needle!r}: {self.lines} {self.p.stderr.read() if self.p.poll() is not None else ''}")

    def stop(self, sig=signal.SIGTERM) -> int:
        if self.p.poll() is None:
            self.p.send_signal(sig)
        try:
            return self.p.wait(30)
        finally:
            if self.p.poll() is None:
                self.p.kill()




#: what a host that is judged on what it delivered (a completeness figure, "every chip streamed")
#: runs at: what is delivered is under test, not how soon. A deadline of 2 s (the helpers' 0.5 s was
#: short of a sheet process a loaded machine left behind: "late" answers, and runs below their
#: figure, with three test workers and two busy loops), at a SYNC rate whose open counters
#: (`Host`'s ``max_open``, at most 128) hold those 2 s. A following host takes the deadline alone.
DELIVERY = ("--rate", "50", "--deadline-ms", "2000")
FOLLOWING = ("--deadline-ms", "2000")


def modest_rate(args) -> list:
    """A modest SYNC rate and a generous completion deadline unless the test gives them: what is
    delivered is under test, not speed or latency (a loaded 2-core machine)."""
    args = list(args) if "--rate" in args else [*args, "--rate", "30"]
    return args if "--deadline-ms" in args else [*args, "--deadline-ms", "500"]


def host(*args: str, timeout_s: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + ["host", *modest_rate(args)], capture_output=True, text=True, timeout=timeout_s, env=ENV)


def host_json(*args: str, timeout_s: float = 120) -> tuple[subprocess.CompletedProcess, dict]:
    out = host(*args, "--json", "-q", timeout_s=timeout_s)
    assert "Traceback" not in out.stderr, out.stderr
    assert out.stdout.strip(), (out.returncode, out.stderr)  # JSON alone on stdout
    doc = json.loads(out.stdout)
    return out, doc


def popen_host(*args: str) -> subprocess.Popen:
    return subprocess.Popen(CLI + ["host", *modest_rate(args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ENV)


def wait_line(p: subprocess.Popen, needle: str, timeout_s: float, sink: list) -> None:
    """Read ``p``'s stderr (into ``sink``) until a line holds ``needle``."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        line = p.stderr.readline()
        if not line:
            break
        sink.append(line)
        if needle in line:
            return
    raise AssertionError(f"host never printed {needle!r}: {''.join(sink)}")


def drain(p: subprocess.Popen, sink: list) -> threading.Thread:
    t = threading.Thread(target=lambda: sink.extend(iter(p.stderr.readline, "")), daemon=True)
    t.start()
    return t


def finish(p: subprocess.Popen, drainer: threading.Thread, timeout_s: float = 60) -> str:
    """The host's stdout once it has exited, while ``drainer`` (not ``communicate``, which would
    race it for stderr) reads stderr to its end."""
    box: list = []
    reader = threading.Thread(target=lambda: box.append(p.stdout.read()), daemon=True)
    reader.start()
    p.wait(timeout_s)
    reader.join(timeout_s)
    drainer.join(timeout_s)
    return box[0]


@pytest.fixture
def udp_bus_lock():
    """One udp_multicast test on this machine at a time (tests/host/udp_lock.py says why)."""
    from tests.host.udp_lock import udp_multicast_lock
    with udp_multicast_lock():
        yield


def host_here(cli_here, *args: str, timeout_s: float = 120) -> subprocess.CompletedProcess:
    """`host` through the entry point in this process (tests/host/cli/conftest.py's ``cli_here``):
    the same command line (`modest_rate`), the same fields of the result. For a run whose process
    proves nothing more than the command does (a refusal, a session after the first)."""
    code, out, err = cli_here(["host", *modest_rate(args)], timeout_s=timeout_s)
    return subprocess.CompletedProcess(["capsheet", "host", *args], code, out, err)


def host_json_here(cli_here, *args: str, timeout_s: float = 120) -> tuple[subprocess.CompletedProcess, dict]:
    """`host_json` through the entry point in this process (`host_here`)."""
    out = host_here(cli_here, *args, "--json", "-q", timeout_s=timeout_s)
    assert "Traceback" not in out.stderr, out.stderr
    assert out.stdout.strip(), (out.returncode, out.stderr)
    return out, json.loads(out.stdout)
