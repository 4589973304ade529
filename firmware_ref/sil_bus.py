"""A link MCU's sensor bus in software-in-the-loop: the C drivers' `capsheet_bus_t` (firmware_ref/
drivers/capsheet_bus.h) served by the register emulators of virtual_sheet/parts/.

    part = ICM42688P(seed=1)
    bus = SilBus(spi={0: part})                 # chip select 0 -> the part; I2C: i2c={0x30: mag}
    lib.icm42688p_init(dev, bus.c_bus, 0, True)

A device on SPI answers ``spi_transfer(tx) -> rx``; on I2C ``i2c_write_read(tx, n) -> rx``; both
``advance(now_s)``. A device that raises (an emulated stuck bus), or a chip select / address with no
device, is a bus error: the callback returns -1 (what a port's SPI/I2C driver returns on a timeout or
a NAK) and `errors` counts it. With ``delay=True`` the bus has a delay_us that advances every device's
clock (a blocking port); without it the drivers answer "busy, call again" (``delay_us`` NULL).
"""

from __future__ import annotations

from typing import Any

from ._ffi import ffi, lib


class SilBus:
    """The sensor bus of one emulated link MCU (see the module docstring)."""

    def __init__(self, spi: dict[int, Any] | None = None, i2c: dict[int, Any] | None = None, *,
                 delay: bool = False, now_s: float = 0.0) -> None:
        self.spi = dict(spi or {})
        self.i2c = dict(i2c or {})
        self.now_s = float(now_s)
        self.errors = 0
        self.transfers = 0
        self._handle = ffi.new_handle(self)
        self.c_bus = ffi.new("capsheet_bus_t *")
        self.c_bus.user = self._handle
        self.c_bus.spi_transfer = lib.capsheet_py_spi_transfer
        self.c_bus.i2c_write_read = lib.capsheet_py_i2c_write_read
        self.c_bus.delay_us = lib.capsheet_py_delay_us if delay else ffi.NULL

    def devices(self):
        return list(self.spi.values()) + list(self.i2c.values())

    def advance(self, now_s: float) -> None:
        """Run every device's clock to `now_s` (s)."""
        self.now_s = max(self.now_s, float(now_s))
        for d in self.devices():
            d.advance(self.now_s)

    # the callbacks' Python side (SPI's is in its callback, `capsheet_py_spi_transfer`)
    def _i2c(self, addr: int, tx: bytes, n: int) -> bytes | None:
        self.transfers += 1
        dev = self.i2c.get(addr)
        if dev is None:
            return None
        try:
            rx = dev.i2c_write_read(tx, n)
        except RuntimeError:
            return None
        return bytes(rx) if len(rx) == n else None


@ffi.def_extern()
def capsheet_py_spi_transfer(user, cs, tx, rx, length):
    # every transaction of every link passes here: the device answers in place, no copy, no extra call
    bus: SilBus = ffi.from_handle(user)
    bus.transfers += 1
    dev = bus.spi.get(cs)   # cs: a Python int already
    if dev is not None:
        try:
            out = dev.spi_transfer(ffi.buffer(tx, length)[:])
        except RuntimeError:
            out = None
        if out is not None and len(out) == length:
            ffi.memmove(rx, out if type(out) is bytes else bytes(out), length)
            return 0
    bus.errors += 1
    return -1


@ffi.def_extern()
def capsheet_py_i2c_write_read(user, addr, tx, tx_len, rx, rx_len):
    bus: SilBus = ffi.from_handle(user)
    out = bus._i2c(int(addr), bytes(ffi.buffer(tx, tx_len)) if tx_len else b"", int(rx_len))
    if out is None:
        bus.errors += 1
        return -1
    if rx_len:
        ffi.memmove(rx, out, rx_len)
    return 0


@ffi.def_extern()
def capsheet_py_delay_us(user, us):
    bus: SilBus = ffi.from_handle(user)
    bus.advance(bus.now_s + int(us) * 1e-6)
