"""Command processes for the feature x transport matrix (tests/host/test_matrix.py), forked from one
interpreter that has imported what they import: ``python -m tests.host.matrix_fork``.

Each of a batch's commands ran in an interpreter of its own, and each paid the interpreter's start
and the imports of numpy, scipy, matplotlib, python-can, the session and the virtual sheet before
its first frame (0.3-1.5 s of CPU a command, most of a batch's CPU). This server pays them once: it
imports them, then for each ``RUN`` line it reads forks a child that runs the command
(`host.cli.main`, or tests/host/matrix_sheet.py's ``main`` for a command with its sheet in its own
process) with stdout and stderr in files of its own, and ends as the interpreter ends
``python -m host.cli``: its exit status, its atexit handlers, its threads joined. Each child is a
process of its own on the real transport (its own pid, ports, sockets, signal handlers and
threads), as before; what it does not do is start an interpreter. The matrix keeps one command per
transport started the ordinary way (``python -m host.cli``): the stream run.

The protocol, one line each way:

* in: ``RUN ID {"argv": [...], "out": PATH, "err": PATH, "sheet": BOOL, "in": FIFO or null}``
  (``in``: the child's stdin, a FIFO the test writes to; else /dev/null); answered ``STARTED ID
  PID``, and ``EXIT ID STATUS`` when the child has ended (a signal's death: minus its number);
* the server ends once its stdin has closed and its children have ended.

The server starts no thread (a fork copies only the thread that forks), and checks so before every
fork.
"""

from __future__ import annotations

import errno
import gc
import json
import os
import select
import signal
import sys
import threading
import time

#: what the forked commands import (their start's CPU), loaded once here: first what every command
#: and sheet needs (then the server takes RUN lines), then, while no line waits, what calibrate,
#: tactile and the host's estimates add (a child forked before those are loaded imports them itself)
PRELOAD = (
    "numpy", "serial", "can", "mcap.writer", "mcap.reader",
    "host.cli", "host.cli.host", "host.cli.conformance", "host.session", "host.conformance.runner",
    "host.record.recording", "virtual_sheet.sheet", "virtual_sheet.devices", "virtual_sheet.slcan",
    "virtual_sheet.board", "virtual_sheet.memport", "tests.host.matrix_sheet", "tests.host.conformance.mutants",
)
PRELOAD_LATER = (
    "scipy.special", "scipy.optimize", "scipy.spatial.transform", "scipy.linalg", "cantools",
    "matplotlib", "matplotlib.figure", "matplotlib.backends.backend_agg",
    "host.cli.calibrate", "host.cli.tactile", "host.analysis.estimator", "host.analysis.calibration",
    "host.analysis.tactile", "host.analysis.tactile.plot",
)


def load(name: str) -> bool:
    """Import ``name``; False if it does not import (a module renamed: a child imports what it
    needs itself, as before)."""
    import importlib
    try:
        importlib.import_module(name)
    except ImportError:
        return False
    return True


def preload() -> list[str]:
    """Import `PRELOAD` (BLAS single-threaded first, as every command starts); the names that did
    not import."""
    from host.runtime import one_blas_thread
    one_blas_thread()
    return [name for name in PRELOAD if not load(name)]


def child(spec: dict) -> int:
    """In the forked child: stdio to the spec's files, then the command; its exit status."""
    devnull = os.open(os.devnull, os.O_RDONLY)
    if spec.get("in"):  # a FIFO the test writes to (a sheet process's "stop NAME" lines)
        f = os.open(spec["in"], os.O_RDONLY)
        os.dup2(f, 0)
        os.close(f)
    else:
        os.dup2(devnull, 0)
    for fd, path in ((1, spec["out"]), (2, spec["err"])):
        f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(f, fd)
        os.close(f)
    os.close(devnull)
    sys.stdin = open(0, closefd=False)
    argv = list(spec["argv"])
    try:
        if spec.get("sheet"):
            from tests.host.matrix_sheet import main as run
        else:
            from host.cli import main as run
        return int(run(argv) or 0)
    except SystemExit as exc:  # what the interpreter does with it at the end of python -m
        if exc.code is None or isinstance(exc.code, int):
            return exc.code or 0
        print(exc.code, file=sys.stderr)
        return 1


def serve() -> int:
    """Read RUN lines until stdin closes; fork a child for each; report starts and exits. In a
    child, the command's exit status (`main` returns it to the interpreter)."""
    out = sys.stdout
    missing = preload()
    gc.collect()
    gc.freeze()  # the imported modules' objects: no child's collections walk them (nor copy their pages)
    print("READY " + json.dumps(missing), file=out, flush=True)
    running: dict[int, str] = {}
    stdin = sys.stdin.buffer.raw
    buf = b""
    open_in = True
    # a child's end wakes the select below (no polling: the server idles between batches)
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    later = list(PRELOAD_LATER)
    while open_in or running:
        # a module of PRELOAD_LATER each time no line and no child's end came for 50 ms (the lines
        # a batch sends come together: they are forked first)
        ready, _, _ = select.select([stdin, wake_r] if open_in else [wake_r], [], [], 0.05 if later else 1.0)
        if not ready and later:
            load(later.pop(0))
            gc.freeze()
            continue
        if wake_r in ready:
            try:
                os.read(wake_r, 4096)
            except BlockingIOError:
                pass
        if stdin in ready:
            chunk = os.read(stdin.fileno(), 65536)
            if not chunk:
                open_in = False
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                word, ident, rest = line.decode().split(" ", 2)
                if word != "RUN":
                    continue
                if threading.active_count() != 1:
                    raise SystemExit(f"matrix_fork: {threading.active_count()} threads: will not fork")
                out.flush()
                sys.stderr.flush()
                pid = os.fork()
                if pid == 0:
                    signal.set_wakeup_fd(-1)
                    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                    os.close(wake_r)
                    os.close(wake_w)
                    return child(json.loads(rest))
                running[pid] = ident
                print(f"STARTED {ident} {pid}", file=out, flush=True)
        while running:
            pid, status = os.waitpid(-1, os.WNOHANG)
            if pid == 0:
                break
            print(f"EXIT {running.pop(pid)} {os.waitstatus_to_exitcode(status)}", file=out, flush=True)
        if not open_in and not running:
            break
    return 0


if __name__ == "__main__":
    sys.exit(serve())


# ---------------------------------------------------------------------------------------------------
# the test's side
# ---------------------------------------------------------------------------------------------------

class Forked:
    """A command forked by a `Forker` (as `subprocess.Popen` is used by the matrix: ``wait``,
    ``stdout``, ``stderr``)."""

    def __init__(self, server: "Forker", ident: str, argv: list[str], out: str, err: str,
                 stdin_fifo: str | None = None) -> None:
        self.server, self.ident, self.argv, self._out, self._err = server, ident, argv, out, err
        self._in = stdin_fifo

    def wait(self, timeout_s: float = 240.0) -> int:
        s = self.server
        with s.cond:
            if not s.cond.wait_for(lambda: self.ident in s.exits or s.gone, timeout_s):
                pid = s.pids.get(self.ident)
                if pid is not None:
                    os.kill(pid, signal.SIGKILL)  # a hang: as Proc.wait kills a process past its timeout
                s.cond.wait_for(lambda: self.ident in s.exits or s.gone, 30)
                raise TimeoutError(f"{self.argv[:4]} still running after {timeout_s} s")
            if self.ident not in s.exits:
                raise RuntimeError(f"matrix_fork ended before {self.argv[:4]}: {s.stderr_text()}")
            return s.exits[self.ident]

    def exited(self) -> bool:
        with self.server.cond:
            return self.ident in self.server.exits or self.server.gone

    def open_stdin(self, timeout_s: float = 60.0):
        """The write end of the child's stdin FIFO (``run(..., stdin_fifo=True)``), once it has
        opened the read end."""
        end = time.monotonic() + timeout_s
        while True:
            try:
                fd = os.open(self._in, os.O_WRONLY | os.O_NONBLOCK)
                break
            except OSError as exc:  # ENXIO: no reader yet
                if exc.errno != errno.ENXIO or self.exited() or time.monotonic() > end:
                    raise RuntimeError(f"{self.argv[:4]} never read its stdin: {self.stderr[-2000:]}") from exc
                time.sleep(0.01)
        os.set_blocking(fd, True)
        return os.fdopen(fd, "w")

    def wait_line(self, needle: str, timeout_s: float = 60.0) -> str:
        """The first line of stdout holding ``needle`` (AssertionError if none comes in time)."""
        end = time.monotonic() + timeout_s
        while True:
            done = self.exited()
            for line in self.stdout.splitlines():
                if needle in line:
                    return line
            if done or time.monotonic() > end:
                raise AssertionError(f"{self.argv[:4]} never printed {needle!r}: {self.stdout} {self.stderr}")
            time.sleep(0.02)

    def _read(self, path: str) -> str:
        try:
            with open(path, encoding="utf-8", errors="replace") as f:
                return f.read()
        except FileNotFoundError:
            return ""

    @property
    def stdout(self) -> str:
        return self._read(self._out)

    @property
    def stderr(self) -> str:
        return self._read(self._err)


class Forker:
    """A ``python -m tests.host.matrix_fork`` server (module docstring), started with ``python``
    (the interpreter) and ``cwd``/``env`` as the matrix starts its processes; its own output goes to
    ``tmp/matrix_fork.err``."""

    def __init__(self, python: str, cwd, env: dict, tmp) -> None:
        import subprocess
        self.tmp = tmp
        self._errpath = os.path.join(str(tmp), f"matrix_fork-{os.getpid()}.err")  # a server per worker
        self._errf = open(self._errpath, "w")
        self.p = subprocess.Popen([python, "-m", "tests.host.matrix_fork"], cwd=cwd, env=env, text=True,
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self._errf)
        self.cond = threading.Condition()
        self.exits: dict[str, int] = {}
        self.pids: dict[str, int] = {}
        self.ready = False
        self.gone = False
        self._n = 0
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()  # `run` waits for its READY: start it before what can run meanwhile

    def stderr_text(self) -> str:
        with open(self._errpath, encoding="utf-8", errors="replace") as f:
            return f.read()[-3000:]

    def _read(self) -> None:
        for line in self.p.stdout:
            word, _, rest = line.strip().partition(" ")
            with self.cond:
                if word == "READY":
                    self.ready = True
                elif word == "STARTED":
                    ident, pid = rest.split()
                    self.pids[ident] = int(pid)
                elif word == "EXIT":
                    ident, status = rest.split()
                    self.exits[ident] = int(status)
                self.cond.notify_all()
        with self.cond:
            self.gone = True
            self.cond.notify_all()

    def run(self, name: str, argv: list[str], *, sheet: bool = False, tmp=None, stdin_fifo: bool = False) -> Forked:
        """Fork ``capsheet ARGV`` (with ``sheet``: tests/host/matrix_sheet.py's ``ARGV``, a sheet
        and the command after its ``--`` in one process); its stdout and stderr go to
        ``TMP/NAME.out`` and ``TMP/NAME.err`` (``tmp`` default: the server's)."""
        with self.cond:
            if not self.cond.wait_for(lambda: self.ready or self.gone, 120) or not self.ready:
                raise RuntimeError(f"matrix_fork did not start: {self.stderr_text()}")
        self._n += 1
        ident = f"{self._n}-{name}"
        out, err = (os.path.join(str(tmp or self.tmp), f"{name}.{x}") for x in ("out", "err"))
        fifo = None
        if stdin_fifo:
            fifo = os.path.join(str(tmp or self.tmp), f"{name}.in")
            os.mkfifo(fifo)
        self.p.stdin.write(f"RUN {ident} " + json.dumps({"argv": argv, "out": out, "err": err, "sheet": sheet,
                                                          "in": fifo}) + "\n")
        self.p.stdin.flush()
        return Forked(self, ident, argv, out, err, fifo)

    def alive(self) -> bool:
        return not self.gone and self.p.poll() is None

    def close(self) -> None:
        """Stop taking commands; the server ends once its children have (the test waited for them)."""
        try:
            self.p.stdin.close()
        except OSError:
            pass
        try:
            self.p.wait(30)
        except Exception:  # noqa: BLE001 - a server that hangs is killed
            self.p.kill()
            self.p.wait(10)
        self._reader.join(10)
        self._errf.close()
