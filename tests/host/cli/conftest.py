"""The command line through its entry point, in the test's process (`cli_here`).

For a command that refuses before it starts anything (a bad value, a file it will not replace, a
method the recording cannot take), a subprocess proves nothing more than ``host.cli.main(argv)``
does — the same parser, the same checks, the same one line on stderr and exit status — and costs an
interpreter's start (~0.5 s of CPU) per case. Each command keeps its runs through a real process
elsewhere (docs/testing.md says which)."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys

import pytest

from tests.host.cli.cli_runs import Virtual, udp_bus_lock  # noqa: F401 -- the fixture, for this folder


class _Deadline(Exception):
    pass


@contextlib.contextmanager
def _deadline(seconds: float):
    """A command that hangs fails the test after ``seconds``, as a subprocess's timeout did (the
    main thread only: pytest and its xdist workers run tests there)."""
    def ring(_sig, _frame):
        raise _Deadline(f"no answer within {seconds} s")
    old = signal.signal(signal.SIGALRM, ring)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@pytest.fixture
def cli_here(capsys, monkeypatch):
    """``run(argv, cwd=None, timeout_s=60) -> (exit status, stdout, stderr)``: ``capsheet ARGV``
    through `host.cli.main` here. argparse's own refusals (SystemExit) give their status; the
    process-wide state a command sets (root logging handlers, the interpreter's switch interval,
    the working directory, the SIGTERM/SIGHUP/SIGINT handlers) is put back after each call, so one
    case cannot leak into the next."""
    from host.cli import main

    def run(argv: list[str], cwd=None, timeout_s: float = 60.0) -> tuple[int, str, str]:
        root = logging.getLogger()
        handlers, level = list(root.handlers), root.level
        switch = sys.getswitchinterval()
        # a command that streams takes SIGTERM/SIGHUP for itself (host, virtual, view): put back
        handlers_sig = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)}
        here = os.getcwd()
        capsys.readouterr()
        try:
            if cwd is not None:
                os.chdir(cwd)
            with _deadline(timeout_s):
                try:
                    code = main(list(argv))
                except SystemExit as exc:
                    code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
                    if exc.code is not None and not isinstance(exc.code, int):
                        print(exc.code, file=sys.stderr)  # what the interpreter prints at such an exit
        finally:
            os.chdir(here)
            root.handlers[:] = handlers
            root.setLevel(level)
            sys.setswitchinterval(switch)
            for sig, h in handlers_sig.items():
                signal.signal(sig, h)
        got = capsys.readouterr()
        return code, got.out, got.err

    return run


@pytest.fixture
def virtuals():
    """``make(*args)``: a `Virtual` sheet, killed at the test's end."""
    made: list[Virtual] = []

    def make(*args):
        v = Virtual(*args)
        made.append(v)
        return v
    yield make
    for v in made:
        v.stop(signal.SIGKILL)
