"""TDK InvenSense ICM-42688-P, register level, over SPI: written from datasheet DS-000347.

The pinned seam (other tools drive the part this way)::

    part = ICM42688P(seed=1)
    part.advance(now_s)                       # the part's time: conversions on its own ODR clock
    part.set_motion(f_mps2, w_rps)            # specific force (m/s²) and rate (rad/s), sensor frame,
                                              # held until the next call
    rx = part.spi_transfer(bytes([0x80 | 0x75, 0]))   # one chip-select transaction: rx[1] == 0x47

What it models (section numbers of DS-000347; the register map in `icm42688p_regs`):

* **SPI** (§9): the first byte is the address, bit 7 set for a read; the address auto-increments for
  every further byte of the transaction, reads and writes alike; MISO is 0x00 during the address byte.
  A burst read sees one consistent state (conversions happen in `advance`, between transactions).
  (The banks are bytearrays whose write-only and reserved bytes stay 0, so a burst read that does not
  wrap past 0x7F is one slice; the clear-on-read registers it covers are cleared after it.)
* **Banks** (§13): REG_BANK_SEL (0x76 in every bank) selects bank 0..4; reset values, read-only,
  clear-on-read (INT_STATUS) and reserved registers (read 0x00, writes ignored) per `Reg.access`.
* **Reset** (§14 DEVICE_CONFIG): SOFT_RESET_CONFIG puts every register back to its reset value and
  the part answers nothing for 1 ms (reads 0x00, writes ignored); then INT_STATUS has RESET_DONE_INT.
  Power-on is the same, at t = 0.
* **Power modes** (§14 PWR_MGMT0; §3.1 Table 1, §3.2 Table 2): both sensors off after reset; a
  sensor turned on (low noise, or low power for the accelerometer, modelled with the low-noise figures;
  the gyroscope's standby gives no output) converts after its start-up time —
  30 ms gyroscope, 10 ms accelerometer; an off or starting sensor's data registers read −32768
  (§4.11), the temperature too while both are off.
* **Conversions** on the part's own ODR clock (GYRO_CONFIG0 / ACCEL_CONFIG0 ODR), which runs fast or
  slow by a per-part error within ``odr_tolerance`` (±1 %: *assumed*, see ODR_TOLERANCE); each sets
  INT_STATUS DATA_RDY_INT and raises INT1 (`drdy_s`, the time of the latest edge, for a port's
  timestamped data-ready interrupt).
* **Accelerometer** (§3.2 Table 2): sensitivity 32768 / full scale LSB per g (16384 at ±2 g … 2048 at
  ±16 g) with a per-part sensitivity error (±0.5 %, taken as 1 σ) and zero-g offset (±20 mg, 1 σ),
  white noise of 70 µg/√Hz over the UI filter's bandwidth (ODR / divisor, GYRO_ACCEL_CONFIG0).
* **Gyroscope** (§3.1 Table 1): 32768 / full scale LSB per °/s (16.4 at ±2000 … 2097.2 at ±15.625),
  sensitivity error ±0.5 % and zero-rate offset ±0.5 °/s (1 σ), 2.8 mdps/√Hz.
* **Saturation**: counts clip to −32768 … 32767.
* **Temperature** (§4.13; §14 TEMP_DATA1): TEMP_DATA = (T − 25 °C) · 132.48.
* **Self-test** (SELF_TEST_CONFIG; the response limits in firmware_ref/drivers/icm42688p_reg.h): an
  enabled axis adds its response, ST_OTP = 2620 · 1.01^(code − 1) LSB at ±250 °/s / ±2 g (scaled to the
  full scale in use), times a per-part factor in 0.9 … 1.1; the factory codes (bank 1 XG/YG/ZG_ST_DATA,
  bank 2 XA/YA/ZA_ST_DATA) are drawn per part. The accelerometer's needs ACCEL_ST_POWER as well.
* **Faults on demand** (`fault`): ``"no_answer"`` (MISO pulled up: every byte 0xFF), ``"stuck_bus"``
  (the transfer fails: `BusError`), ``"wrong_id"`` (WHO_AM_I reads 0x42, another part of the family),
  ``"self_test_fail"`` (the self-test response at a fifth of its code), ``"reset"`` (a brown-out: the
  part is back at its power-on state), ``"garbage"`` (every byte read is random: a broken line or a
  part answering out of turn); ``None`` clears the lasting ones.

Deliberately wrong variants for testing a driver (``miswire``): ``"bit_order"`` (every byte travels
LSB first, both ways), ``"read_bit"`` (the read bit's polarity inverted: bit 7 clear reads).
"""

from __future__ import annotations

import math
import struct

import numpy as np

from protocol.constants import G0

from . import icm42688p_regs as R

#: §3.2 Table 2 / §3.1 Table 1 figures
ACCEL_NOISE_G_RTHZ = 70e-6          # 70 µg/√Hz
GYRO_NOISE_DPS_RTHZ = 2.8e-3        # 2.8 mdps/√Hz
ACCEL_OFFSET_G = 0.020              # zero-g offset, board-level initial tolerance ±20 mg (1 σ here)
GYRO_OFFSET_DPS = 0.5               # zero-rate offset, initial tolerance ±0.5 °/s (1 σ here)
SENSITIVITY_TOLERANCE = 0.005       # ±0.5 % both sensors (1 σ here)
TEMP_LSB_PER_C = 132.48             # §4.13, §14 TEMP_DATA1
TEMP_ROOM_C = 25.0
GYRO_STARTUP_S = 0.030              # §3.1 Table 1
ACCEL_STARTUP_S = 0.010             # §3.2 Table 2
RESET_S = 0.001                     # §14 DEVICE_CONFIG: 1 ms after a soft reset
#: ODR tolerance of the part's own clock. *Assumed* ±1 %: this project could not confirm the
#: datasheet's figure for the internal clock in low-noise mode; a per-part value is drawn within it.
ODR_TOLERANCE = 0.01
ST_OTP_BASE = 2620.0                # LSB at FS_SEL 3 (±250 °/s, ±2 g) for code 1
FAULTS = ("no_answer", "stuck_bus", "wrong_id", "self_test_fail", "reset", "garbage")
MISWIRES = ("bit_order", "read_bit")

_WHO_AM_I = R.ADDR["WHO_AM_I"]
_INT_STATUS = R.ADDR["INT_STATUS"]
#: per bank, by address: the register (None: reserved or not modelled)
_BANK_REGS = tuple(tuple(R.REGISTERS.get((b, a)) for a in range(0x80)) for b in range(5))
_RESET = tuple(bytes(r.reset if r is not None and r.access != "w" else 0 for r in regs) for regs in _BANK_REGS)
# a write-only register reads 0x00 because its byte is never stored to: SIGNAL_PATH_RESET is the one
# (`ICM42688P._write` acts on it and returns)
assert [r.name for r in R.REGISTERS.values() if r.access == "w"] == ["SIGNAL_PATH_RESET"]
#: per bank, the clear-on-read addresses (INT_STATUS, INT_STATUS2, INT_STATUS3 in bank 0)
_CLEAR_ON_READ = tuple(tuple(a for a, r in enumerate(regs) if r is not None and r.access == "rc")
                       for regs in _BANK_REGS)
#: per bank, the span (first, last + 1) of its clear-on-read addresses ((0, 0): none)
_CLEAR_SPAN = tuple((c[0], c[-1] + 1) if c else (0, 0) for c in _CLEAR_ON_READ)
_SPI_READ = R.SPI_READ
_NAMES = tuple(tuple(r.name if r is not None and r.access not in ("r", "rc") else None for r in regs)
               for regs in _BANK_REGS)   # the writable registers' names (None: a write is ignored)
_BE16X3 = struct.Struct(">hhh")   # three data registers' pairs, high byte first (§14 *_DATA_*1, *0)
_REV8 = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))


class BusError(RuntimeError):
    """The SPI transfer did not complete (a stuck line): the bus driver reports a bus error."""


def _clip16(v: float) -> int:
    """Round half to even (as np.rint) and clip to the 16-bit two's complement range."""
    r = round(v)
    return -32768 if r < -32768 else (32767 if r > 32767 else r)


_DEG_PER_RAD = 180.0 / math.pi   # np.degrees' factor: x · (180/π), the same double for every x
_SCALES: dict = {}


def _scale(gyro: bool, cfg: int, filt: int) -> tuple[float, float]:
    """(sensitivity LSB per g or °/s, noise σ in LSB) for the accelerometer's or gyroscope's CONFIG0
    and UI filter code: 32768 / full scale (§3.1 Table 1, §3.2 Table 2) and the noise density over
    ODR / divisor (§5.5). Computed once per setting: the same doubles as at every conversion."""
    key = (gyro, cfg, filt & 0x07)
    v = _SCALES.get(key)
    if v is None:
        full_scale, noise_rthz = (R.GYRO_FS_DPS, GYRO_NOISE_DPS_RTHZ) if gyro else (R.ACCEL_FS_G, ACCEL_NOISE_G_RTHZ)
        sens = 32768.0 / full_scale[cfg >> 5]
        bw = R.ODR_HZ.get(cfg & 0x0F, 1000.0) / R.UI_FILT_DIV[filt & 0x07]
        v = _SCALES[key] = (sens, noise_rthz * math.sqrt(bw) * sens)
    return v


def st_otp(code: int) -> float:
    """Factory self-test response in LSB at ±250 °/s / ±2 g for a factory code (0: no code)."""
    return ST_OTP_BASE * 1.01 ** (code - 1) if code else 0.0


class ICM42688P:
    """One ICM-42688-P on an SPI bus (see the module docstring).

    Parameters
    ----------
    seed : int
        Seed of the part's own errors and noise (``Generator(MT19937(seed))``).
    temperature_c : float
        Die temperature, °C.
    miswire : str or None
        A deliberately wrong part for driver tests (``"bit_order"``, ``"read_bit"``).
    odr_error : float or None
        The part's clock error (fraction; None: drawn within ±ODR_TOLERANCE).
    """

    def __init__(self, seed: int = 0, *, temperature_c: float = 25.0, miswire: str | None = None,
                 odr_error: float | None = None) -> None:
        if miswire is not None and miswire not in MISWIRES:
            raise ValueError(f"Unknown miswire {miswire!r} (expected one of {', '.join(MISWIRES)})")
        self._rng = np.random.Generator(np.random.MT19937(int(seed)))
        g = self._rng
        self.temperature_c = float(temperature_c)
        self.miswire = miswire
        self.odr_error = float(g.uniform(-ODR_TOLERANCE, ODR_TOLERANCE) if odr_error is None else odr_error)
        # the part's own errors (hidden truth), fixed for its life
        self.accel_offset_g = g.normal(0.0, ACCEL_OFFSET_G, 3)
        self.accel_scale = 1.0 + g.normal(0.0, SENSITIVITY_TOLERANCE, 3)
        self.gyro_offset_dps = g.normal(0.0, GYRO_OFFSET_DPS, 3)
        self.gyro_scale = 1.0 + g.normal(0.0, SENSITIVITY_TOLERANCE, 3)
        self.gyro_st_codes = tuple(int(c) for c in g.integers(20, 90, 3))
        self.accel_st_codes = tuple(int(c) for c in g.integers(20, 90, 3))
        self.st_factor = g.uniform(0.9, 1.1, 6)
        # the same, as plain floats for the per-conversion arithmetic
        self._a_scale, self._a_off = self.accel_scale.tolist(), self.accel_offset_g.tolist()
        self._g_scale, self._g_off = self.gyro_scale.tolist(), self.gyro_offset_dps.tolist()
        self._a_st = [st_otp(c) * float(f) for c, f in zip(self.accel_st_codes, self.st_factor[3:])]
        self._g_st = [st_otp(c) * float(f) for c, f in zip(self.gyro_st_codes, self.st_factor[:3])]
        self._fault: str | None = None
        # a variant that answers registers its own way (a `_read` of its own) is read register by register
        self._burst = type(self)._read is ICM42688P._read
        self._temp_for, self._temp_data = None, 0   # the temperature TEMP_DATA was computed for
        self._f_g = [0.0, 0.0, 1.0]   # specific force in g, rate in °/s: the held motion as floats
        self._w_dps = [0.0, 0.0, 0.0]
        self.now_s = 0.0
        self.transactions = 0
        self.conversions = 0
        #: time of the latest INT1 data-ready edge (None: none yet)
        self.drdy_s: float | None = None
        self._power_on(0.0)

    # ---- state ---------------------------------------------------------------------------------

    def _power_on(self, t: float) -> None:
        # one bytearray per bank, at the reset values; a write-only or reserved byte is never stored
        # to (it stays 0: what it reads)
        self._banks = [bytearray(r) for r in _RESET]
        self._bank = 0
        self._busy_until = t + RESET_S
        self._banks[0][_INT_STATUS] = 0   # RESET_DONE appears when the reset completes
        self._reset_done_pending = True
        self._accel_on_at: float | None = None      # when the accelerometer's start-up ends
        self._gyro_on_at: float | None = None
        self._next_tick: float | None = None        # the next conversion on the part's clock
        self._period = 0.0
        self._set_data_off(accel=True, gyro=True)
        for i, c in enumerate(self.gyro_st_codes):
            self._banks[1][0x5F + i] = c
        for i, c in enumerate(self.accel_st_codes):
            self._banks[2][0x3B + i] = c

    def _reg0(self, name: str) -> int:
        return self._banks[0][R.ADDR[name]]

    def _set16(self, name: str, value: int) -> None:
        a = R.ADDR[name]
        u = value & 0xFFFF
        self._banks[0][a] = u >> 8
        self._banks[0][a + 1] = u & 0xFF

    def _set_data_off(self, *, accel: bool, gyro: bool) -> None:
        for axis in "XYZ":
            if accel:
                self._set16(f"ACCEL_DATA_{axis}1", -32768)
            if gyro:
                self._set16(f"GYRO_DATA_{axis}1", -32768)
        if accel and gyro:
            self._set16("TEMP_DATA1", -32768)

    # ---- the seam ------------------------------------------------------------------------------

    def set_motion(self, specific_force_mps2, rate_rps) -> None:
        """Specific force (m/s², shape (3,)) and angular rate (rad/s, shape (3,)), sensor frame; held.

        Lists of 3 numbers take a path without numpy (its per-call cost is most of the work at size
        3); the arithmetic is the same, value for value (x / G0, and x · 180/π as np.degrees)."""
        f, w = specific_force_mps2, rate_rps
        if type(f) is list and type(w) is list and len(f) == 3 and len(w) == 3:
            try:
                f_g = [float(f[0]) / G0, float(f[1]) / G0, float(f[2]) / G0]
                w_dps = [float(w[0]) * _DEG_PER_RAD, float(w[1]) * _DEG_PER_RAD, float(w[2]) * _DEG_PER_RAD]
                self._f_g, self._w_dps = f_g, w_dps
                return
            except TypeError:   # not 3 numbers: numpy's reading of them below
                pass
        f = np.asarray(f, dtype=float).reshape(-1)
        w = np.asarray(w, dtype=float).reshape(-1)
        if f.shape != (3,) or w.shape != (3,):
            raise ValueError(f"Expected specific force and rate of shape (3,), got {f.shape} and {w.shape}.")
        self._f_g = (f / G0).tolist()
        self._w_dps = np.degrees(w).tolist()

    def advance(self, now_s: float) -> None:
        """Run the part's clock to `now_s` (s; never backwards): reset completion, start-ups, conversions."""
        now_s = float(now_s)
        if now_s < self.now_s:
            raise ValueError(f"Time runs forwards: advance({now_s}) after {self.now_s}")
        self.now_s = now_s
        if self._reset_done_pending and now_s >= self._busy_until:
            self._reset_done_pending = False
            self._banks[0][_INT_STATUS] |= R.RESET_DONE_INT
        if self._next_tick is None or now_s < self._next_tick:
            return
        n = math.floor((now_s - self._next_tick) / self._period) + 1
        last = self._next_tick + (n - 1) * self._period
        self._next_tick = last + self._period
        self.conversions += n - 1   # the earlier ones were overwritten unread
        self._convert(last)

    def fault(self, kind: str | None) -> None:
        """Inject a fault (`FAULTS`) from now on; None clears the lasting ones."""
        if kind is not None and kind not in FAULTS:
            raise ValueError(f"Unknown fault {kind!r} (expected one of {', '.join(FAULTS)})")
        if kind == "reset":
            self._power_on(self.now_s)
            return
        self._fault = kind

    def spi_transfer(self, tx: bytes) -> bytes:
        """One chip-select transaction, full duplex: len(tx) bytes in, as many out."""
        tx = bytes(tx)
        self.transactions += 1
        if self._fault is None and self.miswire is None and tx and self.now_s >= self._busy_until:
            if tx[0] & _SPI_READ:   # the common case first: a read of a healthy part, as below
                return self._read_burst(tx[0] & 0x7F, len(tx) - 1)
        if self._fault == "stuck_bus":
            raise BusError("ICM-42688-P: SPI transfer did not complete (stuck bus)")
        if not tx:
            return b""
        if self._fault == "no_answer":
            return b"\xff" * len(tx)
        if self._fault == "garbage":   # MISO noise: random bytes, whatever was asked
            return bytes([0]) + self._rng.integers(0, 256, len(tx) - 1, dtype=np.uint8).tobytes()
        if self.miswire == "bit_order":
            tx = tx.translate(_REV8)
        read = bool(tx[0] & R.SPI_READ)
        if self.miswire == "read_bit":
            read = not read
        addr = tx[0] & 0x7F
        n = len(tx) - 1
        if self.now_s < self._busy_until:   # in reset: reads 0x00, writes ignored
            out = bytes(n + 1)
        elif read:   # conversions happen in advance(), never within a transaction: one consistent state
            out = self._read_burst(addr, n)
        else:
            for i in range(1, n + 1):
                self._write((addr + i - 1) & 0x7F, tx[i])
            out = bytes(n + 1)
        return out.translate(_REV8) if self.miswire == "bit_order" else out

    # ---- register access -----------------------------------------------------------------------

    def _read_burst(self, addr: int, n: int) -> bytes:
        """MISO of a burst read of ``n`` registers from ``addr`` on in the selected bank: 0x00 (the
        address byte), then each register's value; the clear-on-read ones it covered are cleared
        after it (WHO_AM_I reads 0x42 under the ``wrong_id`` fault)."""
        bank = self._bank
        regs = self._banks[bank]
        end = addr + n
        if end > 0x80 or not self._burst:   # wraps past 0x7F (the clear-on-read order matters), or a variant
            return b"\x00" + bytes(self._read(bank, (addr + i) & 0x7F) for i in range(n))
        out = b"\x00" + regs[addr:end]
        lo, hi = _CLEAR_SPAN[bank]
        if addr < hi and end > lo:
            for a in _CLEAR_ON_READ[bank]:
                if addr <= a < end:
                    regs[a] = 0
        if bank == 0 and addr <= _WHO_AM_I < end and self._fault == "wrong_id":
            k = _WHO_AM_I - addr + 1
            out = out[:k] + b"\x42" + out[k + 1:]
        return out

    def _read(self, bank: int, addr: int) -> int:
        regs = self._banks[bank]
        value = regs[addr]   # 0 for a write-only or reserved register (never stored to)
        if bank == 0 and addr == _WHO_AM_I and self._fault == "wrong_id":
            value = 0x42
        if addr in _CLEAR_ON_READ[bank]:
            regs[addr] = 0
        return value

    def _write(self, addr: int, value: int) -> None:
        name = _NAMES[self._bank][addr]
        if name is None:   # reserved, read only or clear on read: ignored
            return
        if name == "REG_BANK_SEL":
            self._bank = value & 0x07 if (value & 0x07) <= 4 else self._bank
            for b in range(5):
                self._banks[b][0x76] = self._bank
            return
        if name == "DEVICE_CONFIG" and value & R.SOFT_RESET_CONFIG:
            self._power_on(self.now_s)
            return
        if name == "SIGNAL_PATH_RESET":
            if value & R.TMST_STROBE:   # latch the part's µs timestamp into bank 1 TMSTVAL0..2 (20 bits)
                ts = int(self.now_s * 1e6 * (1.0 + self.odr_error)) & 0xFFFFF
                self._banks[1][0x62], self._banks[1][0x63], self._banks[1][0x64] = (
                    ts & 0xFF, (ts >> 8) & 0xFF, ts >> 16)
            return
        old = self._banks[self._bank][addr]
        self._banks[self._bank][addr] = value
        if self._bank == 0 and name in ("PWR_MGMT0", "ACCEL_CONFIG0", "GYRO_CONFIG0"):
            self._reconfigure(name, old, value)

    def _reconfigure(self, name: str, old: int, new: int) -> None:
        t = self.now_s
        if name == "PWR_MGMT0":
            accel_was, accel_is = (old & 3) >= 2, (new & 3) >= 2
            gyro_was, gyro_is = ((old >> 2) & 3) == 3, ((new >> 2) & 3) == 3
            if accel_is and not accel_was:
                self._accel_on_at = t + ACCEL_STARTUP_S
            if not accel_is:
                self._accel_on_at = None
                self._set_data_off(accel=True, gyro=False)
            if gyro_is and not gyro_was:
                self._gyro_on_at = t + GYRO_STARTUP_S
            if not gyro_is:
                self._gyro_on_at = None
                self._set_data_off(accel=False, gyro=True)
            if not accel_is and not gyro_is:
                self._set_data_off(accel=True, gyro=True)
        # the conversion clock: the accelerometer's ODR when it is on, else the gyroscope's
        on = [x for x in (self._accel_on_at, self._gyro_on_at) if x is not None]
        if not on:
            self._next_tick = None
            return
        code = (self._reg0("ACCEL_CONFIG0") if self._accel_on_at is not None else self._reg0("GYRO_CONFIG0")) & 0x0F
        self._period = 1.0 / (R.ODR_HZ.get(code, 1000.0) * (1.0 + self.odr_error))
        if self._next_tick is None:   # the clock starts with the first sensor's start-up end
            self._next_tick = max(min(on), t)

    # ---- conversions ---------------------------------------------------------------------------

    def _put16(self, addr: int, value: int) -> None:
        regs = self._banks[0]
        regs[addr] = (value >> 8) & 0xFF
        regs[addr + 1] = value & 0xFF

    def _convert(self, t: float) -> None:
        """One conversion of every sensor that is on and started (scalar arithmetic: per-call numpy
        costs more than the three axes' math)."""
        regs = self._banks[0]
        st = regs[0x70]                            # SELF_TEST_CONFIG
        bw_sel = regs[0x52]                        # GYRO_ACCEL_CONFIG0
        st_fail = 0.2 if self._fault == "self_test_fail" else 1.0
        accel = self._accel_on_at is not None and t >= self._accel_on_at
        gyro = self._gyro_on_at is not None and t >= self._gyro_on_at
        # the noise: the stream's next normals, the accelerometer's then the gyroscope's, in one draw
        # (the generator gives the same normals in one call as in two, and one call costs less)
        z = self._rng.standard_normal(6 if accel and gyro else 3).tolist() if accel or gyro else None
        j = 0                                      # the next unused normal of z
        if accel:
            cfg = regs[0x50]                       # ACCEL_CONFIG0
            sens, sd = _scale(False, cfg, bw_sel >> 4)
            f, k, off = self._f_g, self._a_scale, self._a_off
            c = [(f[0] * k[0] + off[0]) * sens + sd * z[j], (f[1] * k[1] + off[1]) * sens + sd * z[j + 1],
                 (f[2] * k[2] + off[2]) * sens + sd * z[j + 2]]
            j += 3                                 # the gyroscope's normals follow the accelerometer's
            if st & R.ACCEL_ST_POWER and st & (R.EN_AX_ST | R.EN_AY_ST | R.EN_AZ_ST):
                for i in range(3):
                    if st & (R.EN_AX_ST << i):
                        c[i] += self._a_st[i] * st_fail * sens / 16384.0
            _BE16X3.pack_into(regs, 0x1F, _clip16(c[0]), _clip16(c[1]), _clip16(c[2]))   # ACCEL_DATA_X1 ... Z0
        if gyro:
            cfg = regs[0x4F]                       # GYRO_CONFIG0
            sens, sd = _scale(True, cfg, bw_sel)
            w, k, off = self._w_dps, self._g_scale, self._g_off
            c = [(w[0] * k[0] + off[0]) * sens + sd * z[j], (w[1] * k[1] + off[1]) * sens + sd * z[j + 1],
                 (w[2] * k[2] + off[2]) * sens + sd * z[j + 2]]
            if st & (R.EN_GX_ST | R.EN_GY_ST | R.EN_GZ_ST):
                for i in range(3):
                    if st & (R.EN_GX_ST << i):
                        c[i] += self._g_st[i] * st_fail * sens / 131.072
            _BE16X3.pack_into(regs, 0x25, _clip16(c[0]), _clip16(c[1]), _clip16(c[2]))   # GYRO_DATA_X1 ... Z0
        if accel or gyro:
            if not regs[0x4E] & 0x20:              # PWR_MGMT0 TEMP_DIS clear
                tc = self.temperature_c
                if tc != self._temp_for:           # TEMP_DATA for this temperature, computed once
                    self._temp_for, self._temp_data = tc, _clip16((tc - TEMP_ROOM_C) * TEMP_LSB_PER_C)
                self._put16(0x1D, self._temp_data)
            regs[0x2D] |= R.DATA_RDY_INT           # INT_STATUS
            self.drdy_s = t
            self.conversions += 1

    # ---- inspection (tests, tools) -------------------------------------------------------------

    def register(self, bank: int, addr: int) -> int:
        """A register's content, without the side effects of a bus read."""
        return self._banks[bank][addr] if 0 <= bank <= 4 and 0 <= addr <= 0x7F else 0

    @property
    def bank(self) -> int:
        return self._bank
