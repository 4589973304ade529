"""ICM-42688-P register map: addresses, reset values and access, as datasheet DS-000347 prints them.

Sections: §13 register map (user banks 0..4), §14 bank 0 descriptions, §15 bank 1, §16 bank 2.
Cross-checked against public drivers written from the datasheet (Zephyr's
drivers/sensor/tdk/icm42688, TDK's Ixm42xxx driver); facts only. The C driver's names are in
firmware_ref/drivers/icm42688p_reg.h (the same names, one source of truth per language).

Access codes: ``"rw"`` read/write; ``"r"`` read only (writes ignored); ``"rc"`` read, cleared by
the read (INT_STATUS* with INT_CONFIG0's reset value); ``"w"`` write, reads 0 (its bits self-clear).
A register not listed is reserved (or not modelled: banks 3 and 4, bank 1's gyroscope static
configuration): it reads 0x00 and ignores writes.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType


@dataclass(frozen=True, slots=True)
class Reg:
    """One register: name as the datasheet prints it, address in its bank, reset value, access."""
    name: str
    bank: int
    addr: int
    reset: int
    access: str  # "rw", "r", "rc", "w"
    section: str  # DS-000347 section

    def __post_init__(self) -> None:
        if self.access not in ("rw", "r", "rc", "w"):
            raise ValueError(f"Invalid access for {self.name}: {self.access!r}")
        if not (0 <= self.addr <= 0x7F and 0 <= self.reset <= 0xFF and 0 <= self.bank <= 4):
            raise ValueError(f"Invalid register {self.name}: bank {self.bank} addr {self.addr:#x} reset {self.reset:#x}")


SPI_READ = 0x80          # §9: bit 7 of the first byte set = read; the address auto-increments
WHO_AM_I_VALUE = 0x47    # §14

_BANK0 = [
    # name, addr, reset, access, section
    ("DEVICE_CONFIG", 0x11, 0x00, "rw", "§14"),
    ("DRIVE_CONFIG", 0x13, 0x05, "rw", "§14"),
    ("INT_CONFIG", 0x14, 0x00, "rw", "§14"),
    ("FIFO_CONFIG", 0x16, 0x00, "rw", "§14"),
    ("TEMP_DATA1", 0x1D, 0x80, "r", "§14"),
    ("TEMP_DATA0", 0x1E, 0x00, "r", "§14"),
    ("ACCEL_DATA_X1", 0x1F, 0x80, "r", "§14"),
    ("ACCEL_DATA_X0", 0x20, 0x00, "r", "§14"),
    ("ACCEL_DATA_Y1", 0x21, 0x80, "r", "§14"),
    ("ACCEL_DATA_Y0", 0x22, 0x00, "r", "§14"),
    ("ACCEL_DATA_Z1", 0x23, 0x80, "r", "§14"),
    ("ACCEL_DATA_Z0", 0x24, 0x00, "r", "§14"),
    ("GYRO_DATA_X1", 0x25, 0x80, "r", "§14"),
    ("GYRO_DATA_X0", 0x26, 0x00, "r", "§14"),
    ("GYRO_DATA_Y1", 0x27, 0x80, "r", "§14"),
    ("GYRO_DATA_Y0", 0x28, 0x00, "r", "§14"),
    ("GYRO_DATA_Z1", 0x29, 0x80, "r", "§14"),
    ("GYRO_DATA_Z0", 0x2A, 0x00, "r", "§14"),
    ("TMST_FSYNCH", 0x2B, 0x00, "r", "§14"),
    ("TMST_FSYNCL", 0x2C, 0x00, "r", "§14"),
    ("INT_STATUS", 0x2D, 0x10, "rc", "§14"),
    ("FIFO_COUNTH", 0x2E, 0x00, "r", "§14"),
    ("FIFO_COUNTL", 0x2F, 0x00, "r", "§14"),
    ("FIFO_DATA", 0x30, 0x00, "r", "§14"),
    ("APEX_DATA0", 0x31, 0x00, "r", "§14"),
    ("APEX_DATA1", 0x32, 0x00, "r", "§14"),
    ("APEX_DATA2", 0x33, 0x00, "r", "§14"),
    ("APEX_DATA3", 0x34, 0x00, "r", "§14"),
    ("APEX_DATA4", 0x35, 0x00, "r", "§14"),
    ("APEX_DATA5", 0x36, 0x00, "r", "§14"),
    ("INT_STATUS2", 0x37, 0x00, "rc", "§14"),
    ("INT_STATUS3", 0x38, 0x00, "rc", "§14"),
    ("SIGNAL_PATH_RESET", 0x4B, 0x00, "w", "§14"),
    ("INTF_CONFIG0", 0x4C, 0x30, "rw", "§14"),
    ("INTF_CONFIG1", 0x4D, 0x91, "rw", "§14"),
    ("PWR_MGMT0", 0x4E, 0x00, "rw", "§14"),
    ("GYRO_CONFIG0", 0x4F, 0x06, "rw", "§14"),
    ("ACCEL_CONFIG0", 0x50, 0x06, "rw", "§14"),
    ("GYRO_CONFIG1", 0x51, 0x16, "rw", "§14"),
    ("GYRO_ACCEL_CONFIG0", 0x52, 0x11, "rw", "§14"),
    ("ACCEL_CONFIG1", 0x53, 0x0D, "rw", "§14"),
    ("TMST_CONFIG", 0x54, 0x23, "rw", "§14"),
    ("APEX_CONFIG0", 0x56, 0x82, "rw", "§14"),
    ("SMD_CONFIG", 0x57, 0x00, "rw", "§14"),
    ("FIFO_CONFIG1", 0x5F, 0x00, "rw", "§14"),
    ("FIFO_CONFIG2", 0x60, 0x00, "rw", "§14"),
    ("FIFO_CONFIG3", 0x61, 0x00, "rw", "§14"),
    ("FSYNC_CONFIG", 0x62, 0x10, "rw", "§14"),
    ("INT_CONFIG0", 0x63, 0x00, "rw", "§14"),
    ("INT_CONFIG1", 0x64, 0x10, "rw", "§14"),
    ("INT_SOURCE0", 0x65, 0x10, "rw", "§14"),
    ("INT_SOURCE1", 0x66, 0x00, "rw", "§14"),
    ("INT_SOURCE3", 0x68, 0x00, "rw", "§14"),
    ("INT_SOURCE4", 0x69, 0x00, "rw", "§14"),
    ("FIFO_LOST_PKT0", 0x6C, 0x00, "r", "§14"),
    ("FIFO_LOST_PKT1", 0x6D, 0x00, "r", "§14"),
    ("SELF_TEST_CONFIG", 0x70, 0x00, "rw", "§14"),
    ("WHO_AM_I", 0x75, WHO_AM_I_VALUE, "r", "§14"),
    ("REG_BANK_SEL", 0x76, 0x00, "rw", "§14"),
]
_BANK1 = [
    ("XG_ST_DATA", 0x5F, 0x00, "r", "§15"),   # factory gyroscope self-test codes (per part)
    ("YG_ST_DATA", 0x60, 0x00, "r", "§15"),
    ("ZG_ST_DATA", 0x61, 0x00, "r", "§15"),
    ("TMSTVAL0", 0x62, 0x00, "r", "§15"),
    ("TMSTVAL1", 0x63, 0x00, "r", "§15"),
    ("TMSTVAL2", 0x64, 0x00, "r", "§15"),
    ("REG_BANK_SEL", 0x76, 0x00, "rw", "§14"),
]
_BANK2 = [
    ("XA_ST_DATA", 0x3B, 0x00, "r", "§16"),   # factory accelerometer self-test codes (per part)
    ("YA_ST_DATA", 0x3C, 0x00, "r", "§16"),
    ("ZA_ST_DATA", 0x3D, 0x00, "r", "§16"),
    ("REG_BANK_SEL", 0x76, 0x00, "rw", "§14"),
]
_OTHER = [("REG_BANK_SEL", 0x76, 0x00, "rw", "§14")]

#: every modelled register, by (bank, addr)
REGISTERS: MappingProxyType = MappingProxyType({
    (bank, a): Reg(n, bank, a, r, acc, sec)
    for bank, table in ((0, _BANK0), (1, _BANK1), (2, _BANK2), (3, _OTHER), (4, _OTHER))
    for n, a, r, acc, sec in table})

#: bank-0 addresses by name (the data path's registers)
ADDR: MappingProxyType = MappingProxyType({n: a for n, a, *_ in _BANK0})

# INT_STATUS bits (§14)
DATA_RDY_INT = 0x08
RESET_DONE_INT = 0x10
# DEVICE_CONFIG (§14)
SOFT_RESET_CONFIG = 0x01
# SIGNAL_PATH_RESET (§14)
TMST_STROBE = 0x04
# SELF_TEST_CONFIG (§14)
EN_GX_ST, EN_GY_ST, EN_GZ_ST = 0x01, 0x02, 0x04
EN_AX_ST, EN_AY_ST, EN_AZ_ST = 0x08, 0x10, 0x20
ACCEL_ST_POWER = 0x40

#: ODR codes (GYRO_CONFIG0 / ACCEL_CONFIG0 bits 3:0, §14) -> Hz; 0 and 12..14 (gyroscope) reserved
ODR_HZ: MappingProxyType = MappingProxyType({
    1: 32000.0, 2: 16000.0, 3: 8000.0, 4: 4000.0, 5: 2000.0, 6: 1000.0, 7: 200.0, 8: 100.0, 9: 50.0,
    10: 25.0, 11: 12.5, 12: 6.25, 13: 3.125, 14: 1.5625, 15: 500.0})
#: GYRO_FS_SEL -> full scale °/s (§14); sensitivity 32768 / full scale LSB per °/s (§3.1 Table 1)
GYRO_FS_DPS = (2000.0, 1000.0, 500.0, 250.0, 125.0, 62.5, 31.25, 15.625)
#: ACCEL_FS_SEL -> full scale g (§14); sensitivity 32768 / full scale LSB per g (§3.2 Table 2)
ACCEL_FS_G = (16.0, 8.0, 4.0, 2.0, 16.0, 16.0, 16.0, 16.0)  # codes 4..7 reserved: taken as ±16 g
#: GYRO_ACCEL_CONFIG0 UI filter bandwidth code -> ODR divisor (§5.5, §14; low-noise mode)
UI_FILT_DIV = (2.0, 4.0, 5.0, 8.0, 10.0, 16.0, 20.0, 40.0)
