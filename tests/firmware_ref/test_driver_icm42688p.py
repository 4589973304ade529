"""The C ICM-42688-P driver (firmware_ref/drivers/icm42688p.c) and its link glue (link_sensors.c) in
SIL through cffi, against the register emulator (virtual_sheet.parts.icm42688p): probe, reset,
self-test, configuration, reads; every error path failing once; and the driver against deliberately
wrong emulators (bit order, read bit), which must fail.

Expected register values are typed from DS-000347 (§14: PWR_MGMT0 0x0F both sensors low noise;
GYRO_CONFIG0 0x26 = ±1000 °/s at 1 kHz; ACCEL_CONFIG0 0x66 = ±2 g at 1 kHz); counts from the
sensitivities of §3.1/§3.2 (16384 LSB/g at ±2 g; the protocol's ±2 g word, 1024 counts per g)."""

from __future__ import annotations

import pytest

from firmware_ref._ffi import ffi, lib
from firmware_ref.sil_bus import SilBus
from virtual_sheet.parts.icm42688p import ICM42688P

G0 = 9.80665
STALE = 0x4   # docs/protocol.md §5.2: SampleStatus bit 2


class Rig:
    """One part on chip select 0 of a SIL bus, and the driver (or the glue) over it."""

    def __init__(self, part: ICM42688P | None = None, *, self_test: bool = True, delay: bool = True,
                 glue: bool = False) -> None:
        self.part = part if part is not None else ICM42688P(seed=5)
        self.bus = SilBus(spi={0: self.part}, delay=delay)
        if glue:
            self.ls = ffi.new("capsheet_link_sensors_t *")
            assert lib.capsheet_link_sensors_init(self.ls, self.bus.c_bus, 0, ffi.NULL, ffi.NULL, self_test) == 0
            self.dev = ffi.addressof(self.ls, "imu")
        else:
            self.dev = ffi.new("icm42688p_t *")
            assert lib.icm42688p_init(self.dev, self.bus.c_bus, 0, self_test) == 0
        self.now = ffi.new("uint64_t *", 0)

    @property
    def now_us(self) -> int:
        return int(round(self.bus.now_s * 1e6))

    def run(self) -> int:
        self.now[0] = self.now_us
        return lib.icm42688p_run(self.dev, self.now)

    def tick(self, dt_s: float) -> None:
        """Time passes; a data-ready edge is timestamped, as a port's INT1 capture would."""
        self.bus.advance(self.bus.now_s + dt_s)
        if self.part.drdy_s is not None:
            lib.icm42688p_data_ready(self.dev, int(round(self.part.drdy_s * 1e6)))

    def read(self):
        s = ffi.new("icm42688p_sample_t *")
        rc = lib.icm42688p_read(self.dev, self.now_us, s)
        return rc, s


def reg(part: ICM42688P, addr: int) -> int:
    return part.register(0, addr)


def test_bring_up_probe_reset_self_test_configure():
    r = Rig()
    assert r.run() == 0
    assert r.dev.self_test == lib.ICM42688P_ST_RAN | lib.ICM42688P_ST_GYRO_PASS | lib.ICM42688P_ST_ACCEL_PASS
    assert (reg(r.part, 0x4E), reg(r.part, 0x4F), reg(r.part, 0x50)) == (0x0F, 0x26, 0x66)
    assert reg(r.part, 0x65) == 0x08          # DATA_RDY to INT1
    assert r.part.register(0, 0x70) == 0x00   # self-test off again
    assert r.part.bank == 0


def test_bring_up_without_delay_answers_how_long_to_wait():
    r = Rig(delay=False, self_test=False)
    waits = []
    for _ in range(10):
        rc = lib.icm42688p_step(r.dev, r.now_us)
        if rc <= 0:
            break
        waits.append(rc)
        r.bus.advance(r.bus.now_s + rc * 1e-6)
    assert rc == 0
    # power-up 1 ms, soft reset 1 ms (§14 DEVICE_CONFIG), gyroscope start-up 30 ms (§3.1 Table 1)
    assert waits == [1000, 1000, 30000]
    assert lib.icm42688p_run(r.dev, r.now) == lib.ICM42688P_ERR_ARGUMENT   # no delay_us: cannot block


def test_read_counts_freshness_and_latch():
    r = Rig()
    assert r.run() == 0                                # the self-test wants the part at rest
    r.part.set_motion([0, 0, G0], [0, 0, 0.5])
    r.tick(0.0025)
    rc, s = r.read()
    assert rc == 0 and s.fresh and not s.saturated
    assert abs(s.accel[2] - 16384) < 16384 * 0.1      # 1 g at ±2 g (§3.2 Table 2), within offset/scale error
    assert abs(s.gyro[2] - 0.5 * 57.29578 * 32.8) < 50  # 0.5 rad/s at ±1000 °/s: 32.8 LSB/(°/s)
    assert s.latch_known and s.latch_us == int(round(r.part.drdy_s * 1e6))
    assert s.latch_us <= r.now_us
    rc, s2 = r.read()                                  # no conversion since: not fresh
    assert rc == 0 and not s2.fresh


def test_saturation_is_reported():
    r = Rig(self_test=False)
    assert r.run() == 0
    r.part.set_motion([3 * G0, 0, 0], [0, 0, 0])
    r.tick(0.002)
    rc, s = r.read()
    assert rc == 0 and s.fresh and s.saturated and s.accel[0] == 32767


def test_configuration_change_waits_for_a_new_conversion():
    r = Rig(self_test=False)
    assert r.run() == 0
    r.tick(0.002)
    cfg = ffi.new("icm42688p_config_t *")
    lib.icm42688p_default_config(cfg)
    cfg.accel_fs_sel = 0                               # ±16 g
    assert lib.icm42688p_configure(r.dev, cfg) == 0
    assert lib.icm42688p_step(r.dev, r.now_us) >= 0
    assert reg(r.part, 0x50) == 0x06                   # ±16 g at 1 kHz
    rc, s = r.read()
    assert rc == 0 and not s.fresh                     # the DATA_RDY of the old range was cleared
    r.tick(0.0015)
    rc, s = r.read()
    assert rc == 0 and s.fresh and abs(s.accel[2] - 2048) < 2048 * 0.1   # 2048 LSB/g at ±16 g
    cfg.odr = 0                                        # reserved code
    assert lib.icm42688p_configure(r.dev, cfg) == lib.ICM42688P_ERR_ARGUMENT


# ---- every error path, once ---------------------------------------------------------------------

def test_bus_error_at_probe():
    part = ICM42688P(seed=5)
    part.fault("stuck_bus")
    r = Rig(part)
    assert r.run() == lib.ICM42688P_ERR_BUS
    assert r.bus.errors >= 1


def test_no_answer_at_probe_is_a_wrong_id():
    part = ICM42688P(seed=5)
    part.fault("no_answer")
    assert Rig(part).run() == lib.ICM42688P_ERR_WHO_AM_I


def test_wrong_who_am_i():
    part = ICM42688P(seed=5)
    part.fault("wrong_id")
    assert Rig(part).run() == lib.ICM42688P_ERR_WHO_AM_I


def test_failing_self_test():
    part = ICM42688P(seed=5)
    part.fault("self_test_fail")
    r = Rig(part)
    assert r.run() == lib.ICM42688P_ERR_SELF_TEST
    rc, _ = r.read()
    assert rc == lib.ICM42688P_ERR_SELF_TEST          # sticky


class NoResetDone(ICM42688P):
    """A part whose INT_STATUS never shows RESET_DONE (a reset that did not complete)."""

    def spi_transfer(self, tx: bytes) -> bytes:
        rx = super().spi_transfer(tx)
        if len(tx) == 2 and tx[0] == 0xAD:
            return bytes([rx[0], rx[1] & ~0x10])
        return rx


def test_reset_not_done():
    assert Rig(NoResetDone(seed=5)).run() == lib.ICM42688P_ERR_RESET


def test_read_before_bring_up():
    r = Rig(delay=False)
    rc, _ = r.read()
    assert rc == lib.ICM42688P_ERR_NOT_READY


@pytest.mark.parametrize("fault,error", [("reset", "ICM42688P_ERR_GONE"), ("no_answer", "ICM42688P_ERR_GONE"),
                                         ("stuck_bus", "ICM42688P_ERR_BUS"), ("garbage", "ICM42688P_ERR_GONE")])
def test_part_lost_mid_stream_fails_and_stays_failed(fault, error):
    r = Rig(self_test=False)
    assert r.run() == 0
    r.tick(0.002)
    assert r.read()[0] == 0
    r.part.fault(fault)
    r.tick(0.002)
    rc, s = r.read()
    assert rc == getattr(lib, error)
    r.part.fault(None)
    r.tick(0.002)
    assert r.read()[0] == getattr(lib, error)          # sticky: never a frozen value after


def test_part_that_stops_converting_is_gone_after_100_ms():
    r = Rig(self_test=False)
    assert r.run() == 0
    r.tick(0.002)
    assert r.read()[0] == 0
    r.part.spi_transfer(bytes([0x4E, 0x00]))          # sensors off behind the driver's back
    for _ in range(10):
        r.tick(0.009)
        assert r.read()[0] == 0                        # STALE for a while (not fresh) ...
    r.tick(0.020)
    assert r.read()[0] == lib.ICM42688P_ERR_GONE       # ... then a fault (§8.6)


# ---- deliberately wrong emulators ---------------------------------------------------------------

@pytest.mark.parametrize("miswire", ["bit_order", "read_bit"])
def test_driver_against_a_wrong_emulator_fails(miswire):
    assert Rig(ICM42688P(seed=5, miswire=miswire)).run() == lib.ICM42688P_ERR_WHO_AM_I


# ---- the glue: capsheet_hal_t read_axes / read_imu ----------------------------------------------

def read_axes(r: Rig):
    xyz = ffi.new("int16_t[3]")
    st = ffi.new("uint8_t *")
    rc = lib.capsheet_link_read_axes(r.ls, r.now_us, xyz, st)
    return rc, list(xyz), st[0]


def test_glue_reports_protocol_counts_stale_and_faults():
    r = Rig(glue=True, delay=False, self_test=False)
    r.part.set_motion([0, 0, G0], [0, 0, 0])
    rc, xyz, st = read_axes(r)
    assert rc == 0 and xyz == [0, 0, 0] and st == STALE
    for i in range(60):                                # the bring-up, driven by the reads themselves
        r.tick(0.001)
        rc, xyz, st = read_axes(r)
        assert rc == 0
        if i > 35 and st == 0:                         # running: a fresh conversion (ODR 500 Hz here)
            break
    assert st == 0 and abs(xyz[2] - 1024) < 1024 * 0.1   # the protocol's ±2 g word: 1024 counts per g
    rc, xyz2, st = read_axes(r)
    assert rc == 0 and st == STALE and xyz2 == xyz        # STALE: the last value again, flagged (§5.3)
    out = ffi.new("capsheet_imu_reading_t *")
    assert lib.capsheet_link_read_imu(r.ls, r.now_us, 3, 0, False, out) == 0
    r.part.fault("no_answer")
    r.tick(0.001)
    rc, _, _ = read_axes(r)
    assert rc < 0                                       # a sensor fault: the chip sends INVALID
    assert lib.capsheet_link_read_imu(r.ls, r.now_us, 3, 0, False, out) < 0


def test_glue_without_a_magnetometer_refuses_a_mag_read():
    r = Rig(glue=True, self_test=False)
    out = ffi.new("capsheet_imu_reading_t *")
    assert lib.capsheet_link_read_imu(r.ls, 0, 3, 0, True, out) < 0


# ---- the build: firmware_ref/Makefile's strict flags, 64-bit (cc) and 32-bit (arm-none-eabi-gcc) ----

def _strict_flags() -> list[str]:
    from pathlib import Path
    mk = Path(__file__).resolve().parents[2] / "firmware_ref" / "Makefile"
    line = next(ln for ln in mk.read_text().splitlines() if ln.startswith("STRICT"))
    return line.split(":=", 1)[1].split()


@pytest.mark.parametrize("cc,arch", [("cc", []), ("arm-none-eabi-gcc", ["-mcpu=cortex-m0plus", "-mthumb"])])
def test_drivers_build_warning_free_under_the_strict_flags(cc, arch, tmp_path):
    import shutil
    import subprocess
    from pathlib import Path
    if shutil.which(cc) is None:
        pytest.skip(f"{cc} not installed")
    fw = Path(__file__).resolve().parents[2] / "firmware_ref"
    for src in ("icm42688p.c", "link_sensors.c"):
        p = subprocess.run([cc, *arch, *_strict_flags(), "-O2", f"-I{fw / 'include'}", f"-I{fw / 'drivers'}", "-c",
                            str(fw / "drivers" / src), "-o", str(tmp_path / (src + ".o"))],
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == 0 and p.stderr == "", p.stderr


def test_glue_flags_self_test_while_it_runs_then_reads():
    r = Rig(glue=True, delay=False, self_test=True)
    seen = set()
    for _ in range(1500):                              # 1 ms main-loop steps through the bring-up
        r.tick(0.001)
        rc, xyz, st = read_axes(r)
        assert rc == 0
        seen.add(st)
    assert 0x2 | STALE in seen                         # SELF_TEST (§5.2 bit 1) while the self-test runs
    assert st == 0 and r.dev.self_test == 0x7         # then fresh readings, self-test passed


def test_a_part_answering_garbage_fails_at_the_first_read_never_a_reading():
    """Random MISO bytes (64 parts, seeded): the first read after is a fault for every one of them —
    INT_STATUS's flags alone would let about half of them through with a random 'reading'."""
    failed_first = 0
    for seed in range(64):
        r = Rig(ICM42688P(seed=seed), self_test=False)
        assert r.run() == 0
        r.tick(0.002)
        assert r.read()[0] == 0
        r.part.fault("garbage")
        r.tick(0.002)
        failed_first += r.read()[0] == lib.ICM42688P_ERR_GONE
    assert failed_first == 64
