"""`capsheet conformance` against both virtual chips (the Python model and the C firmware), on a
pty serial port and on a python-can virtual bus, through the virtual sheet's own devices — and
against a broken chip, which it must fail."""

from __future__ import annotations

import pytest

from host.cli import main
from host.conformance import CHECKS, CanLink, SerialLink, run_checks, summary
from virtual_sheet.chip import ChipModel
from virtual_sheet.devices import CanDevice, PtyDevice
from virtual_sheet.sheet import VirtualSheet


def _c_chip():
    pytest.importorskip("firmware_ref._capsheet_fw", reason="C firmware extension not built")
    from firmware_ref.chip import CFirmwareChip
    return CFirmwareChip


FACTORIES = {"python": lambda: ChipModel, "c": _c_chip}


@pytest.mark.parametrize("firmware", ["python", "c"])
@pytest.mark.parametrize("transport", ["serial", "can"])
def test_every_check_passes_on_a_virtual_chip(firmware, transport):
    sheet = VirtualSheet("flat", "2x2", transport=transport, chip_factory=FACTORIES[firmware]())
    lines = []

    class Out:
        def write(self, s):
            lines.append(s)

        def flush(self):
            pass

    if transport == "serial":
        with PtyDevice(sheet) as dev:
            link = SerialLink(str(dev.path)).start()
            try:
                results = run_checks(link, timeout_s=0.3, out=Out())
            finally:
                link.close()
    else:
        with CanDevice(sheet) as dev:
            link = CanLink(f"virtual:{dev.channels[0]}").start()
            try:
                results = run_checks(link, timeout_s=0.3, out=Out())
            finally:
                link.close()
    failed = [r for r in results if r.outcome != "PASS"]
    assert not failed, "".join(lines)
    # every check ran, except the other transport's own
    assert len(results) == len([c for c in CHECKS if c.transport in (None, transport)])
    assert summary(results).startswith(f"conformance: {len(results)} checks passed, 0 failed")


class OffByOneChip(ChipModel):
    """Answers SYNC with the wrong counter: a non-conforming device."""

    def handle(self, frame, now_s, decoded=None):
        from protocol.framing import decode_frame, encode
        from protocol.messages import Sample
        out = super().handle(frame, now_s, decoded)
        fixed = []
        for f in out:
            m = decode_frame(f[:-1])
            fixed.append(encode(Sample(m.node, (m.counter + 1) & 0xFFFF, m.x, m.y, m.z, m.status))
                         if isinstance(m, Sample) else f)
        return fixed


def test_a_non_conforming_chip_fails_and_the_command_exits_non_zero(capsys):
    sheet = VirtualSheet("flat", "2x2", transport="serial", chip_factory=OffByOneChip)
    with PtyDevice(sheet) as dev:
        code = main(["conformance", "--port", str(dev.path), "--timeout", "0.3", "--only", "5.1"])
    out = capsys.readouterr().out
    assert code == 1
    assert "FAIL" in out and "§5.1" in out and "answered with counter" in out
    assert "1 failed" in out


def test_list_and_usage_errors(capsys):
    assert main(["conformance", "--list"]) == 0
    out = capsys.readouterr().out
    assert all(f"{c.number:2d}  {c.clause}" in out for c in CHECKS)
    assert main(["conformance"]) == 2
    assert main(["conformance", "--port", "/nonexistent/tty"]) == 2
    assert "Cannot open serial port" in capsys.readouterr().err
