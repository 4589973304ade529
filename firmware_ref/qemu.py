"""The reference firmware on an emulated Cortex-M: build it, boot it in QEMU, hold it to the spec.

``python -m firmware_ref.qemu build [--mutant M] [--sensors S]`` builds ``firmware_ref/build/qemu/*.elf``
(``make -C firmware_ref qemu``; ``--sensors accel+gyro`` or ``accel+gyro+mag``: a 6/9-axis chip, docs
§16). ``python -m firmware_ref.qemu conformance [--runs N] [--mutant M] [--sensors S]``
boots a fresh QEMU ``mps2-an385`` per run with UART0 on a TCP chardev (QEMU is the server and waits
for the client: the boot ANNOUNCE is not lost) and runs ``capsheet conformance --port
socket://127.0.0.1:PORT`` against it; the exit status is the first non-zero one of the runs (1: a
check failed). ``--json`` prints one JSON object (runs, outcomes, durations, stack high-water) on
stdout. `QemuChip` is the same as a context manager, for tests.

The stack high-water mark is read after a run through QEMU's monitor (a Unix socket): the startup
code paints the stack with 0xDEADBEEF; the deepest word no longer painted is the high-water mark.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["QEMU", "ARM_CC", "missing_tools", "build", "QemuChip", "main"]

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
QEMU = os.environ.get("QEMU", "qemu-system-arm")
ARM_CC = os.environ.get("ARM_CC", "arm-none-eabi-gcc")
def _mutants() -> tuple[str, ...]:
    """The mutant builds: every ``capsheet_mutant_t`` of the header (the library's test build), and
    ``slow_clock`` (the port's clock at half speed)."""
    names = re.findall(r"^\s*CAPSHEET_MUT_([A-Z0-9_]+)", (HERE / "include" / "capsheet_fw.h").read_text(), re.M)
    return tuple(n.lower() for n in names if n not in ("NONE", "COUNT")) + ("slow_clock",)


MUTANTS = _mutants()
#: the port's sensor builds (``make -C firmware_ref qemu SENSORS=...``) and their ELF name suffix
SENSORS = {"accel": "", "accel+gyro": "_6axis", "accel+gyro+mag": "_9axis"}
STACK_PAINT = 0xDEADBEEF


def missing_tools() -> str | None:
    """None if QEMU and the Arm toolchain (with newlib) are installed, else why not (one line)."""
    missing = [t for t in (QEMU, ARM_CC) if shutil.which(t) is None]
    if missing:
        return (f"not installed: {', '.join(missing)} (apt-get install --no-install-recommends qemu-system-arm "
                f"gcc-arm-none-eabi libnewlib-arm-none-eabi)")
    probe = subprocess.run([ARM_CC, "--specs=nano.specs", "-print-file-name=libc_nano.a"], capture_output=True,
                           text=True)
    if probe.returncode != 0 or not Path(probe.stdout.strip()).is_file():
        return "newlib for arm-none-eabi is not installed (apt-get install libnewlib-arm-none-eabi)"
    return None


def elf_path(mutant: str | None = None, out: Path | None = None, sensors: str = "accel") -> Path:
    base = Path(out) if out is not None else HERE / "build"
    return base / "qemu" / (f"capsheet_mps2{SENSORS[sensors]}" + (f"_{mutant}" if mutant else "") + ".elf")


def build(mutant: str | None = None, *, out: Path | None = None, quiet: bool = True, sensors: str = "accel") -> Path:
    """``make -C firmware_ref qemu [MUTANT=...] [SENSORS=...] [OUT=...]``; returns the ELF. RuntimeError on
    failure."""
    if mutant is not None and mutant not in MUTANTS:
        raise ValueError(f"Invalid mutant {mutant!r} (known: {', '.join(MUTANTS)})")
    if sensors not in SENSORS:
        raise ValueError(f"Invalid sensors {sensors!r} (known: {', '.join(SENSORS)})")
    cmd = ["make", "-s", "-C", str(HERE), "qemu", f"SENSORS={sensors}"] + ([f"MUTANT={mutant}"] if mutant else []) + \
        ([f"OUT={Path(out).resolve()}"] if out is not None else [])
    r = subprocess.run(cmd, capture_output=quiet, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {(r.stderr or r.stdout or '').strip()[-2000:]}")
    return elf_path(mutant, out, sensors)


def _symbol(elf: Path, name: str) -> int:
    nm = shutil.which("arm-none-eabi-nm") or "arm-none-eabi-nm"
    out = subprocess.run([nm, str(elf)], capture_output=True, text=True, check=True).stdout
    m = re.search(rf"^([0-9a-fA-F]+) \w {re.escape(name)}$", out, re.M)
    if not m:
        raise RuntimeError(f"symbol {name} not in {elf}")
    return int(m.group(1), 16)


class QemuChip:
    """One QEMU mps2-an385 running the firmware; ``url`` is the pyserial URL of its UART0.

    Use as a context manager; QEMU is killed (by its pid) on exit. ``boot_timeout_s`` bounds the
    wait for QEMU to listen on its TCP port.
    """

    def __init__(self, elf: Path | None = None, *, boot_timeout_s: float = 20.0) -> None:
        self.elf = Path(elf) if elf is not None else elf_path()
        if not self.elf.is_file():
            raise FileNotFoundError(f"{self.elf} not built (make firmware-qemu)")
        self.boot_timeout_s = boot_timeout_s
        self.proc: subprocess.Popen | None = None
        self._dir = tempfile.mkdtemp(prefix="capsheet-qemu-")
        self.monitor_path = os.path.join(self._dir, "monitor.sock")
        self.url = ""

    def start(self) -> "QemuChip":
        with socket.socket() as s:  # a free port; QEMU binds it right after (a tiny window, retried below)
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        cmd = [QEMU, "-M", "mps2-an385", "-nographic", "-no-reboot",
               "-chardev", f"socket,id=uart0,host=127.0.0.1,port={port},server=on,wait=on,nodelay=on",
               "-serial", "chardev:uart0", "-monitor", f"unix:{self.monitor_path},server=on,wait=off",
               "-kernel", str(self.elf)]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True)
        # QEMU says on stderr when it listens ("QEMU waiting for connection on: ...")
        deadline = time.monotonic() + self.boot_timeout_s
        lines = []
        while time.monotonic() < deadline:
            line = self.proc.stderr.readline()
            if not line:
                break
            lines.append(line.strip())
            if "waiting for connection" in line:
                self.url = f"socket://127.0.0.1:{port}"
                return self
        self.stop()
        raise RuntimeError(f"QEMU did not start listening: {' | '.join(lines)[-500:]}")

    def monitor(self, command: str, timeout_s: float = 5.0) -> str:
        """One QEMU monitor command; its output."""
        with socket.socket(socket.AF_UNIX) as s:
            s.settimeout(timeout_s)
            s.connect(self.monitor_path)
            buf = b""
            while not buf.endswith(b"(qemu) "):
                buf += s.recv(65536)
            s.sendall(command.encode() + b"\n")
            buf = b""
            while not buf.endswith(b"(qemu) "):
                chunk = s.recv(65536)
                if not chunk:
                    break
                buf += chunk
        return buf.decode(errors="replace")

    def stack_high_water(self) -> int:
        """Bytes of stack ever used (from the unpainted words at the bottom of the painted region)."""
        bottom, top = _symbol(self.elf, "__stack_bottom"), _symbol(self.elf, "__stack_top")
        words = (top - bottom) // 4
        out = self.monitor(f"xp /{words}wx 0x{bottom:x}")
        values = [int(v, 16) for v in re.findall(r"0x([0-9a-fA-F]{8})(?!:)", out.split("\n", 1)[1])]
        values = values[:words]
        untouched = 0
        for v in values:
            if v != STACK_PAINT:
                break
            untouched += 1
        return (words - untouched) * 4

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(timeout=10)
        if self.proc is not None and self.proc.stderr is not None:
            self.proc.stderr.close()
        shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self) -> "QemuChip":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _conformance(url: str, extra: list[str]) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "host.cli", "conformance", "--port", url] + extra
    return subprocess.run(cmd, capture_output=True, text=True, cwd=str(ROOT))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m firmware_ref.qemu", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build", help="build the QEMU image (make -C firmware_ref qemu)")
    b.add_argument("--mutant", choices=MUTANTS)
    c = sub.add_parser("conformance", help="boot QEMU and run capsheet conformance against it")
    c.add_argument("--runs", type=int, default=1, help="consecutive runs, each on a fresh QEMU (default 1)")
    c.add_argument("--mutant", choices=MUTANTS, help="a deliberately broken build (the suite must fail it)")
    for q in (b, c):
        q.add_argument("--sensors", choices=tuple(SENSORS), default="accel",
                       help="the chip's sensors (docs/protocol.md §16): accel (default), or a 6/9-axis chip")
    c.add_argument("--json", action="store_true", help="print one JSON summary on stdout (run logs to stderr)")
    for q in (b, c):
        q.add_argument("--out", type=Path, default=None, help="build directory (default firmware_ref/build)")
    c.add_argument("extra", nargs=argparse.REMAINDER, help="passed to capsheet conformance (after --)")
    args = p.parse_args(argv)
    why = missing_tools()
    if why:
        print(f"firmware_ref.qemu: SKIPPED: {why}", file=sys.stderr)
        return 2
    try:
        elf = build(args.mutant, out=args.out, sensors=args.sensors)
    except RuntimeError as exc:
        print(f"firmware_ref.qemu: {exc}", file=sys.stderr)
        return 2
    if args.cmd == "build":
        print(elf)
        return 0
    if args.runs < 1:
        print(f"firmware_ref.qemu: Invalid --runs {args.runs} (need >= 1)", file=sys.stderr)
        return 2
    extra = [a for a in args.extra if a != "--"]
    log = sys.stderr if args.json else sys.stdout
    runs, first_bad = [], 0
    for i in range(args.runs):
        t0 = time.monotonic()
        with QemuChip(elf) as q:
            r = _conformance(q.url, extra)
            stack = q.stack_high_water()
        dt = time.monotonic() - t0
        last = (r.stdout.strip().splitlines() or [""])[-1]
        print(f"run {i + 1}/{args.runs}: exit {r.returncode}, {dt:.1f} s, stack high-water {stack} B: {last}",
              file=log, flush=True)
        if r.returncode != 0:
            print(r.stdout + r.stderr, file=log)
            first_bad = first_bad or r.returncode
        runs.append({"exit": r.returncode, "seconds": round(dt, 2), "stack_high_water_bytes": stack,
                     "summary": last,
                     "failed": [ln for ln in r.stdout.splitlines() if ln.startswith(("FAIL", "LOST"))],
                     "passed": [int(ln.split()[1]) for ln in r.stdout.splitlines() if ln.startswith("PASS")],
                     "skipped": [ln for ln in r.stdout.splitlines() if ln.startswith("SKIP")]})
    if args.json:
        print(json.dumps({"elf": str(elf), "mutant": args.mutant, "sensors": args.sensors, "runs": len(runs),
                          "passed": sum(x["exit"] == 0 for x in runs),
                          "stack_high_water_bytes_max": max(x["stack_high_water_bytes"] for x in runs),
                          "seconds_max": max(x["seconds"] for x in runs), "per_run": runs}))
    return first_bad


if __name__ == "__main__":
    sys.exit(main())
