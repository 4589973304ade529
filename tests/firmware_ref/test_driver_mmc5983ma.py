"""The MMC5983MA C driver (firmware_ref/drivers/mmc5983ma.c) in SIL, against the register emulator.

The driver is compiled with cffi into a test module whose SPI bus is Python: every transaction goes
to `virtual_sheet.parts.mmc5983ma.MMC5983MA`, with bus time passing as a 10 MHz SPI clock would take
it. Expected counts are typed from docs/protocol.md §16.1 (``B · 32768 / (4 (r + 1))`` counts per
gauss), never computed by the driver; each error path is shown failing once, and emulators that
break the part's bus rules (bytes swapped, the read bit ignored or inverted) make the driver fail.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from virtual_sheet.parts.mmc5983ma import MMC5983MA

cffi = pytest.importorskip("cffi")

ROOT = Path(__file__).resolve().parents[2]
FW = ROOT / "firmware_ref"

# mmc5983ma.h's error codes
ERR_BUS, ERR_PRODUCT_ID, ERR_OTP, ERR_SELF_TEST = -40, -41, -42, -43
ERR_TIMEOUT, ERR_GONE, ERR_NOT_READY, ERR_ARGUMENT = -44, -45, -46, -47
SATURATED, STALE, INVALID = 0x1, 0x4, 0x8

CDEF = r"""
typedef struct {
    void *user;
    int32_t (*spi_transfer)(void *user, uint8_t cs, const uint8_t *tx, uint8_t *rx, size_t len);
    int32_t (*i2c_write_read)(void *user, uint8_t addr7, const uint8_t *tx, size_t tx_len, uint8_t *rx, size_t rx_len);
    void (*delay_us)(void *user, uint32_t us);
} capsheet_bus_t;
typedef struct {
    void *ctx;
    int32_t (*poll)(void *ctx, uint64_t now_us);
    int32_t (*read)(void *ctx, uint64_t now_us, uint8_t mag_range, int16_t mag[3], uint8_t *status);
} capsheet_mag_driver_t;
typedef struct {
    uint8_t phase;
    int32_t error;
    int32_t offset2[3];
    uint32_t measurements;
    uint8_t tout;
    ...;
} mmc5983ma_t;
int32_t mmc5983ma_init(mmc5983ma_t *d, const capsheet_bus_t *bus, uint8_t cs, uint8_t bw);
int32_t mmc5983ma_init_i2c(mmc5983ma_t *d, const capsheet_bus_t *bus, uint8_t addr7, uint8_t bw);
int32_t mmc5983ma_set_axes(mmc5983ma_t *d, const int8_t axes[3]);
int32_t mmc5983ma_step(mmc5983ma_t *d, uint64_t now_us);
int32_t mmc5983ma_run(mmc5983ma_t *d, uint64_t *now_us);
int32_t mmc5983ma_read(mmc5983ma_t *d, uint64_t now_us, uint8_t mag_range, int16_t mag[3], uint8_t *status,
                       uint64_t *latch_us);
int32_t mmc5983ma_temperature_dc(const mmc5983ma_t *d);
void mmc5983ma_mag_driver(mmc5983ma_t *d, capsheet_mag_driver_t *out);
extern "Python" int32_t sil_spi(void *, uint8_t, const uint8_t *, uint8_t *, size_t);
extern "Python" void sil_delay(void *, uint32_t);
extern "Python" int32_t sil_i2c(void *, uint8_t, const uint8_t *, size_t, uint8_t *, size_t);
"""


@pytest.fixture(scope="session")
def sil(tmp_path_factory):
    """The driver compiled for this test session, its bus routed to Python."""
    ffi = cffi.FFI()
    ffi.cdef(CDEF)
    ffi.set_source("_mmc5983ma_sil", '#include "mmc5983ma.h"\n',
                   sources=[str(FW / "drivers" / "mmc5983ma.c")],
                   include_dirs=[str(FW / "include"), str(FW / "drivers")],
                   extra_compile_args=["-std=c99", "-Wall", "-Wextra", "-Werror", "-Wconversion", "-Wsign-conversion"])
    out = tmp_path_factory.mktemp("mmc5983ma_sil")
    so = ffi.compile(tmpdir=str(out), verbose=False)
    spec = importlib.util.spec_from_file_location("_mmc5983ma_sil", so)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["_mmc5983ma_sil"] = mod
    spec.loader.exec_module(mod)

    @mod.ffi.def_extern()
    def sil_spi(user, cs, tx, rx, n):
        return mod.ffi.from_handle(user).spi(cs, bytes(mod.ffi.buffer(tx, n)), rx, n)

    @mod.ffi.def_extern()
    def sil_i2c(user, addr, tx, tx_len, rx, rx_len):
        return mod.ffi.from_handle(user).i2c(addr, bytes(mod.ffi.buffer(tx, tx_len)) if tx_len else b"", rx, rx_len)

    @mod.ffi.def_extern()
    def sil_delay(user, us):
        mod.ffi.from_handle(user).now_us += us

    return mod


class Rig:
    """One part on chip select 1 of a 10 MHz SPI bus whose time the driver's calls set."""

    SCK_HZ = 10e6

    def __init__(self, sil, part: MMC5983MA, *, bw: int = 1, delay: bool = False, cs: int = 1,
                 i2c_addr: int | None = None):
        self.sil, self.ffi, self.lib = sil, sil.ffi, sil.lib
        self.part = part
        self.now_us = 0.0
        self.fail_bus = False
        self.cs_seen: set[int] = set()
        self.transactions: list[bytes] = []
        self._h = self.ffi.new_handle(self)
        self.bus = self.ffi.new("capsheet_bus_t *")
        self.bus.user = self._h
        self.bus.spi_transfer = self.lib.sil_spi
        self.bus.i2c_write_read = self.lib.sil_i2c
        self.bus.delay_us = self.lib.sil_delay if delay else self.ffi.NULL
        self.dev = self.ffi.new("mmc5983ma_t *")
        if i2c_addr is None:
            assert self.lib.mmc5983ma_init(self.dev, self.bus, cs, bw) == 0
        else:
            assert self.lib.mmc5983ma_init_i2c(self.dev, self.bus, i2c_addr, bw) == 0
        self.i2c_seen: set[int] = set()

    def spi(self, cs, tx, rx, n):
        self.cs_seen.add(cs)
        if self.fail_bus:
            return -1
        self.part.advance(self.now_us / 1e6)
        self.transactions.append(tx)
        ans = self.part.spi_transfer(tx)
        self.ffi.memmove(rx, ans, n)
        self.now_us += n * 8 / self.SCK_HZ * 1e6 + 0.1  # the clocks, and CS high between transactions
        return 0

    def i2c(self, addr, tx, rx, n):
        """I2C at 400 kHz (DS p.3): 9 clocks a byte, the address byte twice (a repeated start)."""
        self.i2c_seen.add(addr)
        if self.fail_bus or addr != 0x30:
            return -1                                     # no acknowledge
        self.part.advance(self.now_us / 1e6)
        try:
            ans = self.part.i2c_write_read(tx, n)
        except RuntimeError:
            return -1
        if n:
            self.ffi.memmove(rx, ans, n)
        self.now_us += (len(tx) + n + 2) * 9 / 400e3 * 1e6
        return 0

    def at(self, t_us: float) -> int:
        self.now_us = max(self.now_us, t_us)
        return int(self.now_us)

    def step(self, t_us: float) -> int:
        return self.lib.mmc5983ma_step(self.dev, self.at(t_us))

    def bring_up(self, t_us: float = 0.0, limit: int = 200) -> tuple[int, float]:
        """Step until running (0) or failed (< 0); returns (the code, the time then)."""
        t = t_us
        for _ in range(limit):
            rc = self.step(t)
            if rc <= 0:
                return rc, self.now_us
            t = self.now_us + rc
        raise AssertionError("the bring-up never ended")

    def read(self, t_us: float, r: int = 0):
        mag = self.ffi.new("int16_t[3]")
        st = self.ffi.new("uint8_t *")
        latch = self.ffi.new("uint64_t *")
        rc = self.lib.mmc5983ma_read(self.dev, self.at(t_us), r, mag, st, latch)
        return rc, tuple(mag), st[0], latch[0]


def ideal(seed=3, **kw) -> MMC5983MA:
    """A part exactly at its nominal figures, but for a bridge offset (removed by SET/RESET)."""
    kw.setdefault("offset_g", [0.1, -0.2, 0.05])
    return MMC5983MA(seed=seed, clock_error=0.0, gain=[1, 1, 1], cross=[[0] * 3] * 3, noise=False, **kw)


def running(sil, part=None, **kw) -> Rig:
    rig = Rig(sil, part if part is not None else ideal(), **kw)
    rc, _ = rig.bring_up()
    assert rc == 0, rc
    return rig


EARTH_T = (20e-6, -5e-6, 45e-6)  # 0.2, -0.05, 0.45 gauss


def settle(rig, field_t, t_us, r=0):
    """Feel `field_t` from t_us on; two reads 10 ms apart (the first starts a measurement with it)."""
    rig.part.set_field(field_t)
    rig.read(t_us, r)
    return rig.read(t_us + 10_000, r)


# ---------------------------------------------------------------------------------- a healthy part
def test_bring_up_then_counts_at_every_range_typed_from_the_protocol(sil):
    rig = running(sil)
    # 0.2 G, -0.05 G, 0.45 G at 8192 / 4096 / 2730.67 / 2048 counts per gauss (§16.1), ±1 count for
    # the 18-bit quantisation of the two SET/RESET outputs the offset comes from
    expected = {0: (1638, -410, 3686), 1: (819, -205, 1843), 2: (546, -137, 1229), 3: (410, -102, 922)}
    t = 60_000
    for r, want in expected.items():
        rc, mag, st, _ = settle(rig, EARTH_T, t, r)
        assert rc == 0 and st == 0
        assert all(abs(m - w) <= 1 for m, w in zip(mag, want)), (r, mag, want)
        t += 30_000


def test_the_bridge_offset_is_measured_by_set_and_reset_and_removed(sil):
    rig = running(sil)
    # offset 0.1, -0.2, 0.05 G = 1638.4, -3276.8, 819.2 counts of 18 bits; offset2 holds twice that
    assert [abs(o - w) <= 2 for o, w in zip(rig.dev.offset2, (3277, -6554, 1638))] == [True] * 3
    rc, mag, _, _ = settle(rig, (0.0, 0.0, 0.0), 60_000)
    assert rc == 0 and all(abs(m) <= 1 for m in mag)
    # without the SET/RESET offset the zero field would read 0.1 G = 819 counts on x
    assert rig.part.events.sets >= 2 and rig.part.events.resets == 1


def test_saturation_is_sent_at_the_rail_and_flagged(sil):
    rig = running(sil)
    rc, mag, st, _ = settle(rig, (5e-4, -5e-4, 0.0), 60_000, r=0)  # ±5 G at ±4 G
    assert rc == 0 and mag[:2] == (32767, -32768) and st & SATURATED
    rc, mag, st, _ = settle(rig, (5e-4, -5e-4, 0.0), 90_000, r=1)  # ±5 G at ±8 G: 20480 counts
    assert rc == 0 and st == 0 and abs(mag[0] - 20480) <= 1 and abs(mag[1] + 20480) <= 1
    # 9 G is past the part's own ±8 G (its output at the 18-bit rail): the rail at ±16 G too
    rc, mag, st, _ = settle(rig, (9e-4, -9e-4, 0.0), 120_000, r=3)
    assert rc == 0 and mag[:2] == (32767, -32768) and st & SATURATED


def test_a_measurement_in_flight_repeats_the_last_output_without_stale(sil):
    rig = running(sil, bw=1)  # 4 ms measurements
    settle(rig, EARTH_T, 60_000)
    rc, mag, st, latch = rig.read(80_000)           # takes the earth field's measurement, starts one
    rig.part.set_field((0.0, 0.0, 0.0))             # felt from 80 ms on: by the measurement in flight
    assert rc == 0 and abs(mag[0] - 1638) <= 1 and not st & STALE
    rc, mag2, st, latch2 = rig.read(81_000)         # 1 ms later: still converting
    assert rc == 0 and mag2 == mag and latch2 == latch and not st & STALE
    rc, mag3, st, latch3 = rig.read(84_500)         # 4.5 ms after the start: the zero field
    assert rc == 0 and all(abs(m) <= 1 for m in mag3)
    # the instant is the middle of the 4 ms window that started at the 80 ms read
    assert 80_000 + 2_000 <= latch3 <= 80_000 + 2_000 + 5


def test_the_sample_instant_follows_the_bandwidth_code(sil):
    for bw, half_us in ((0, 4_000), (2, 1_000), (3, 250)):
        rig = running(sil, bw=bw)
        rig.read(60_000)
        rc, _, _, latch = rig.read(70_000)
        assert rc == 0 and 60_000 + half_us <= latch <= 60_000 + half_us + 5, (bw, latch)


def test_axes_follow_the_mounting(sil):
    rig = running(sil)
    axes = sil.ffi.new("int8_t[3]", [2, -1, 3])
    assert sil.lib.mmc5983ma_set_axes(rig.dev, axes) == 0
    rc, mag, _, _ = settle(rig, EARTH_T, 60_000)
    assert rc == 0 and abs(mag[0] + 410) <= 1 and abs(mag[1] + 1638) <= 1 and abs(mag[2] - 3686) <= 1
    bad = sil.ffi.new("int8_t[3]", [1, -1, 3])
    assert sil.lib.mmc5983ma_set_axes(rig.dev, bad) == ERR_ARGUMENT


def test_the_bring_up_waits_the_datasheet_times_and_misuses_nothing(sil):
    rig = Rig(sil, ideal(), bw=1)
    rc, t_end = rig.bring_up()
    assert rc == 0
    ev = rig.part.events
    # 10 ms power-on, 10 ms after SW_RST (DS p.15; each waited 20 % longer: the datasheet's times are
    # typical), SET measurement, RESET measurement, TM_T (4 ms each at BW 01, p.15)
    assert 12_000 + 12_000 + 3 * 4_000 <= t_end <= 12_000 + 12_000 + 3 * 4_000 + 100
    for _ in range(50):
        assert rig.read(rig.now_us + 7_000)[0] == 0
    assert (ev.ignored_while_booting, ev.command_during_set_reset, ev.read_of_write_only, ev.write_to_read_only,
            ev.write_to_reserved, ev.command_while_busy, ev.tm_m_with_tm_t) == (0, 0, 0, 0, 0, 0, 0)
    assert rig.cs_seen == {1}
    # 25 °C -> Tout (25 + 75) / 0.8 = 125 (DS p.14) -> -75 + 0.8 · 125 = 25.0 °C
    assert sil.lib.mmc5983ma_temperature_dc(rig.dev) == 250


def test_run_blocks_with_the_bus_delay(sil):
    rig = Rig(sil, ideal(), delay=True)
    now = sil.ffi.new("uint64_t *", 0)
    assert sil.lib.mmc5983ma_run(rig.dev, now) == 0
    assert now[0] >= 36_000
    rig2 = Rig(sil, ideal(), delay=False)
    assert sil.lib.mmc5983ma_run(rig2.dev, now) == ERR_ARGUMENT


def test_the_glue_hook_reads_through_the_mag_driver_table(sil):
    rig = running(sil)
    drv = sil.ffi.new("capsheet_mag_driver_t *")
    sil.lib.mmc5983ma_mag_driver(rig.dev, drv)
    assert drv.poll(drv.ctx, rig.at(60_000)) >= 0
    rig.part.set_field(EARTH_T)
    mag = sil.ffi.new("int16_t[3]")
    st = sil.ffi.new("uint8_t *")
    assert drv.read(drv.ctx, rig.at(61_000), 1, mag, st) == 0
    assert drv.read(drv.ctx, rig.at(71_000), 1, mag, st) == 0
    assert abs(mag[0] - 819) <= 1 and st[0] == 0


# ---------------------------------------------------------------------------------- every error path
def test_arguments_are_checked(sil):
    rig = Rig(sil, ideal())
    assert sil.lib.mmc5983ma_init(rig.dev, rig.bus, 1, 4) == ERR_ARGUMENT
    assert sil.lib.mmc5983ma_init(sil.ffi.NULL, rig.bus, 1, 0) == ERR_ARGUMENT
    rig = running(sil)
    assert rig.read(60_000, r=4)[0] == ERR_ARGUMENT


def test_read_before_the_bring_up_is_not_ready(sil):
    rig = Rig(sil, ideal())
    assert rig.read(0)[0] == ERR_NOT_READY
    assert rig.step(0) > 0 and rig.read(1_000)[0] == ERR_NOT_READY


def test_a_bus_error_is_a_sticky_bus_fault(sil):
    rig = Rig(sil, ideal())
    rig.fail_bus = True
    assert rig.bring_up()[0] == ERR_BUS
    rig.fail_bus = False
    assert rig.step(rig.now_us + 50_000) == ERR_BUS  # sticky


@pytest.mark.parametrize("fault, err", [("wrong_id", ERR_PRODUCT_ID), ("otp_fail", ERR_OTP),
                                        ("dead_axis", ERR_SELF_TEST), ("frozen", ERR_TIMEOUT),
                                        ("no_answer", ERR_PRODUCT_ID), ("stuck_bus", ERR_PRODUCT_ID)])
def test_each_injected_fault_fails_the_bring_up(sil, fault, err):
    part = ideal()
    part.inject(fault)
    assert Rig(sil, part).bring_up()[0] == err


def test_a_healthy_part_is_not_failed_by_those_checks(sil):
    # the control: the same rig and part without a fault
    assert Rig(sil, ideal()).bring_up()[0] == 0


def test_a_self_test_offset_beyond_the_null_field_limit_fails(sil):
    # 0.6 G offset: beyond the datasheet's 0.5 G null-field output
    assert Rig(sil, ideal(offset_g=[0.6, 0.0, 0.0])).bring_up()[0] == ERR_SELF_TEST
    assert Rig(sil, ideal(offset_g=[0.45, 0.0, 0.0])).bring_up()[0] == 0


@pytest.mark.parametrize("fault, err", [("no_answer", ERR_GONE), ("stuck_bus", ERR_GONE), ("frozen", ERR_TIMEOUT)])
def test_a_part_gone_mid_stream_is_a_fault_never_a_frozen_value(sil, fault, err):
    rig = running(sil)
    t = 60_000
    for _ in range(5):
        assert rig.read(t)[0] == 0
        t += 7_000
    rig.part.inject(fault)
    codes = []
    for _ in range(5):
        codes.append(rig.read(t)[0])
        t += 7_000
    assert err in codes and codes[-1] == err   # found within the timeout (4 x 4 ms + 1 ms), and sticky
    assert codes.index(err) <= 3
    rig.part.clear_faults()                    # the part comes back: still a fault until re-initialised
    assert rig.read(t)[0] == err


def test_a_part_reset_behind_the_drivers_back_is_found(sil):
    rig = running(sil)
    rig.read(60_000)
    # a brown-out: the part reboots (SW_RST written by someone else), forgets its measurement
    rig.part.spi_transfer(bytes([0x0A, 0x80]))
    codes = [rig.read(60_000 + 1_000 * k)[0] for k in range(1, 40)]
    assert codes[-1] in (ERR_GONE, ERR_TIMEOUT) and 0 not in codes[codes.index(codes[-1]):]


# ---------------------------------------------------------------------------------- wrong emulators
class SwappedBytes(MMC5983MA):
    """Answers Xout0/Xout1 (and Y, Z) the wrong way round: low byte first."""

    def _read(self, addr):
        if addr <= 5:
            return super()._read(addr ^ 1)
        return super()._read(addr)


class ReadBitInverted(MMC5983MA):
    """Takes bit 7 clear as the read command (the opposite of DS p.6/p.7)."""

    def spi_transfer(self, tx):
        tx = bytes(tx)
        return super().spi_transfer(bytes([tx[0] ^ 0x80]) + tx[1:]) if tx else super().spi_transfer(tx)


class ReadBitIgnored(MMC5983MA):
    """Reads whatever bit 7 says: every write is lost."""

    def spi_transfer(self, tx):
        tx = bytes(tx)
        return super().spi_transfer(bytes([tx[0] | 0x80]) + tx[1:]) if tx else super().spi_transfer(tx)


def _wrong(cls):
    return cls(seed=3, clock_error=0.0, gain=[1, 1, 1], cross=[[0] * 3] * 3, noise=False, offset_g=[0.1, -0.2, 0.05])


@pytest.mark.parametrize("cls, err", [(SwappedBytes, ERR_SELF_TEST), (ReadBitInverted, ERR_PRODUCT_ID),
                                      (ReadBitIgnored, ERR_TIMEOUT)])
def test_a_wrong_emulator_makes_the_driver_fail(sil, cls, err):
    part = _wrong(cls)
    part.set_field(EARTH_T)
    assert Rig(sil, part).bring_up()[0] == err


def test_a_field_over_10_gauss_is_undone_by_the_set_before_each_measurement(sil):
    # DS p.10 / p.2 note 6: over 10 G the film flips (the reading's sign with it) until a SET
    rig = running(sil)
    settle(rig, EARTH_T, 60_000)
    rig.part.set_field((1.2e-3, 0.0, 0.0))  # 12 G: a magnet against the sheet
    rig.read(80_000)
    rc, mag, _, _ = settle(rig, EARTH_T, 90_000)
    assert rc == 0 and abs(mag[0] - 1638) <= 1 and abs(mag[2] - 3686) <= 1


# ---------------------------------------------------------------------------------- the 9-axis link glue
def test_the_link_glue_reads_the_magnetometer_beside_the_imu_on_one_spi_bus():
    """The firmware's own SIL build: ICM-42688-P on chip select 0, MMC5983MA on 1, one bus; read_imu's
    magnetometer is this driver's, through link_sensors.h's capsheet_mag_driver_t."""
    from firmware_ref._ffi import ffi, lib
    from firmware_ref.sil_bus import SilBus
    from virtual_sheet.parts.icm42688p import ICM42688P

    imu, mag = ICM42688P(seed=5), ideal()
    imu.set_motion([0, 0, 9.80665], [0, 0, 0])
    mag.set_field(EARTH_T)
    bus = SilBus(spi={0: imu, 1: mag})
    dev = ffi.new("mmc5983ma_t *")
    assert lib.mmc5983ma_init(dev, bus.c_bus, 1, 1) == 0
    drv = ffi.new("capsheet_mag_driver_t *")
    lib.mmc5983ma_mag_driver(dev, drv)
    ls = ffi.new("capsheet_link_sensors_t *")
    assert lib.capsheet_link_sensors_init(ls, bus.c_bus, 0, drv, ffi.NULL, False) == 0
    us = lambda: int(round(bus.now_s * 1e6))  # noqa: E731
    xyz, st = ffi.new("int16_t[3]"), ffi.new("uint8_t *")
    for _ in range(200):                                # the main loop: the glue's poll, the IMU's reads
        bus.advance(bus.now_s + 0.001)
        assert lib.capsheet_link_sensors_poll(ls, us()) >= 0
        assert lib.capsheet_link_read_axes(ls, us(), xyz, st) == 0
    assert dev.phase == 9 and dev.error == 0          # the magnetometer's bring-up ran through the glue
    out = ffi.new("capsheet_imu_reading_t *")
    for _ in range(3):                                  # a SYNC every 10 ms
        bus.advance(bus.now_s + 0.010)
        assert lib.capsheet_link_read_axes(ls, us(), xyz, st) == 0
        assert lib.capsheet_link_read_imu(ls, us(), 3, 1, True, out) == 0
    # 0.2, -0.05, 0.45 G at ±8 G (4096 counts per gauss, §16.1)
    assert [abs(m - w) <= 1 for m, w in zip(out.mag, (819, -205, 1843))] == [True] * 3
    assert not out.status & SATURATED
    mag.inject("no_answer")                             # the magnetometer falls off the bus
    bus.advance(bus.now_s + 0.010)
    # the glue polls the magnetometer at read_axes: the link's sensors fail there, and read_imu says so
    assert lib.capsheet_link_read_axes(ls, us(), xyz, st) == ERR_GONE
    assert lib.capsheet_link_read_imu(ls, us(), 3, 1, True, out) == ERR_GONE   # a sensor fault, not old counts
    assert ls.fault == ERR_GONE


@pytest.mark.parametrize("seed", range(12))
def test_parts_drawn_at_the_datasheets_tolerances_come_up_and_read_within_them(sil, seed):
    # offset within 0.5 G (removed), gain within 5 %, cross-axis 0.8 %, noise 0.6 mG RMS at BW 01,
    # clock within 3 %: the field at ±4 G (8192 counts per gauss) within 5 % + 2 · 0.8 % of the
    # largest component (0.45 G: 3686 counts -> 243) and 6 counts of noise and quantisation
    rig = running(sil, MMC5983MA(seed=seed))
    rc, mag, st, _ = settle(rig, EARTH_T, 60_000)
    assert rc == 0 and st == 0
    for m, w in zip(mag, (1638, -410, 3686)):
        assert abs(m - w) <= 0.05 * abs(w) + 0.016 * 3686 + 6, (seed, mag)


# ---------------------------------------------------------------------------------- on I2C
def test_on_i2c_the_same_bring_up_and_counts(sil):
    rig = Rig(sil, ideal(), i2c_addr=0x30)
    rc, _ = rig.bring_up()
    assert rc == 0 and rig.i2c_seen == {0x30}
    rc, mag, st, _ = settle(rig, EARTH_T, 60_000, r=1)
    assert rc == 0 and st == 0
    assert [abs(m - w) <= 1 for m, w in zip(mag, (819, -205, 1843))] == [True] * 3


def test_on_i2c_a_part_that_stops_acknowledging_is_a_bus_fault(sil):
    rig = Rig(sil, ideal(), i2c_addr=0x30)
    assert rig.bring_up()[0] == 0
    assert rig.read(60_000)[0] == 0
    rig.part.inject("no_answer")
    assert rig.read(70_000)[0] == ERR_BUS
    rig.part.clear_faults()
    assert rig.read(80_000)[0] == ERR_BUS        # sticky


def test_on_i2c_the_wrong_address_never_comes_up(sil):
    rig = Rig(sil, ideal(), i2c_addr=0x31)
    assert rig.bring_up()[0] == ERR_BUS
    rig = Rig(sil, ideal())
    assert rig.lib.mmc5983ma_init_i2c(rig.dev, rig.bus, 0x80, 1) == ERR_ARGUMENT


class Garbage:
    """A "part" that answers every byte at random (seeded): noise on SDO, a wrong part, a bad wire."""

    def __init__(self, seed):
        self.rng = np.random.Generator(np.random.MT19937(seed))

    def advance(self, now_s):
        pass

    def spi_transfer(self, tx):
        return bytes(self.rng.integers(0, 256, len(tx), dtype=np.uint8)) if len(tx) else b""


def test_a_bus_answering_garbage_never_comes_up_and_never_crashes(sil):
    codes = set()
    for seed in range(100):
        rc, _ = Rig(sil, Garbage(seed)).bring_up()
        codes.add(rc)
    assert codes <= {ERR_PRODUCT_ID, ERR_OTP, ERR_GONE, ERR_SELF_TEST, ERR_TIMEOUT} and ERR_PRODUCT_ID in codes


def test_garbage_mid_stream_is_a_fault(sil):
    for seed in range(20):
        rig = running(sil)
        g = Garbage(seed)
        rig.part.spi_transfer = g.spi_transfer          # the wire goes bad under a running driver
        codes = [rig.read(60_000 + 7_000 * k)[0] for k in range(6)]
        assert codes[-1] < 0, (seed, codes)


def test_a_read_with_an_older_now_is_not_a_timeout(sil):
    # a caller whose clock read is older than the measurement's start (an interrupt's timestamp)
    rig = running(sil)
    assert rig.read(60_000)[0] == 0
    mag = sil.ffi.new("int16_t[3]")
    st = sil.ffi.new("uint8_t *")
    assert sil.lib.mmc5983ma_read(rig.dev, 59_000, 0, mag, st, sil.ffi.NULL) == 0
