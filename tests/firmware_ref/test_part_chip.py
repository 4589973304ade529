"""C chips reading the ICM-42688-P through its driver, in the loop (firmware_ref/part_chip.py): the
sheet's truth -> the part's registers -> the C driver and glue -> the C chip -> the protocol.

In process (a gateway, simulated clock, exact counts; the conformance runs on the simulated clock
too, host/conformance/simulated.py) and end to end over a real pty through the command line (``capsheet virtual --firmware c --part icm42688p`` and ``capsheet host``). Expected
values: 1024 counts per g (docs/protocol.md §5.2) within the part's datasheet errors (zero-g offset
±20 mg, sensitivity ±0.5 %: DS-000347 §3.2 Table 2), the gyroscope at rest within its zero-rate
offset (±0.5 °/s, §3.1 Table 1) at 32.8 counts per °/s (±1000 °/s, §16.1)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from protocol.framing import StreamDecoder, encode
from protocol.messages import ConfigImu, ImuSample, Start, Sync
from virtual_sheet.gateway import Gateway
from virtual_sheet.sheet import VirtualSheet

part_chip = pytest.importorskip("firmware_ref.part_chip")
from host.cli.virtual import part_chip_factory  # noqa: E402 -- the firmware and the simulator meet in the CLI

G0 = 9.80665
INVALID, STALE = 0x8, 0x4   # docs/protocol.md §5.2


def stream(n_syncs: int = 60, *, fault_link: int | None = None, fault_at: int | None = None, fault="no_answer"):
    fac = part_chip_factory("icm42688p")
    sheet = VirtualSheet("gaussian", "3x3", seed=6, chip_factory=fac, sensors="accel+gyro")
    fac.bind(sheet)
    gw = Gateway(sheet, packed=False)
    gw.power_on(0.0)
    gw.pop_output(0.0)
    gw.commission(0.1, start=False)
    gw.feed(encode(ConfigImu(0, format=1, gyro_range=3)), 0.2)
    gw.feed(encode(Start(0)), 0.3)
    for t in np.arange(0.3, 2.0, 0.01):        # the chips' timers (the sensors came up at bind)
        gw.poll(float(t))
    gw.pop_output(2.0)
    for i in range(n_syncs):
        now = 2.0 + 0.01 * i
        if fault_link is not None and i == fault_at:
            fac.links[fault_link].part.fault(fault)   # the factory's links are in link order
        gw.feed(encode(Sync(counter=i)), now)
        gw.poll(now)
    msgs = StreamDecoder().feed(gw.pop_bytes(10.0))
    recs = [m for m in msgs if isinstance(m, ImuSample)]
    return sheet, fac, recs


def test_records_come_from_the_part_through_the_driver():
    sheet, fac, recs = stream()
    n = sheet.n_links
    assert len(recs) == 60 * n
    assert [ls.link for ls in fac.links] == list(range(n))
    assert all(ls.ls.imu.self_test == 0x7 for ls in fac.links)          # ran, gyroscope and accelerometer passed
    assert all(ls.part.transactions > 60 * 2 for ls in fac.links)       # every read went over the SPI bus
    ideal = sheet.specific_force(2.0) / G0 * 1024.0                        # counts per g at ±2 g (§5.2)
    by_node = {}
    for r in recs:
        by_node.setdefault(r.node, []).append(r)
    for node, rs in by_node.items():
        k = node - 1                                                     # commission: node = 1 + link
        a = np.array([(r.x, r.y, r.z) for r in rs], dtype=float).mean(axis=0)
        # zero-g offset ±20 mg (4 σ: 82 counts) and sensitivity ±0.5 % (4 σ: 21 counts at 1 g)
        assert np.all(np.abs(a - ideal[k]) < 82 + 21), (node, a, ideal[k])
        g = np.array([(r.gx, r.gy, r.gz) for r in rs], dtype=float).mean(axis=0)
        assert np.all(np.abs(g) < 4 * 0.5 * 32.8)                      # at rest: the zero-rate offset only
        assert all(r.status & ~STALE == 0 for r in rs)
        # the data-ready edge is the latch: within one ODR period (500 Hz at CONFIG's 145 Hz) before the SYNC
        assert all(-2100 <= r.time_us <= 0 for r in rs)


@pytest.mark.parametrize("fault", ["no_answer", "reset", "stuck_bus", "garbage"])
def test_a_part_lost_mid_stream_is_invalid_never_frozen(fault):
    sheet, fac, recs = stream(40, fault_link=4, fault_at=20, fault=fault)
    bad = [r for r in recs if r.node == 5]
    assert len(bad) == 40
    assert all(r.status & INVALID == 0 for r in bad[:20])
    assert all(r.status == INVALID and (r.x, r.y, r.z, r.gx, r.gy, r.gz) == (0,) * 6 for r in bad[20:])
    assert all(r.status & INVALID == 0 for r in recs if r.node != 5)    # nothing else lost


def test_a_part_failing_its_self_test_is_a_sensor_fault():
    fac = part_chip_factory("icm42688p")
    sheet = VirtualSheet("gaussian", "2x2", seed=6, chip_factory=fac, sensors="accel+gyro")
    fac.links[1].part.fault("self_test_fail")   # before the link MCUs boot (bind)
    fac.bind(sheet)
    gw = Gateway(sheet, packed=False)
    gw.power_on(0.0)
    gw.pop_output(0.0)
    gw.commission(0.1)
    for t in np.arange(0.1, 2.0, 0.01):
        gw.poll(float(t))
    gw.pop_output(2.0)
    gw.feed(encode(Sync(counter=1)), 2.0)
    msgs = StreamDecoder().feed(gw.pop_bytes(3.0))
    s = {m.node: m for m in msgs if type(m).__name__ == "Sample"}
    assert len(s) == sheet.n_links
    assert [n for n, m in sorted(s.items()) if m.status == INVALID] == [2]   # link 1: node 2 (commission)
    assert s[2].x == s[2].y == s[2].z == 0
    assert fac.links[1].ls.imu.error == -23                               # ICM42688P_ERR_SELF_TEST


def test_part_needs_the_c_firmware_and_a_6_axis_set():
    with pytest.raises(ValueError, match="Unknown part"):
        part_chip_factory("bmi270")
    fac = part_chip_factory("icm42688p")
    with pytest.raises(ValueError, match="a 6-axis part"):
        VirtualSheet("gaussian", "2x2", chip_factory=fac, sensors="accel+gyro+mag")


@pytest.mark.parametrize("part,sensors", [("icm42688p", "accel+gyro"), ("icm42688p+mmc5983ma", "accel+gyro+mag")])
def test_end_to_end_over_a_pty_through_the_command_line(tmp_path, part, sensors):
    """``capsheet virtual --firmware c --part ...`` (a 4x4 6- or 9-axis sheet) streams to ``capsheet host``
    over a real pty: every snapshot complete, every link sample with its gyroscope.

    What is delivered is under test, not how soon. The sheet's 24 C chips each read their part's
    register emulator in Python: the 9-axis sheet took 17-24 % of a core at 50 SYNC/s (11-12 % since the
    emulators were made cheaper: docs/benchmarks.md), and beside the suite's peaks (load 16 on two
    cores: 16 of these runs at once with two busy loops) it was starved of the CPU for longer than the
    host's default waits — links marked silent after 0.5 s, commands given up after 2.5 s — and, 16 at
    once at load 17, 2 s behind by the end of the run. So: a modest 25 SYNC/s; the host waits 4 s for a
    snapshot's links (``--deadline-ms 4000``, which its watchdog then waits out too, and so does the end
    of the run for the counters still open) and 1 s for each command's ACK (``--ack-timeout-ms 1000``);
    it is given the layout the sheet wrote, so its discovery ends once every chip answered (the command
    the sheet prints says ``--layout``). A snapshot that still lacks a link lost a frame, and fails."""
    from tests.host.cli.cli_runs import Virtual, host_json
    lay = tmp_path / "sheet.csv"
    v = Virtual("--lattice", "4x4", "--sensors", sensors, "--firmware", "c", "--part", part,
                "--symlink", str(tmp_path / "sheet"), "--layout-out", str(lay))
    cmd = list(v.host_cmd)
    cmd[cmd.index("--rate") + 1] = "25"
    assert cmd[cmd.index("--layout") + 1] == str(lay)  # the sheet's own layout: discovery ends early
    try:
        # a 5 s discovery window (answers after the default 0.5 s were seen beside busy loops),
        # which the layout ends as soon as every chip has answered
        out, doc = host_json(*cmd, "--duration", "4", "--deadline-ms", "4000", "--ack-timeout-ms", "1000",
                             "--discover-s", "5")
    finally:
        assert v.stop() == 0
    assert out.returncode == 0, out.stderr
    assert doc["waits"] == {"ack_timeout_ms": 1000.0, "watchdog_ms": 4000.0}, doc["waits"]
    s = doc["summary"]
    assert s["sensors"] == sensors and s["links"] == 24
    # the whole summary and the host's own lines on failure: beside two busy loops a run in the
    # suite lost whole snapshots (97 of 102 complete, none late) and pytest's short form hid why
    why = json.dumps(s) + "\n" + out.stderr[-3000:]
    assert s["snapshots"] > 0 and s["complete_snapshots"] == s["snapshots"] and s["late"] == 0, why
    assert s["missing_links"] == [] and s["valid_links_pct"] == 100.0, why
    assert s["imu_links_pct"] == pytest.approx(s["valid_links_pct"], abs=1e-6)
    assert s["errors"] == {}, s["errors"]


#: the conformance runs of `test_conformance_passes_a_healthy_part_and_reports_a_failed_one_as_a_sensor_fault`
PART_RUNS = [("serial", None), ("can", None), ("serial", "no_answer"), ("serial", "self_test_fail")]


@pytest.mark.parametrize("transport,fault", PART_RUNS)
def test_conformance_passes_a_healthy_part_and_reports_a_failed_one_as_a_sensor_fault(transport, fault):
    """`capsheet conformance`'s chip profile over serial and classic CAN: a chip reading a healthy part
    passes every check (the §16 ones among them); a part that stops answering, or fails its self-test,
    is the spec's sensor fault: the sample check sees INVALID while streaming (§8.6). On the simulated
    clock (the part, its driver and the C chip are driven by the ``now`` they are given): the subject is
    what the part makes of the chip's answers; the part over a real pty is the end-to-end run above."""
    from tests.host.conformance.test_checks import _run_simulated

    fac = part_chip_factory("icm42688p")
    sheet = VirtualSheet("flat", "2x2", noise=0.5, sensors="accel+gyro", chip_factory=fac, transport=transport)
    if fault is not None:
        for ls in fac.links:
            ls.part.fault(fault)
    fac.bind(sheet)
    results = _run_simulated(sheet, allow_broadcast=True)
    report = "\n".join(r.line() for r in results)
    failed = {r.number: r for r in results if r.outcome != "PASS"}
    if fault is None:
        assert failed == {}, report
        assert ({42, 43, 44} if transport == "can" else {42, 43}) <= {r.number for r in results}, report
    else:
        assert 25 in failed and "INVALID" in failed[25].detail, report


def test_an_accelerometer_only_chip_keeps_the_gyroscope_off():
    fac = part_chip_factory("icm42688p")
    sheet = VirtualSheet("gaussian", "2x2", seed=6, chip_factory=fac)   # sensors "accel"
    fac.bind(sheet)
    for ls in fac.links:
        assert ls.part.register(0, 0x4E) == 0x03    # PWR_MGMT0 (§14): accelerometer low noise, gyroscope off
        assert ls.ls.imu.self_test == 0x5           # ran; accelerometer passed; no gyroscope test


@pytest.mark.parametrize("args,needle", [
    (["--part", "icm42688p"], "--part icm42688p needs --firmware c"),
    (["--firmware", "c", "--part", "icm42688p", "--sensors", "accel+gyro+mag"], "a 6-axis part"),
    (["--firmware", "c", "--part", "icm42688p+mmc5983ma", "--sensors", "accel+gyro"], "accel+gyro+mag"),
    (["--firmware", "c", "--part", "bmi270"], "invalid choice: 'bmi270'"),
])
def test_bad_part_options_are_one_line_errors(args, needle):
    import subprocess
    import sys
    p = subprocess.run([sys.executable, "-m", "host.cli", "virtual", "--lattice", "2x2", "--duration", "0.1", *args],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert needle in p.stderr and "Traceback" not in p.stderr
    assert len([ln for ln in p.stderr.splitlines() if ln.startswith("capsheet virtual:")]) == 1


def test_nine_axis_records_carry_the_magnetometer_read_through_its_driver():
    """``icm42688p+mmc5983ma``: format-2 records whose magnetometer counts are the sheet's field in the
    link's frame (docs/protocol.md §16.1: 8192 counts per gauss at mag_range 0), read by the MMC5983MA
    driver on the same SPI bus: within 10° of the truth (the part's own offset and gain errors)."""
    fac = part_chip_factory("icm42688p+mmc5983ma")
    sheet = VirtualSheet("gaussian", "3x3", seed=4, chip_factory=fac, sensors="accel+gyro+mag")
    fac.bind(sheet)
    gw = Gateway(sheet, packed=False)
    gw.power_on(0.0)
    gw.pop_output(0.0)
    gw.commission(0.1, start=False)
    gw.feed(encode(ConfigImu(0, format=2, gyro_range=3, mag_range=0)), 0.2)
    gw.feed(encode(Start(0)), 0.3)
    gw.pop_output(1.0)
    for i in range(20):
        gw.feed(encode(Sync(counter=i)), 1.0 + 0.01 * i)
        gw.poll(1.0 + 0.01 * i)
    recs = [m for m in StreamDecoder().feed(gw.pop_bytes(5.0)) if isinstance(m, ImuSample)]
    assert len(recs) == 20 * sheet.n_links and all(r.status == 0 for r in recs)
    assert all(ls.mag_dev.error == 0 and ls.mag_dev.measurements >= 20 for ls in fac.links)   # read by its driver
    _f, _w, b = fac.truth.at(1.1)
    for r in recs[-sheet.n_links:]:
        m = np.array([r.mx, r.my, r.mz], dtype=float)
        t = b[r.node - 1] * 1e4 * 8192.0
        angle = np.degrees(np.arccos(np.dot(m, t) / np.linalg.norm(m) / np.linalg.norm(t)))
        assert angle < 10.0, (r.node, m, t)
