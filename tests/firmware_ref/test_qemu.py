"""The reference firmware on an emulated Cortex-M: the unmodified src/ built for QEMU mps2-an385
(firmware_ref/ports/qemu-mps2/), booted with its UART on a TCP chardev, and held to the whole
conformance suite — as an accelerometer chip and as a 6-axis and a 9-axis chip (SENSORS=..., docs
§16: checks 42 and 43 run and pass; 44 is classic CAN's, and the port is a serial chip); its
compile-time mutants fail exactly their checks. Skipped, with the reason, where qemu-system-arm or
the Arm toolchain is not installed."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from firmware_ref.qemu import QemuChip, build, elf_path, missing_tools
from protocol.framing import StreamDecoder, encode
from protocol.messages import Announce, Info, provisional_node
from tests.shared_runs import session_root, shared_runs

WHY = missing_tools()
pytestmark = pytest.mark.skipif(WHY is not None, reason=f"QEMU conformance: {WHY}")

UID = 0x0123456789ABCDEF  # CAPSHEET_QEMU_UID, the port's default


#: the runs the tests below look at: (mutant, sensors). The first, the healthy accelerometer chip, runs
#: through the command line end to end (``python -m firmware_ref.qemu conformance --json``: the build,
#: QEMU, ``capsheet conformance`` in a process of its own); the others the same way but for the first
#: interpreter: built, booted and read from the test's process (`_one_process_less`)
SUITES = [(None, None), (None, "accel+gyro"), (None, "accel+gyro+mag"), ("dead_sensor", None), ("wrong_crc", None),
          ("frozen_sample", None), ("slow_clock", None)]


def _out(root, mutant, sensors):
    return root / f"qemu-{mutant or 'healthy'}-{sensors or 'accel'}"


def _cli(out, mutant, sensors) -> list:
    """``python -m firmware_ref.qemu conformance --json``: ``[exit status, stdout, stderr]``."""
    cmd = [sys.executable, "-m", "firmware_ref.qemu", "conformance", "--json", "--out", str(out)]
    cmd += (["--mutant", mutant] if mutant else []) + (["--sensors", sensors] if sensors else [])
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        stdout, stderr = p.communicate(timeout=300)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait(10)
    return [p.returncode, stdout, stderr]


def _one_process_less(out, mutant, sensors) -> list:
    """What `_cli` gives, without its first interpreter: the image built as the command builds it
    (`build`), booted in QEMU (`QemuChip`) from here, ``capsheet conformance`` in a process of its own
    against QEMU's UART (as the command runs it: each suite's timing checks in a process of their own,
    with no other suite's threads beside them), the stack high-water read from QEMU's monitor, and the
    report the command's --json, from the same lines."""
    try:
        elf = build(mutant, out=out, sensors=sensors or "accel")
    except RuntimeError as exc:
        return [2, "", f"firmware_ref.qemu: {exc}"]
    t0 = time.monotonic()
    with QemuChip(elf) as q:
        r = subprocess.run([sys.executable, "-m", "host.cli", "conformance", "--port", q.url],
                           capture_output=True, text=True, timeout=300)
        stack = q.stack_high_water()
    lines = r.stdout.splitlines()
    run = {"exit": r.returncode, "seconds": round(time.monotonic() - t0, 2), "stack_high_water_bytes": stack,
           "summary": (r.stdout.strip().splitlines() or [""])[-1],
           "failed": [ln for ln in lines if ln.startswith(("FAIL", "LOST"))],
           "passed": [int(ln.split()[1]) for ln in lines if ln.startswith("PASS")],
           "skipped": [ln for ln in lines if ln.startswith("SKIP")]}
    report = {"elf": str(elf), "mutant": mutant, "sensors": sensors or "accel", "runs": 1,
              "passed": int(r.returncode == 0), "stack_high_water_bytes_max": stack, "seconds_max": run["seconds"],
              "per_run": [run]}
    return [r.returncode, json.dumps(report), r.stdout + r.stderr]


@pytest.fixture(scope="module")
def suites(tmp_path_factory):
    """``{(mutant, sensors): (exit status, stdout, stderr)}``: every run started at once, each with its
    own build directory and QEMU. A run mostly waits for the emulated chip's heartbeats and silences
    (~14 s of wall for ~2 s of CPU): one after another they took ~90 s. Made once per test session,
    whichever workers need them splitting the runs (tests/shared_runs.py)."""
    root = session_root(tmp_path_factory)

    def job(mutant, sensors, _k):
        out = _out(root, mutant, sensors)
        out.mkdir(exist_ok=True)
        if (mutant, sensors) == SUITES[0]:
            return _cli(out, mutant, sensors)
        try:
            return _one_process_less(out, mutant, sensors)
        except Exception as exc:  # noqa: BLE001 - reported by the run's own test
            return [2, "", f"{type(exc).__name__}: {exc}"]
    runs = shared_runs(root, "qemu", {f"{m}/{s}": (lambda k, m=m, s=s: job(m, s, k)) for m, s in SUITES},
                       at_once=len(SUITES))
    return {(m, s): tuple(runs[f"{m}/{s}"]) for m, s in SUITES}


def test_boot_frames_are_byte_identical_to_the_python_encoder(suites, tmp_path_factory):
    """The healthy image the command line built (`suites`), booted again: its first frames."""
    import serial
    code, _out_text, err = suites[SUITES[0]]
    elf = elf_path(None, _out(session_root(tmp_path_factory), None, None))
    assert elf.is_file(), f"exit {code}: {err[-3000:]}"
    with QemuChip(elf) as q:
        port = serial.serial_for_url(q.url, timeout=0.1)
        data = b""
        deadline = time.monotonic() + 10
        while data.count(b"\x00") < 2 and time.monotonic() < deadline:
            data += port.read(64)
        port.close()
    node = provisional_node(UID, 0)
    ann, info = StreamDecoder().feed(data)[:2]
    assert ann == Announce(node, UID)
    assert isinstance(info, Info) and info.state == 0 and info.protocol_version == 1
    assert data.startswith(encode(ann) + encode(info))


def _suite(suites, mutant=None, sensors=None):
    code, out, err = suites[(mutant, sensors)]
    assert out.strip(), f"exit {code}, no report: {err[-3000:]}"
    return code, json.loads(out), err


def test_the_whole_suite_passes_against_the_firmware_in_qemu(suites):
    code, rep, log = _suite(suites)
    assert code == 0, log
    assert rep["passed"] == rep["runs"] == 1
    run = rep["per_run"][0]
    assert run["failed"] == [] and "0 failed" in run["summary"]
    assert 0 < rep["stack_high_water_bytes_max"] < 2048  # measured, within the port's 2 KiB stack


@pytest.mark.parametrize("sensors, fmt", [("accel+gyro", 1), ("accel+gyro+mag", 2)])
def test_the_firmware_in_qemu_passes_as_a_6_or_9_axis_chip(suites, sensors, fmt):
    code, rep, log = _suite(suites, sensors=sensors)
    assert code == 0, log
    assert rep["sensors"] == sensors and rep["elf"].endswith(f"_{3 + 3 * fmt}axis.elf")
    run = rep["per_run"][0]
    assert run["failed"] == [] and {42, 43, 45} <= set(run["passed"]), run  # 45: §17, v1.3
    assert not [ln for ln in run["skipped"] if " 42 " in ln or " 43 " in ln], run
    assert 0 < rep["stack_high_water_bytes_max"] < 2048


@pytest.mark.parametrize("mutant, expected", [("dead_sensor", {25, 26}), ("wrong_crc", {1, 39}),
                                              ("frozen_sample", {26}), ("slow_clock", {8, 9, 11})])
def test_a_c_mutant_fails_exactly_its_checks(suites, mutant, expected):
    code, rep, log = _suite(suites, mutant)
    assert code == 1, log
    failed = {int(line.split()[1]) for line in rep["per_run"][0]["failed"] if line.startswith("FAIL")}
    assert failed == expected, log
