"""Software in the loop: the host's back-to-back suite (tests/test_host_back2back.py) run
unchanged against a virtual sheet whose every chip is the C reference firmware
(`firmware_ref.chip.CFirmwareChip`, what ``capsheet virtual --firmware c`` uses)."""

from __future__ import annotations

import functools

import pytest

pytest.importorskip("firmware_ref._capsheet_fw", reason="C firmware extension not built")
from firmware_ref.chip import CFirmwareChip  # noqa: E402

import tests.host.test_back2back as base  # noqa: E402
from tests.host.test_back2back import rig_factory  # noqa: E402,F401  (the suite's fixture)
from virtual_sheet.sheet import VirtualSheet  # noqa: E402


@pytest.fixture(autouse=True)
def _c_firmware_chips(monkeypatch):
    monkeypatch.setattr(base, "VirtualSheet", functools.partial(VirtualSheet, chip_factory=CFirmwareChip))


def test_the_suite_really_runs_the_c_firmware(rig_factory):  # noqa: F811
    rig = rig_factory("memory")
    assert all(isinstance(c, CFirmwareChip) for c in rig.sheet.chips)


# every test of the host's suite, collected again here with C chips
for _name in dir(base):
    if _name.startswith("test_"):
        globals()[_name] = getattr(base, _name)
del _name
