"""The register emulators' fast paths answer what their plain paths answer.

The emulators read a burst of registers as one slice; the plain path (register by register) is
the reference, so every expected value here comes from the same part taking the plain path, never
from a number typed for the occasion: a fast path that answered otherwise fails here. (What the answers should
be is tested against the datasheets in test_icm42688p.py and test_mmc5983ma.py; what the sheets
emit, byte for byte, in tests/firmware_ref/test_part_frames_same.py.)
"""

from __future__ import annotations

import numpy as np

from virtual_sheet.parts.icm42688p import ICM42688P
from virtual_sheet.parts.mmc5983ma import MMC5983MA


class ICMByRegister(ICM42688P):
    """An ICM-42688-P read register by register (a `_read` of its own: no burst slices)."""

    def _read(self, bank, addr):
        return super()._read(bank, addr)


class MMCByRegister(MMC5983MA):
    """An MMC5983MA read register by register."""

    def _read(self, addr):
        return super()._read(addr)


def icm_session(part) -> list:
    """Every answer of a part taken through bring-up, conversions, bank switches, clear-on-read
    registers, bursts that wrap past 0x7F, a wrong WHO_AM_I and MISO garbage."""
    rng = np.random.Generator(np.random.MT19937(7))
    out = []
    t = 0.0

    def xfer(tx):
        out.append(part.spi_transfer(bytes(tx)))

    for step in range(400):
        t += float(rng.uniform(0.0002, 0.004))
        part.advance(t)
        if step == 10:
            xfer([0x4E, 0x0F])                    # PWR_MGMT0: both sensors low noise
        if step == 60:
            xfer([0x70, 0x7F])                    # SELF_TEST_CONFIG: every axis, accelerometer powered
        if step == 120:
            xfer([0x70, 0x00])
        if step == 150:
            part.fault("wrong_id")
        if step == 170:
            part.fault("garbage")
        if step == 180:
            part.fault(None)
        if step == 250:
            xfer([0x76, 0x01])                    # bank 1: the gyroscope's self-test codes, TMSTVAL
            xfer([0x4B, 0x04])                    # SIGNAL_PATH_RESET TMST_STROBE (a write-only register)
        if step == 260:
            xfer([0x76, 0x00])
        addr = int(rng.integers(0, 0x80))
        n = int(rng.integers(1, 20)) if step % 7 else int(rng.integers(100, 140))   # some wrap past 0x7F
        xfer([0x80 | addr] + [0] * n)
        xfer([0x80 | 0x1D] + [0] * 14)           # TEMP_DATA1 .. GYRO_DATA_Z0: the driver's burst
        xfer([0x80 | 0x2D, 0])                   # INT_STATUS (clear on read)
    out.append(part.conversions)
    return out


def test_icm_burst_reads_answer_what_register_by_register_reads_answer():
    fast = icm_session(ICM42688P(seed=3))
    assert fast == icm_session(ICMByRegister(seed=3))
    assert len(set(fast)) > 100                      # the session saw changing data, not one answer


def mmc_session(part) -> tuple:
    rng = np.random.Generator(np.random.MT19937(8))
    out = []
    t = 0.0
    part.set_field([2e-5, -1e-5, 4e-5])
    for step in range(300):
        t += float(rng.uniform(0.0005, 0.006))
        part.advance(t)
        if step == 5:
            part.spi_transfer(bytes([0x0A, 0x01]))          # Internal control 1: BW 01
            part.spi_transfer(bytes([0x0B, 0x0D]))          # continuous mode, 100 Hz
        if step == 100:
            part.spi_transfer(bytes([0x09, 0x08]))          # SET
            part.spi_transfer(bytes([0x0C, 0x02]))          # St_enp
        if step == 150:
            part.spi_transfer(bytes([0x0C, 0x00]))
            part.inject("wrong_id")
        addr = int(rng.integers(0, 0x40))
        n = int(rng.integers(1, 14))
        out.append(part.spi_transfer(bytes([0x80 | addr]) + bytes(n)))
        out.append(part.spi_transfer(bytes([0x80]) + bytes(9)))   # Xout0 .. Status: the driver's burst
        out.append(part.spi_transfer(bytes([0x08, 0x01])))         # clear Meas_M_Done
    ev = part.events
    return out, (ev.read_of_write_only, ev.measurements, ev.sets), part.raw_outputs()


def test_mmc_burst_reads_answer_what_register_by_register_reads_answer():
    fast, plain = mmc_session(MMC5983MA(seed=5)), mmc_session(MMCByRegister(seed=5))
    assert fast == plain
    assert fast[1][0] > 0 and fast[1][1] > 50                  # write-only reads counted, measurements made
