"""`capsheet conformance` against the C firmware (cffi) built as a 6-axis and a 9-axis chip, behind a
virtual sheet at rest on a real pty (serial) and a python-can virtual bus (classic CAN): every check
of the chip profile passes, the §16 checks 42-44 among them — run, not skipped — and the command line
says so. The sheet's IMU models feed the firmware's read_imu as they feed the Python chip model."""

from __future__ import annotations

import dataclasses
import re

import pytest

from host.cli import main
from host.conformance import CHECKS
from host.conformance.runner import CheckResult
from tests.host.conformance.test_checks import _run_can, _run_serial
from tests.shared_runs import session_root, shared_runs
from virtual_sheet.devices import PtyDevice
from virtual_sheet.sheet import VirtualSheet

pytest.importorskip("firmware_ref._capsheet_fw", reason="C firmware extension not built")
from firmware_ref.chip import CFirmwareChip  # noqa: E402

#: the chip profile's §16 checks (6/9-axis chips); 44 is classic CAN's (46, §16.5, is a gateway's)
IMU_CHECKS = {c.number for c in CHECKS if c.clauses[0].startswith("16") and "chip" in c.profiles}
assert IMU_CHECKS == {42, 43, 44}


RUNS = [("serial", "accel+gyro"), ("serial", "accel+gyro+mag"), ("can", "accel+gyro"), ("can", "accel+gyro+mag")]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """``{(transport, sensors): {"engine", "c_chip", "results"} or {"error"}}``: the four runs made at
    once in threads (each mostly waits: ~11.5 s of wall for ~0.3 s of CPU; one after another ~47 s),
    each C chip a struct of its own, each CAN run on a virtual channel of its own. Made once per test
    session, whichever workers need them splitting the runs (tests/shared_runs.py): each worker that
    reached this module made all four before."""
    def one(k):
        transport, sensors = RUNS[k]
        sheet = VirtualSheet("flat", "2x2", transport=transport, noise=0.5, sensors=sensors,
                             chip_factory=CFirmwareChip)
        try:
            if transport == "serial":
                results = _run_serial(sheet, allow_broadcast=True)
            else:
                results = _run_can(sheet, channel=f"cimu{k}", allow_broadcast=True)
        except Exception as exc:  # noqa: BLE001 - raised again by the run's own test
            return {"error": f"{type(exc).__name__}: {exc}"}
        return {"engine": sheet.engine_name, "c_chip": sheet.chip_factory is CFirmwareChip,
                "results": [dataclasses.asdict(r) for r in results]}
    got = shared_runs(session_root(tmp_path_factory), "c-imu", {"/".join(run): one for run in RUNS},
                      at_once=len(RUNS))
    return {run: got["/".join(run)] for run in RUNS}


@pytest.mark.parametrize("transport, sensors", RUNS)
def test_the_c_firmware_as_a_6_or_9_axis_chip_passes_every_check(transport, sensors, runs):
    run = runs[(transport, sensors)]
    if "error" in run:
        raise AssertionError(f"{transport}/{sensors}: the conformance run raised {run['error']}")
    assert run["engine"] == "chips" and run["c_chip"]
    results = [CheckResult(**r) for r in run["results"]]
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
