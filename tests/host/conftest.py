"""Fixtures of the tests of host/: real recorded sessions, made once per module that uses them
(tests/host/record/test_replay.py, tests/host/cli/test_replay.py, tests/host/cli/test_estimate.py)."""

from __future__ import annotations

import pytest

_can_channel = iter(range(10_000))


@pytest.fixture(scope="module")
def pty_recording(tmp_path_factory):
    """A real session: the virtual 5x5 sheet on a pty, ``capsheet host --record``."""
    from host.cli import main
    from virtual_sheet.devices import PtyDevice
    from virtual_sheet.sheet import VirtualSheet

    from virtual_sheet.sensor import SensorModel

    d = tmp_path_factory.mktemp("pty")
    # chips with their own offsets and sensitivities: the replay must use the recorded calibration
    sheet = VirtualSheet("gaussian", "5x5", seed=5,
                         sensor=SensorModel(noise_pct_g=0.5, bias_counts=6.0, scale_error=0.02, chip_seed=3))
    layout = sheet.write_layout(d / "sheet.csv")
    out = d / "run.mcap"
    with PtyDevice(sheet) as dev:
        # a long deadline, as can_recording's: at load 10 the default one left 5x5 at 100 Hz below
        # --min-complete (exit 1), and what the tests read is the recording, not how late it came
        assert main(["host", "--port", dev.path, "--lattice", "5x5", "--layout", str(layout), "--rate", "100",
                     "--deadline-ms", "300", "--record", str(out), "--duration", "1.5", "-q"]) == 0
    return out


@pytest.fixture(scope="module")
def can_recording(tmp_path_factory):
    """A real session on two python-can virtual buses, recorded to MCAP and to three CAN logs."""
    from host.cli import main
    from virtual_sheet.devices import CanDevice
    from virtual_sheet.sheet import VirtualSheet

    d = tmp_path_factory.mktemp("can")
    sheet = VirtualSheet("gaussian", "4x4", seed=6, transport="can")
    layout = sheet.write_layout(d / "sheet.csv")
    n = next(_can_channel)
    chans = [f"rp_{n}_a", f"rp_{n}_b"]
    with CanDevice(sheet, n_buses=2, channels=chans) as dev:  # noqa: F841
        # a long deadline: counters complete even on a loaded machine (the test compares complete ones)
        argv = ["host", "--lattice", "4x4", "--layout", str(layout), "--rate", "50", "--duration", "0.8", "-q",
                "--deadline-ms", "300",
                "--record", str(d / "run.mcap"), "--can-log", str(d / "run.log")]
        for c in chans:
            argv += ["--can", f"virtual:{c}"]
        assert main(argv) == 0
    # the same frames through python-can's ASC and BLF writers
    import can
    frames = list(can.LogReader(str(d / "run.log")))
    for suffix in (".asc", ".blf"):
        with can.Logger(str(d / f"run{suffix}")) as w:
            for m in frames:
                w.on_message_received(can.Message(timestamp=m.timestamp, arbitration_id=m.arbitration_id,
                                                  is_extended_id=m.is_extended_id, data=m.data, is_fd=m.is_fd,
                                                  is_rx=m.is_rx, channel=int(m.channel.removeprefix("can"))))
    return d
