"""The ICM-42688-P emulator against datasheet DS-000347, through the pinned seam only
(`ICM42688P(seed=...)`, `.spi_transfer`, `.set_motion`, `.advance`).

Every expected value is typed from the datasheet (the section is named beside it), never computed by
the emulator: reset values (§13/§14), the SPI read bit and auto-increment (§9), start-up times (§3.1
Table 1: 30 ms, §3.2 Table 2: 10 ms), sensitivities per range (Tables 1 and 2), noise densities, the
temperature scale (§4.13), the self-test limits."""

from __future__ import annotations

import numpy as np
import pytest

from virtual_sheet.parts.icm42688p import ICM42688P, BusError

G0 = 9.80665


def rd(part: ICM42688P, addr: int, n: int = 1) -> bytes:
    return part.spi_transfer(bytes([0x80 | addr]) + bytes(n))[1:]


def wr(part: ICM42688P, addr: int, *values: int) -> None:
    part.spi_transfer(bytes([addr, *values]))


def i16(b: bytes) -> list[int]:
    return [int.from_bytes(b[i:i + 2], "big", signed=True) for i in range(0, len(b), 2)]


def ready(seed: int = 1) -> ICM42688P:
    """A part 2 ms after power-on (its registers answer after 1 ms)."""
    p = ICM42688P(seed=seed)
    p.advance(0.002)
    return p


# §13 / §14: bank-0 reset values, typed from the register map
RESET_BANK0 = {
    0x11: 0x00,  # DEVICE_CONFIG
    0x13: 0x05,  # DRIVE_CONFIG
    0x14: 0x00,  # INT_CONFIG
    0x16: 0x00,  # FIFO_CONFIG
    0x4C: 0x30,  # INTF_CONFIG0 (big-endian data)
    0x4D: 0x91,  # INTF_CONFIG1
    0x4E: 0x00,  # PWR_MGMT0: both sensors off
    0x4F: 0x06,  # GYRO_CONFIG0: ±2000 °/s, 1 kHz
    0x50: 0x06,  # ACCEL_CONFIG0: ±16 g, 1 kHz
    0x51: 0x16,  # GYRO_CONFIG1
    0x52: 0x11,  # GYRO_ACCEL_CONFIG0
    0x53: 0x0D,  # ACCEL_CONFIG1
    0x54: 0x23,  # TMST_CONFIG
    0x63: 0x00,  # INT_CONFIG0
    0x64: 0x10,  # INT_CONFIG1
    0x65: 0x10,  # INT_SOURCE0
    0x70: 0x00,  # SELF_TEST_CONFIG
    0x75: 0x47,  # WHO_AM_I
    0x76: 0x00,  # REG_BANK_SEL
}


@pytest.mark.parametrize("addr,value", sorted(RESET_BANK0.items()))
def test_reset_values(addr, value):
    assert rd(ready(), addr) == bytes([value])


def test_registers_silent_during_power_up_then_who_am_i():
    p = ICM42688P(seed=1)
    p.advance(0.0009)              # before the 1 ms (§14 DEVICE_CONFIG)
    assert rd(p, 0x75) == b"\x00"
    p.advance(0.0011)
    assert rd(p, 0x75) == b"\x47"


def test_miso_is_zero_during_the_address_byte_and_read_bit_is_bit_7():
    p = ready()
    assert p.spi_transfer(bytes([0xF5, 0xAA])) == b"\x00\x47"
    # bit 7 clear: a write (to the read-only WHO_AM_I: ignored), MISO 0
    assert p.spi_transfer(bytes([0x75, 0x00])) == b"\x00\x00"
    assert rd(p, 0x75) == b"\x47"


def test_int_status_reset_done_once_then_cleared_by_the_read():
    p = ready()
    assert rd(p, 0x2D) == b"\x10"   # RESET_DONE_INT (§14 INT_STATUS)
    assert rd(p, 0x2D) == b"\x00"


def test_data_registers_read_minus_32768_while_off():
    # §4.11: TEMP_DATA1 .. GYRO_DATA_Z0 (0x1D..0x2A), big-endian
    assert rd(ready(), 0x1D, 14) == bytes.fromhex("8000" * 7)


# register reads after each documented write (bank 0)
WRITES = [
    (0x4E, 0x0F, 0x0F),   # PWR_MGMT0: gyro LN (3:2), accel LN (1:0)
    (0x4F, 0x66, 0x66),   # GYRO_CONFIG0: ±250 °/s, 1 kHz
    (0x50, 0x68, 0x68),   # ACCEL_CONFIG0: ±2 g, 100 Hz
    (0x52, 0x44, 0x44),   # GYRO_ACCEL_CONFIG0
    (0x65, 0x08, 0x08),   # INT_SOURCE0: UI_DRDY_INT1_EN
    (0x70, 0x7F, 0x7F),   # SELF_TEST_CONFIG
    (0x75, 0x00, 0x47),   # WHO_AM_I is read only
    (0x2D, 0xFF, 0x10),   # INT_STATUS is read only (and shows RESET_DONE once)
    (0x12, 0x5A, 0x00),   # reserved: reads 0, writes ignored
    (0x4B, 0x04, 0x00),   # SIGNAL_PATH_RESET: its bits self-clear, reads 0
]


@pytest.mark.parametrize("addr,value,expected", WRITES)
def test_read_after_write(addr, value, expected):
    p = ready()
    wr(p, addr, value)
    assert rd(p, addr) == bytes([expected])


def test_writes_auto_increment():
    p = ready()
    wr(p, 0x4F, 0x26, 0x66)        # GYRO_CONFIG0 then ACCEL_CONFIG0 in one transaction
    assert rd(p, 0x4F, 2) == b"\x26\x66"


def test_banks():
    p = ready()
    wr(p, 0x76, 1)
    assert rd(p, 0x76) == b"\x01"
    assert rd(p, 0x75) == b"\x00"      # WHO_AM_I is a bank-0 register
    codes = rd(p, 0x5F, 3)             # XG/YG/ZG_ST_DATA: factory self-test codes, non-zero
    assert all(c != 0 for c in codes)
    wr(p, 0x76, 0)
    assert rd(p, 0x75) == b"\x47"


def test_soft_reset_restores_reset_values_after_1_ms():
    p = ready()
    wr(p, 0x4F, 0x66)
    wr(p, 0x4E, 0x0F)
    wr(p, 0x11, 0x01)                  # DEVICE_CONFIG SOFT_RESET_CONFIG
    assert rd(p, 0x75) == b"\x00"      # not answering during the 1 ms
    p.advance(0.002 + 0.0011)
    assert rd(p, 0x75) == b"\x47"
    assert rd(p, 0x4F) == b"\x06" and rd(p, 0x4E) == b"\x00"
    assert rd(p, 0x2D) == b"\x10"


@pytest.mark.parametrize("pwr,data_addr,startup_s", [(0x03, 0x1F, 0.010), (0x0C, 0x25, 0.030)])
def test_start_up_times(pwr, data_addr, startup_s):
    # §3.2 Table 2: accelerometer 10 ms; §3.1 Table 1: gyroscope 30 ms
    p = ready()
    t0 = 0.002
    wr(p, 0x4E, pwr)
    p.advance(t0 + startup_s - 0.0005)
    assert i16(rd(p, data_addr, 6)) == [-32768] * 3
    p.advance(t0 + startup_s + 0.0015)
    assert -32768 not in i16(rd(p, data_addr, 6))


def _mean(p: ICM42688P, addr: int, t: float, n: int = 200) -> tuple[np.ndarray, float]:
    xs = []
    for _ in range(n):
        t += 0.001
        p.advance(t)
        xs.append(i16(rd(p, addr, 6)))
    return np.mean(xs, axis=0), t


# §3.2 Table 2: LSB/g by ACCEL_FS_SEL (0 ±16 g .. 3 ±2 g); tolerance ±0.5 % (3 σ: 1.5 %)
@pytest.mark.parametrize("fs_sel,lsb_per_g", [(0, 2048), (1, 4096), (2, 8192), (3, 16384)])
def test_accelerometer_sensitivity(fs_sel, lsb_per_g):
    p = ready(seed=7)
    wr(p, 0x50, (fs_sel << 5) | 0x06)
    wr(p, 0x4E, 0x03)
    p.set_motion([0, 0, G0], [0, 0, 0])
    up, t = _mean(p, 0x1F, 0.020)
    p.set_motion([0, 0, -G0], [0, 0, 0])
    down, _ = _mean(p, 0x1F, t)
    measured = (up[2] - down[2]) / 2.0
    assert abs(measured / lsb_per_g - 1.0) < 0.015


# §3.1 Table 1: LSB/(°/s) by GYRO_FS_SEL; tolerance ±0.5 % (3 σ: 1.5 %) plus the table's rounding
@pytest.mark.parametrize("fs_sel,lsb_per_dps,full_scale", [
    (0, 16.4, 2000), (1, 32.8, 1000), (2, 65.5, 500), (3, 131, 250), (4, 262, 125),
    (5, 524.3, 62.5), (6, 1048.6, 31.25), (7, 2097.2, 15.625)])
def test_gyroscope_sensitivity(fs_sel, lsb_per_dps, full_scale):
    p = ready(seed=8)
    wr(p, 0x4F, (fs_sel << 5) | 0x06)
    wr(p, 0x4E, 0x0C)
    rate = np.radians(full_scale / 2)
    p.set_motion([0, 0, G0], [0, 0, rate])
    up, t = _mean(p, 0x25, 0.040)
    p.set_motion([0, 0, G0], [0, 0, -rate])
    down, _ = _mean(p, 0x25, t)
    measured = (up[2] - down[2]) / 2.0 / (full_scale / 2)
    assert abs(measured / lsb_per_dps - 1.0) < 0.017


def test_accelerometer_noise_density():
    # §3.2 Table 2: 70 µg/√Hz; ODR 1 kHz with the UI filter at ODR/4 (reset value): 250 Hz
    p = ready(seed=9)
    wr(p, 0x50, 0x66)                  # ±2 g, 1 kHz
    wr(p, 0x4E, 0x03)
    t, xs = 0.020, []
    for _ in range(2000):
        t += 0.001
        p.advance(t)
        xs.append(i16(rd(p, 0x1F, 6)))
    sd_g = np.std(np.asarray(xs, dtype=float), axis=0) / 16384.0
    expected = 70e-6 * np.sqrt(250.0)
    assert np.all(np.abs(sd_g / expected - 1.0) < 0.1)


def test_saturation_at_the_16_bit_rails():
    p = ready()
    wr(p, 0x50, 0x66)                  # ±2 g
    wr(p, 0x4E, 0x03)
    p.set_motion([3 * G0, -3 * G0, 0], [0, 0, 0])
    p.advance(0.020)
    x, y, _ = i16(rd(p, 0x1F, 6))
    assert (x, y) == (32767, -32768)


def test_temperature_scale():
    # §4.13: TEMP_DATA = (T - 25 °C) · 132.48 LSB/°C
    p = ICM42688P(seed=1, temperature_c=35.0)
    p.advance(0.002)
    wr(p, 0x4E, 0x03)
    p.advance(0.020)
    assert i16(rd(p, 0x1D, 2)) == [1325]


def test_conversions_on_the_parts_own_clock():
    # 1 kHz within the part's clock tolerance (±1 %: assumed, see the module) over 1 s
    p = ready(seed=11)
    wr(p, 0x4E, 0x03)
    p.advance(0.020)
    first = p.conversions
    p.advance(1.020)
    assert 990 <= p.conversions - first <= 1010
    drdy = [rd(p, 0x2D)[0] & 0x08]
    assert drdy == [0x08]
    assert rd(p, 0x2D)[0] & 0x08 == 0   # DATA_RDY cleared by the read


def _st_ratio(p: ICM42688P, sensor: str) -> np.ndarray:
    """Self-test response / ST_OTP per axis at ±250 °/s / ±2 g, ST_OTP = 2620 · 1.01^(code - 1)."""
    wr(p, 0x4F, 0x66)
    wr(p, 0x50, 0x66)
    wr(p, 0x4E, 0x0C if sensor == "gyro" else 0x03)
    addr = 0x25 if sensor == "gyro" else 0x1F
    off, t = _mean(p, addr, 0.080)
    wr(p, 0x70, 0x07 if sensor == "gyro" else 0x78)
    on, _ = _mean(p, addr, t + 0.2)
    wr(p, 0x76, 1 if sensor == "gyro" else 2)
    codes = rd(p, 0x5F if sensor == "gyro" else 0x3B, 3)
    wr(p, 0x76, 0)
    otp = np.array([2620.0 * 1.01 ** (c - 1) for c in codes])
    return np.abs(on - off) / otp


@pytest.mark.parametrize("sensor", ["gyro", "accel"])
def test_self_test_passes_within_datasheet_limits(sensor):
    ratio = _st_ratio(ready(seed=12), sensor)
    assert np.all((ratio > 0.5) & (ratio < 1.5))


@pytest.mark.parametrize("sensor", ["gyro", "accel"])
def test_self_test_fault_fails_the_limits(sensor):
    p = ready(seed=12)
    p.fault("self_test_fail")
    ratio = _st_ratio(p, sensor)
    assert np.all(ratio < 0.5)


def test_faults_on_demand():
    p = ready()
    p.fault("no_answer")
    assert p.spi_transfer(bytes([0xF5, 0])) == b"\xff\xff"
    p.fault("wrong_id")
    assert rd(p, 0x75) == b"\x42"
    p.fault("stuck_bus")
    with pytest.raises(BusError):
        p.spi_transfer(bytes([0xF5, 0]))
    p.fault("garbage")
    reads = {rd(p, 0x75, 4) for _ in range(8)}
    assert len(reads) > 1                       # random, not a stuck value
    p.fault(None)
    assert rd(p, 0x75) == b"\x47"


def test_reset_fault_is_a_brown_out():
    p = ready()
    rd(p, 0x2D)
    wr(p, 0x4E, 0x0F)
    p.fault("reset")
    p.advance(0.0035)
    assert rd(p, 0x4E) == b"\x00"
    assert rd(p, 0x2D) == b"\x10"


def test_bad_arguments_are_one_line_errors():
    p = ready()
    with pytest.raises(ValueError, match="shape"):
        p.set_motion([0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="forwards"):
        p.advance(0.001)
    with pytest.raises(ValueError, match="Unknown fault"):
        p.fault("melted")
