"""`capsheet conformance` against the C firmware (cffi) built as a 6-axis and a 9-axis chip, behind a
virtual sheet at rest, serial and classic CAN: every check of the chip profile passes, the §16 checks
42-44 among them — run, not skipped — and the command line says so over a real pty. The sheet's IMU
models feed the firmware's read_imu as they feed the Python chip model.

The whole-profile runs are on the simulated clock (`host.conformance.simulated`: the C chip is driven
by the ``now`` it is given, as on a virtual sheet's thread): their subject is the firmware's §16
behaviour, and the same firmware's real-time runs over a real pty and a python-can bus are
tests/host/conformance/test_checks.py's (every check, accelerometer chips), this file's command line
run (a 6-axis chip's §16 checks over a pty) and test_qemu.py's."""

from __future__ import annotations

import re

import pytest

from host.cli import main
from host.conformance import CHECKS
from tests.host.conformance.test_checks import _run_simulated
from virtual_sheet.devices import PtyDevice
from virtual_sheet.sheet import VirtualSheet

pytest.importorskip("firmware_ref._capsheet_fw", reason="C firmware extension not built")
from firmware_ref.chip import CFirmwareChip  # noqa: E402

#: the chip profile's §16 checks (6/9-axis chips); 44 is classic CAN's (46, §16.5, is a gateway's)
IMU_CHECKS = {c.number for c in CHECKS if c.clauses[0].startswith("16") and "chip" in c.profiles}
assert IMU_CHECKS == {42, 43, 44}


RUNS = [("serial", "accel+gyro"), ("serial", "accel+gyro+mag"), ("can", "accel+gyro"), ("can", "accel+gyro+mag")]


@pytest.mark.parametrize("transport, sensors", RUNS)
def test_the_c_firmware_as_a_6_or_9_axis_chip_passes_every_check(transport, sensors):
    sheet = VirtualSheet("flat", "2x2", transport=transport, noise=0.5, sensors=sensors, chip_factory=CFirmwareChip)
    results = _run_simulated(sheet, allow_broadcast=True)
    assert sheet.engine_name == "chips" and sheet.chip_factory is CFirmwareChip
    report = "\n".join(r.line() for r in results)
    assert [r for r in results if r.outcome != "PASS"] == [], report
    ran = {r.number for r in results}
    assert ran & IMU_CHECKS == (IMU_CHECKS if transport == "can" else IMU_CHECKS - {44}), report
    # the records check saw the format the sensors make (9-axis: a magnetometer)
    rec = next(r for r in results if r.number == 43)
    assert f"records of format {2 if sensors.endswith('mag') else 1}" in rec.detail, report
    assert ("mag (" in rec.detail) == sensors.endswith("mag"), report


def test_the_command_line_passes_a_6_axis_c_chip_on_a_pty(capsys):
    sheet = VirtualSheet("flat", "2x2", noise=0.5, sensors="accel+gyro", chip_factory=CFirmwareChip)
    with PtyDevice(sheet) as dev:
        code = main(["conformance", "--port", str(dev.path), "--timeout", "0.3", "--only", "§16"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert re.search(r"^PASS\s+42\s+§16\.2", out, re.M) and re.search(r"^PASS\s+43\s+§16\.3", out, re.M), out
    assert not re.search(r"^(FAIL|SKIP)\s+4[23]\b", out, re.M), out
