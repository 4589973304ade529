"""The MMC5983MA emulator against its datasheet (MEMSIC MMC5983MA Rev A, 4/3/2019).

Every expected value is typed from the datasheet (page cited beside it), never computed by the
emulator: reset values, register reads after each documented write, SPI framing, measurement
times, sensitivity and full scale, SET/RESET, noise per bandwidth, temperature, faults.
"""

from __future__ import annotations

import numpy as np
import pytest

from virtual_sheet.parts.mmc5983ma import FAULTS, MMC5983MA, BusNak

R = 0x80  # DS p.6: the read bit


def nominal(**kw) -> MMC5983MA:
    """A part at exactly its nominal figures (no offset, no gain error, no noise, an exact clock)."""
    kw.setdefault("offset_g", [0.0, 0.0, 0.0])
    return MMC5983MA(seed=1, clock_error=0.0, gain=[1, 1, 1], cross=[[0] * 3] * 3, noise=False, **kw)


def rd(p, addr, n=1) -> bytes:
    return p.spi_transfer(bytes([R | addr]) + bytes(n))[1:]


def wr(p, addr, *vals) -> None:
    p.spi_transfer(bytes([addr, *vals]))


def booted(**kw) -> MMC5983MA:
    p = nominal(**kw)
    p.advance(0.010)  # DS p.15: power-on time 10 ms
    return p


def measure(p, t0, bw_ms=8e-3):
    """TM_M at t0 after a SET; the 7 output bytes once it finished."""
    p.advance(t0)
    wr(p, 0x09, 0x08)          # SET (DS p.18 "Example of SET": 00001000 to 09H)
    p.advance(t0 + 1e-6)
    wr(p, 0x09, 0x01)          # TM_M (DS p.17 "Example measurement": 00000001 to 09H)
    p.advance(t0 + 1e-6 + bw_ms + 1e-6)
    return rd(p, 0x00, 7)


# ------------------------------------------------------------------------- reset values, power-on
def test_reset_values_after_power_on():
    p = booted()
    assert rd(p, 0x2F) == b"\x30"          # DS p.16 Product ID1: 0011 0000
    assert rd(p, 0x08) == b"\x10"          # DS p.14 Status reset value 0, OTP_Rd_Done (bit 4) once the OTP is read
    assert rd(p, 0x09, 4) == b"\x00" * 4   # DS p.14-16 Internal control 0..3 reset value 0 (and write only)
    assert rd(p, 0x00, 8) == b"\x00" * 8


def test_the_part_does_not_answer_during_its_power_on_time():
    p = nominal()
    p.advance(0.0099)
    assert p.spi_transfer(bytes([R | 0x2F, 0])) == b"\xff\xff"   # SDO undriven: the bus's pull-up
    wr(p, 0x09, 0x01)                                             # lost
    p.advance(0.0101)
    assert rd(p, 0x2F) == b"\x30" and rd(p, 0x08) == b"\x10"
    assert p.events.ignored_while_booting == 2 and p.events.measurements == 0


def test_sw_rst_reboots_for_10_ms_and_clears_the_registers():
    p = booted()
    wr(p, 0x0B, 0x0D)                      # continuous mode at 100 Hz
    p.advance(0.020)
    wr(p, 0x0A, 0x80)                      # SW_RST (DS p.15)
    p.advance(0.0299)
    assert rd(p, 0x2F) == b"\xff"          # rebooting
    p.advance(0.0301)
    n = p.events.measurements
    assert rd(p, 0x08) == b"\x10"
    p.advance(0.2)
    assert p.events.measurements == n      # continuous mode was cleared


# ------------------------------------------------------------------------- SPI framing
def test_spi_command_byte_read_bit_dont_care_bit_and_undriven_first_byte():
    p = booted()
    assert p.spi_transfer(bytes([0xAF, 0x00])) == b"\xff\x30"    # 1 0 101111: read Product ID1
    assert p.spi_transfer(bytes([0xEF, 0x00])) == b"\xff\x30"    # bit 6 is don't care (DS p.5)
    p.spi_transfer(bytes([0x2F, 0x55]))                          # a write (RW 0) to a read-only register
    assert p.events.write_to_read_only == 1 and rd(p, 0x2F) == b"\x30"


def test_burst_read_moves_the_address_pointer():
    p = booted()
    got = rd(p, 0x07, 3)                   # Tout, Status, Internal control 0
    assert got == b"\x00\x10\x00"
    assert rd(p, 0x3F, 2) == b"\x00\x00"   # past 0x3F: the pointer wraps (not in the datasheet: the emulator's choice)


def test_burst_write_fills_following_registers():
    p = booted()
    p.spi_transfer(bytes([0x0A, 0x01, 0x0D]))   # Internal control 1 = BW 01, Internal control 2 = 100 Hz continuous
    p.advance(0.010 + 0.0045)                    # the first measurement (started at once) takes 4 ms at BW 01
    assert rd(p, 0x08) == b"\x11"


def test_control_registers_are_write_only():
    p = booted()
    wr(p, 0x0A, 0x03)
    assert rd(p, 0x0A) == b"\x00" and p.events.read_of_write_only == 1


def test_an_empty_transaction_is_counted():
    p = booted()
    assert p.spi_transfer(b"") == b"" and p.events.empty_transaction == 1


# ------------------------------------------------------------------------- measurements and timing
@pytest.mark.parametrize("bw, t_ms", [(0, 8.0), (1, 4.0), (2, 2.0), (3, 0.5)])  # DS p.15 Internal Control 1
def test_measurement_time_per_bandwidth_code(bw, t_ms):
    p = booted()
    wr(p, 0x0A, bw)
    t0 = 0.020
    p.advance(t0)
    wr(p, 0x09, 0x01)
    assert rd(p, 0x08) == b"\x10"                    # Meas_M_Done 0 at the command (DS p.14)
    p.advance(t0 + t_ms * 1e-3 * 0.999)
    assert rd(p, 0x08) == b"\x10"
    p.advance(t0 + t_ms * 1e-3 * 1.001)
    assert rd(p, 0x08) == b"\x11"                    # and 1 at its end


def test_the_parts_clock_sets_its_times():
    p = MMC5983MA(seed=1, clock_error=0.03, noise=False)   # 3 % fast: 8 ms takes 7.767 ms
    p.advance(0.010)
    wr(p, 0x09, 0x01)
    p.advance(0.010 + 0.00776)
    assert rd(p, 0x08) == b"\x10"
    p.advance(0.010 + 0.00777)
    assert rd(p, 0x08) == b"\x11"


def test_status_done_bits_clear_by_writing_one():
    p = booted()
    measure(p, 0.02)
    assert rd(p, 0x08) == b"\x11"
    wr(p, 0x08, 0x10)                      # OTP_Rd_Done is not cleared by a write
    assert rd(p, 0x08) == b"\x11"
    wr(p, 0x08, 0x01)                      # DS p.14: "Writing 1 into this bit will clear"
    assert rd(p, 0x08) == b"\x10"


def test_tm_m_and_tm_t_together_start_nothing():
    p = booted()
    wr(p, 0x09, 0x03)
    p.advance(0.05)
    assert rd(p, 0x08) == b"\x10" and p.events.tm_m_with_tm_t == 1


@pytest.mark.parametrize("gauss, b0, b1, b2", [
    (1.0, 0x90, 0x00, 0x00),      # 131072 + 16384 = 147456 = 0x24000 (DS p.2: 16384 counts/G, null 131072)
    (-1.0, 0x70, 0x00, 0x00),     # 114688 = 0x1C000
    (0.5, 0x88, 0x00, 0x00),      # 139264 = 0x22000
    (8.0, 0xFF, 0xFF, 0xC0),      # full scale ±8 G (DS p.2): 262144 clamps to 262143
    (-8.0, 0x00, 0x00, 0x00),
    (1.0 / 16384, 0x80, 0x00, 0x40),   # one LSB: 131073, Xout[1:0] = 01 in XYZout2 bits 7:6
])
def test_x_output_bytes_for_a_field(gauss, b0, b1, b2):
    p = booted()
    p.set_field((gauss * 1e-4, 0.0, 0.0))
    out = measure(p, 0.02)
    assert (out[0], out[1], out[6]) == (b0, b1, b2)
    assert out[2:6] == b"\x80\x00\x80\x00"   # y, z at the null field, 131072 = 0x20000


def test_16_bit_operation_is_4096_counts_per_gauss():
    p = booted()
    p.set_field((0.0, 2e-4, 0.0))            # 2 G on y
    out = measure(p, 0.02)
    assert (out[2] << 8) | out[3] == 32768 + 2 * 4096   # DS p.2: 16 bits, null 32768, 4096 counts/G


def test_set_and_reset_flip_the_field_not_the_offset():
    # DS p.18: after SET Output1 = +H + Offset, after RESET Output2 = -H + Offset
    p = booted(offset_g=[0.1, 0.0, 0.0])
    p.set_field((0.3e-4, 0.0, 0.0))
    out = measure(p, 0.02)
    x_set = (out[0] << 10) | (out[1] << 2) | (out[6] >> 6)
    wr(p, 0x09, 0x10)                        # RESET (DS p.18 "Example of RESET": 00010000)
    p.advance(0.0300)
    wr(p, 0x09, 0x01)
    p.advance(0.0390)
    out = rd(p, 0x00, 7)
    x_reset = (out[0] << 10) | (out[1] << 2) | (out[6] >> 6)
    assert x_set == 137626                   # 131072 + 16384 · 0.4 = 137625.6
    assert x_reset == 127795                 # 131072 - 16384 · 0.2 = 127795.2
    assert p.events.sets == 1 and p.events.resets == 1


def test_a_field_over_10_gauss_flips_the_film_until_a_set():
    p = booted()
    p.set_field((1e-4, 0.0, 0.0))
    assert measure(p, 0.02)[0] == 0x90
    p.set_field((1.1e-3, 0.0, 0.0))          # 11 G: over the disturbing field (DS p.2 note 6)
    p.set_field((1e-4, 0.0, 0.0))
    p.advance(0.040)
    wr(p, 0x09, 0x01)                        # a measurement without a SET first
    p.advance(0.050)
    assert rd(p, 0x00)[0] == 0x70            # -1 G: the film is flipped
    assert measure(p, 0.06)[0] == 0x90       # the SET restores it


def test_self_test_coil_adds_its_field_both_ways():
    p = booted(self_test_field_g=0.25)       # the coil's field is not in the datasheet: a parameter
    wr(p, 0x0C, 0x02)                        # St_enp
    assert measure(p, 0.02)[0:2] == b"\x84\x00"   # 131072 + 4096 = 0x21000: Xout0 = [17:10] = 0x84
    wr(p, 0x0C, 0x04)                        # St_enm
    assert measure(p, 0.04)[0:2] == b"\x7c\x00"   # 131072 - 4096 = 0x1F000: Xout0 = 0x7C


def test_x_inhibit_keeps_x_unmeasured():
    p = booted()
    p.set_field((1e-4, 1e-4, 0.0))
    measure(p, 0.02)
    wr(p, 0x0A, 0x04)                        # X-inhibit
    p.set_field((-1e-4, -1e-4, 0.0))
    out = measure(p, 0.04)
    assert out[0] == 0x90 and out[2] == 0x70


@pytest.mark.parametrize("code, hz", [(0b001, 1), (0b010, 10), (0b011, 20), (0b100, 50), (0b101, 100)])
def test_continuous_mode_rates(code, hz):   # DS p.16 CM_Freq (BW = 00)
    p = booted()
    wr(p, 0x0B, 0x08 | code)
    p.advance(0.010 + 2.0 - 1e-6)
    assert p.events.measurements == 2 * hz   # the first at once, one every 1/f; the last one started 8 ms before 2 s ends


def test_continuous_mode_200_and_1000_hz_with_their_bandwidths():
    p = booted()
    wr(p, 0x0A, 0x01)                        # BW 01 for 200 Hz (DS p.16)
    wr(p, 0x0B, 0x08 | 0b110)
    p.advance(0.010 + 1.0 - 1e-6)
    assert p.events.measurements == 200
    p = booted()
    wr(p, 0x0A, 0x03)                        # BW 11 for 1000 Hz
    wr(p, 0x0B, 0x08 | 0b111)
    p.advance(0.010 + 1.0 - 1e-6)
    assert p.events.measurements == 1000


def test_continuous_mode_on_a_fast_clock():
    p = MMC5983MA(seed=1, clock_error=0.02, noise=False)
    p.advance(0.010)
    wr(p, 0x0B, 0x08 | 0b101)                # 100 Hz on a clock 2 % fast: 102 in a second
    p.advance(0.010 + 1.0)
    assert p.events.measurements == 102


def test_periodic_set_every_25_measurements():
    p = booted()
    wr(p, 0x09, 0x20)                        # Auto_SR_en
    wr(p, 0x0B, 0x80 | (0b001 << 4) | 0x08 | 0b101)   # En_prd_set, Prd_set 25, Cmm_en, 100 Hz
    p.advance(0.010 + 1.0 - 1e-6)
    assert p.events.measurements == 100 and p.events.sets == 4


# ------------------------------------------------------------------------- noise, tolerances, temperature
@pytest.mark.parametrize("bw, rms_mg", [(0, 0.4), (1, 0.6), (2, 0.8), (3, 1.2)])  # DS p.2 Total RMS noise
def test_noise_per_bandwidth(bw, rms_mg):
    p = MMC5983MA(seed=7, clock_error=0.0, offset_g=[0, 0, 0], gain=[1, 1, 1], cross=[[0] * 3] * 3)
    p.advance(0.010)
    wr(p, 0x0A, bw)
    wr(p, 0x09, 0x08)
    xs = []
    t = 0.011
    for _ in range(1500):
        wr(p, 0x09, 0x01)
        t += 0.009
        p.advance(t)
        out = rd(p, 0x00, 7)
        xs.append((out[0] << 10) | (out[1] << 2) | (out[6] >> 6))
    rms_counts = float(np.std(xs))
    assert rms_mg * 16.384 * 0.9 < rms_counts < rms_mg * 16.384 * 1.1


def test_drawn_tolerances_stay_within_the_datasheet():
    for seed in range(20):
        p = MMC5983MA(seed=seed)
        gain = np.diag(p.sensitivity)
        cross = p.sensitivity - np.diag(gain)
        assert np.all(np.abs(gain - 1) <= 0.05)          # DS p.2 Sensitivity accuracy 5 %
        assert np.all(np.abs(cross) <= 0.008)            # DS p.2 Transverse sensitivity 0.8 %
        assert np.all(np.abs(p.offset_g) <= 0.5)         # DS p.2 Null field output 0.5 G
        assert abs(p.clock_error) <= 0.03                # the emulator's clock tolerance (not in the datasheet)


@pytest.mark.parametrize("temp_c, tout", [(25.0, 125), (-75.0, 0), (125.0, 250), (150.0, 255), (-80.0, 0)])
def test_temperature_output(temp_c, tout):   # DS p.14 Tout: 0 is -75 °C, 0.8 °C/LSB (p.2)
    p = booted()
    p.set_temperature(temp_c)
    wr(p, 0x09, 0x02)                        # TM_T
    assert rd(p, 0x08) == b"\x10"
    p.advance(0.010 + 0.0081)
    assert rd(p, 0x07, 2) == bytes([tout, 0x12])


def test_int_pin_follows_measurement_done_when_enabled():
    p = booted()
    wr(p, 0x09, 0x05)                        # INT_meas_done_en + TM_M
    assert not p.int_pin
    p.advance(0.0181)
    assert p.int_pin                         # DS p.11: INT active high


def test_spi_3w_leaves_sdo_undriven():
    p = booted()
    wr(p, 0x0C, 0x40)                        # Spi_3w (DS p.16)
    assert p.spi_transfer(bytes([R | 0x2F, 0])) == b"\xff\xff"


def test_i2c_write_read_at_the_same_registers():
    p = booted()
    assert p.i2c_write_read(b"\x2f", 1) == b"\x30"
    p.i2c_write_read(b"\x09\x01", 0)         # DS p.17: TM_M through I2C
    p.advance(0.019)
    assert p.i2c_write_read(b"\x07", 2) == b"\x00\x11"
    p.inject("no_answer")
    with pytest.raises(BusNak):
        p.i2c_write_read(b"\x2f", 1)


# ------------------------------------------------------------------------- faults on demand
def test_faults_on_demand():
    p = booted()
    p.inject("no_answer")
    assert p.spi_transfer(bytes([R | 0x2F, 0, 0])) == b"\xff\xff\xff"
    p.clear_faults()
    p.inject("stuck_bus")
    assert p.spi_transfer(bytes([R | 0x2F, 0])) == b"\x00\x00"
    p.clear_faults()
    p.inject("wrong_id")
    assert rd(p, 0x2F) == b"\x31"
    p.clear_faults()
    p.inject("otp_fail")
    assert rd(p, 0x08) == b"\x00"
    p.clear_faults()
    p.inject("dead_axis")
    out = measure(p, 0.02)
    assert out[0:2] == b"\xff\xff" and out[2] == 0x80
    p.clear_faults()
    p.inject("frozen")
    measure(p, 0.04)
    p.advance(1.0)
    assert rd(p, 0x08)[0] & 0x01 == 0
    with pytest.raises(ValueError, match="unknown fault"):
        p.inject("melted")
    assert set(FAULTS) == {"no_answer", "stuck_bus", "wrong_id", "otp_fail", "dead_axis", "frozen"}


def test_bad_input_is_refused_with_a_clear_error():
    p = booted()
    with pytest.raises(ValueError, match="field_t"):
        p.set_field((1.0, 2.0))
    with pytest.raises(ValueError, match="backwards"):
        p.advance(0.001)
