"""Register-level emulators of real sensor parts, written from their datasheets.

One module per part. Each answers its bus the way the part does (an SPI transaction, full duplex,
or an I2C write-read), keeps its register banks, power modes, start-up times and conversions on
its own clock, and is fed the truth the virtual sheet computes for its link:

* `virtual_sheet.parts.icm42688p.ICM42688P` — TDK InvenSense ICM-42688-P 6-axis IMU (SPI):
  ``.spi_transfer(tx) -> rx``, ``.set_motion(specific_force_mps2, rate_rps)``, ``.advance(now_s)``.
* the magnetometer's module likewise, with ``.set_field(field_t)``.

The C drivers of firmware_ref/drivers/ are tested against these (tests/firmware_ref/), and the
emulators against the datasheets' own numbers (tests/virtual_sheet/parts/).
"""
