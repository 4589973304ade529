"""MEMSIC MMC5983MA 3-axis AMR magnetometer, emulated register by register.

Everything here follows the datasheet: MEMSIC "MMC5983MA ±8 Gauss, High Performance 3-axis Magnetic
Sensor", Rev A, formal release 4/3/2019 (it has no document number; cited as "DS p.N, section").
Its register facts were cross-checked against public drivers written from it (SparkFun's MMC5983MA
Arduino library, Kris Winer's MMC5983MA sketches). Where the datasheet is silent the emulator says
so beside the choice it made (``# not in the datasheet``).

Why this part (for docs/hardware.md)
------------------------------------
The 9-axis link uses the **MEMSIC MMC5983MA** beside the TDK ICM-42688-P. Of the three candidates
(MMC5983MA, ST LIS2MDL, Bosch BMM350) it is the one whose SPI port is **4-wire from power-up**
(SDI and SDO apart, up to 10 MHz, DS p.4-7), so it shares the ICM-42688-P's full-duplex SPI bus on a
second chip select: one SPI peripheral and four shared lines per link, the same read bit (bit 7 of
the first byte, DS p.6) and the same burst reads. The LIS2MDL starts in 3-wire SPI: a separate SDO
needs a half-duplex write of its CFG_REG_C 4WSPI bit first (ST's platform-independent lis2mdl
driver), at every power-up and reset, on a bus wired for full duplex; its output is 16 bits at
1.5 mG/LSB. The BMM350 speaks I2C and I3C only (Bosch's SensorAPI, Zephyr's bindings): a second bus
per link. The MMC5983MA's 18-bit output (16384 counts/G, ±8 G, DS p.2) covers the protocol's ±4 and
±8 gauss range codes with bits to spare; its 0.4-1.2 mG RMS noise (DS p.2) is far below the Earth
field's 250-650 mG; its **SET/RESET** strap (DS p.18) measures and removes the bridge offset (its
drift over -40..105 °C is then 3 mG) without a calibration rotation, and restores the sensor after
a field over 10 G (a magnet near the sheet). It is AEC-Q100 qualified (DS p.1), sold on cheap
breakout boards (SparkFun's among them), and its datasheet is public: every register fact the
driver and this emulator use is in it.

Wiring: VDD and VDDIO 2.8-3.6 V (DS p.2: a 3.0-3.3 V link rail serves both parts); a 10 µF low-ESR
capacitor at CAP for the SET/RESET current (DS p.11); SPI_CS on its own MCU pin, SCK/SDI/SDO shared
with the ICM-42688-P. SCK idles high while CS is high (DS p.5): SPI mode 3, which the ICM-42688-P also
takes. INT is optional (the driver polls Meas_M_Done in the same burst as the data).

The seam (pinned: other tools use it this way)
----------------------------------------------
``MMC5983MA(seed=...)`` with ``.spi_transfer(tx) -> bytes`` (one chip-select transaction, full
duplex), ``.i2c_write_read(tx, n) -> bytes`` (the same registers over I2C at address 0x30),
``.set_field(field_t)`` (3-vector in tesla, the part's axes — the marking's axes after a SET,
DS p.9 — held until the next call) and ``.advance(now_s)`` (the part's time, monotonic, from its
power-on at 0 s). Faults: ``.inject(name)`` / ``.clear_faults()``. Bus misuse (a write to a
read-only register, TM_M with TM_T, a command during SET/RESET, ...) is counted in ``.events``.

Model
-----
* Registers (DS p.13-16): Xout0..XYZout2 and Tout read only, Status R/W (a 1 written to
  Meas_M_Done / Meas_T_Done clears it), Internal control 0..3 write only, Product ID1 0x2F = 0x30.
  A read of a write-only register answers 0x00, whatever was written (the datasheet gives no read
  value: a driver must keep its own copy). Addresses with no register read 0x00 and ignore writes.
* Power-on and SW_RST (DS p.15): 10 ms during which the part does not answer (SDO undriven, reads
  the bus's idle level) and ignores writes; then every register is at its reset value and
  OTP_Rd_Done is set (the OTP was read).
* A field measurement (TM_M, or each tick of continuous mode) takes the BW code's measurement time
  (DS p.15: 8, 4, 2, 0.5 ms) on the part's own clock; Meas_M_Done goes to 0 at its start and to 1
  at its end, when the data registers change. Continuous mode (Cmm_en with CM_Freq not 000) starts
  one every 1/f (1, 10, 20, 50, 100, 200, 1000 Hz, DS p.16) on that clock, never two at once.
* The part's clock runs fast or slow by ``clock_error`` (drawn from ±3 % — not in the datasheet,
  which gives every rate and time as typical).
* Output per axis (DS p.2, p.13, p.18): unsigned 18-bit, ``131072 + 16384 · (p · S · B + offset +
  noise)`` with B in gauss, clamped to 0..262143 (±8 G). ``p`` is +1 after SET and -1 after RESET
  (DS p.18: "Output1 = +H + Offset", "Output2 = -H + Offset"). ``S`` is the sensitivity matrix:
  a gain within ±5 % per axis (Sensitivity accuracy, DS p.2) and cross-axis terms within ±0.8 %
  (Transverse sensitivity). ``offset`` is the null-field output, drawn within ±0.25 G of the
  datasheet's 0.5 G (DS p.2, Null field output); every SET or RESET moves it by up to 1 mG (SET/RESET
  repeatability, DS p.2). ``noise`` is Gaussian with the BW code's total RMS noise (0.4, 0.6, 0.8,
  1.2 mG, DS p.2). A field over 10 G (Disturbing field, DS p.2 note 6; p.10) flips the film:
  ``p`` changes sign until the next SET or RESET.
* 16-bit operation (DS p.13) is the top 16 bits of the same registers: nothing to emulate.
* Temperature (DS p.14, p.2): TM_T measures it; Tout = (T + 75 °C) / 0.8 °C, clamped to 0..255.
  How long TM_T takes is not in the datasheet: the emulator takes the BW code's measurement time.
* SET / RESET (DS p.15) last 500 ns each; Auto_SR_en (one-shot): a SET before each measurement; with
  En_prd_set and Cmm_en: a SET every Prd_set measurements (DS p.16) — the datasheet's few words on
  these, as the emulator reads them.
* St_enp / St_enm (DS p.16): an extra field from the internal coil, of a size the datasheet does not
  give; the emulator adds ``self_test_field_g`` per axis (+ for St_enp, - for St_enm).
* SPI (DS p.5-8): the first byte is RW (bit 7), don't care (bit 6), address (bits 5..0); the
  answer's first byte is undriven (the bus's idle level, ``idle``), then one register per byte from
  the address on, the address pointer moving by one (and, not in the datasheet, wrapping from 0x3F
  to 0x00). Spi_3w (DS p.8) moves the answer to SDI: on a 4-wire bus SDO stays undriven.
* Faults on demand (``inject``): ``"no_answer"`` (the part is gone: SDO undriven, writes lost),
  ``"stuck_bus"`` (SDO stuck low: every byte 0x00), ``"wrong_id"`` (Product ID1 reads 0x31),
  ``"otp_fail"`` (OTP_Rd_Done never sets: the self-test's memory check fails), ``"dead_axis"``
  (the X bridge is open: its output sits at the rail), ``"frozen"`` (measurements start and never
  finish).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field as dc_field

import numpy as np

# --- register map (DS p.13 "Register map") ---
XOUT0, XOUT1, YOUT0, YOUT1, ZOUT0, ZOUT1, XYZOUT2, TOUT = range(8)
STATUS = 0x08
INTERNAL_CONTROL_0, INTERNAL_CONTROL_1, INTERNAL_CONTROL_2, INTERNAL_CONTROL_3 = 0x09, 0x0A, 0x0B, 0x0C
PRODUCT_ID_1 = 0x2F
PRODUCT_ID_1_VALUE = 0x30  # DS p.16 "Product ID1", reset value 0011 0000
I2C_ADDR = 0x30  # DS p.9 "Ordering guide", 7-bit address 0110000
READ_BIT = 0x80  # DS p.6 "SPI Read": bit 0 (the first, MSB) is 1
ADDR_MASK = 0x3F  # DS p.5: bits 2-7 are AD(5:0)

# Status (DS p.14)
MEAS_M_DONE, MEAS_T_DONE, OTP_READ_DONE = 0x01, 0x02, 0x10
# Internal control 0 (DS p.14-15)
TM_M, TM_T, INT_MEAS_DONE_EN, SET, RESET, AUTO_SR_EN, OTP_READ = 0x01, 0x02, 0x04, 0x08, 0x10, 0x20, 0x40
# Internal control 1 (DS p.15)
BW_MASK, X_INHIBIT, YZ_INHIBIT, SW_RST = 0x03, 0x04, 0x18, 0x80
# Internal control 2 (DS p.15-16)
CM_FREQ_MASK, CMM_EN, PRD_SET_SHIFT, EN_PRD_SET = 0x07, 0x08, 4, 0x80
# Internal control 3 (DS p.16)
ST_ENP, ST_ENM, SPI_3W = 0x02, 0x04, 0x40

POWER_ON_S = 10e-3  # DS p.15 SW_RST: "The power on time is 10mS"
SET_RESET_S = 500e-9  # DS p.15 Set/Reset: "for 500ns"
MEAS_TIME_S = (8e-3, 4e-3, 2e-3, 0.5e-3)  # DS p.15 Internal Control 1, BW1 BW0 = 00, 01, 10, 11
CM_FREQ_HZ = (0.0, 1.0, 10.0, 20.0, 50.0, 100.0, 200.0, 1000.0)  # DS p.16 CM_Freq[2:0]
PRD_SET_MEASUREMENTS = (1, 25, 75, 100, 250, 500, 1000, 2000)  # DS p.16 Prd_set[2:0]
NOISE_RMS_MG = (0.4, 0.6, 0.8, 1.2)  # DS p.2 Total RMS noise, BW = 00, 01, 10, 11
COUNTS_PER_GAUSS = 16384  # DS p.2 Sensitivity, 18 bits operation
NULL_FIELD_COUNTS = 131072  # DS p.2 Null field output, 18 bits operation
RAW_MAX = (1 << 18) - 1
FULL_SCALE_G = 8.0  # DS p.2 Field range
NULL_FIELD_MAX_G = 0.5  # DS p.2 Null field output
SENSITIVITY_ACCURACY = 0.05  # DS p.2 Sensitivity accuracy, 5 %
TRANSVERSE_SENSITIVITY = 0.008  # DS p.2 Transverse sensitivity, 0.8 %
SET_RESET_REPEATABILITY_G = 1e-3  # DS p.2 SET/RESET repeatability, 1 mG
DISTURBING_FIELD_G = 10.0  # DS p.2 Disturbing field (note 6), p.10 Theory of operation
TOUT_ZERO_C, TOUT_C_PER_LSB = -75.0, 0.8  # DS p.14 Tout; p.2 Temperature sensor output
#: numpy's uniform(lo, hi) is lo + (hi - lo) * U with U = random(): the step of a SET/RESET drawn that way
_SR_LOW, _SR_RANGE = -SET_RESET_REPEATABILITY_G, SET_RESET_REPEATABILITY_G - -SET_RESET_REPEATABILITY_G
CLOCK_TOLERANCE = 0.03  # not in the datasheet (its rates and times are typical): the emulator's choice
GAUSS_PER_TESLA = 1e4

FAULTS = ("no_answer", "stuck_bus", "wrong_id", "otp_fail", "dead_axis", "frozen")


class BusNak(RuntimeError):
    """No acknowledge on I2C (the part is gone or booting): a bus error, as a port's I2C driver reports it."""


_WRITE_ONLY = frozenset((INTERNAL_CONTROL_0, INTERNAL_CONTROL_1, INTERNAL_CONTROL_2, INTERNAL_CONTROL_3))
_READ_ONLY = frozenset(range(8)) | {PRODUCT_ID_1}
_BLOCK_END = STATUS + 1   # Xout0 .. Tout and Status: registers a read leaves as they are (one burst)


@dataclass
class Events:
    """Bus misuse and notable moments, counted (never raised): what a logic analyser would flag."""

    write_to_read_only: int = 0      #: a write to Xout0..Tout or Product ID1 (ignored)
    write_to_reserved: int = 0       #: a write to an address with no register (ignored)
    read_of_write_only: int = 0      #: a read of Internal control 0..3 (answers 0x00)
    tm_m_with_tm_t: int = 0          #: TM_M and TM_T in one write (DS p.14: never both; neither starts)
    command_while_busy: int = 0      #: TM_M or TM_T while a measurement runs (ignored)
    command_during_set_reset: int = 0  #: a measurement asked for within 500 ns of SET/RESET (carried out after it)
    ignored_while_booting: int = 0   #: a transaction during the 10 ms power-on time
    empty_transaction: int = 0       #: a chip-select transaction with no byte
    measurements: int = 0            #: field measurements finished
    sets: int = 0                    #: SET operations (commanded or automatic)
    resets: int = 0                  #: RESET operations
    log: list = dc_field(default_factory=list)  #: (time_s, what) for the misuse above, the first 100


class MMC5983MA:
    """One MMC5983MA, fed a magnetic field, answering SPI (and I2C) transactions.

    Parameters
    ----------
    seed : int
        Seeds the part's sample of its tolerances (offset, sensitivity, clock) and its noise
        (``np.random.Generator(np.random.MT19937(seed))``).
    clock_error, offset_g, gain, cross : optional
        Override the drawn tolerances: the clock's relative error (0.01 runs 1 % fast); the
        null-field offset, shape (3,), gauss; the per-axis gain, shape (3,) (1 = nominal); the
        cross-axis sensitivity, shape (3, 3) off-diagonal terms (diagonal ignored).
    noise : bool
        False: no noise (for tests that type exact register values).
    self_test_field_g : float
        The coil's field with St_enp / St_enm (not given by the datasheet).
    idle : int
        What an undriven SDO reads (a pull-up: 0xFF).
    temperature_c : float
        The die temperature until `set_temperature`.
    """

    def __init__(self, seed: int = 0, *, clock_error: float | None = None, offset_g=None, gain=None, cross=None,
                 noise: bool = True, self_test_field_g: float = 0.1, idle: int = 0xFF,
                 temperature_c: float = 25.0) -> None:
        self._rng = np.random.Generator(np.random.MT19937(seed))
        r = self._rng
        self.clock_error = (float(r.uniform(-CLOCK_TOLERANCE, CLOCK_TOLERANCE)) if clock_error is None
                            else float(clock_error))
        # the null-field offset as 3 floats (`offset_g` shows it as an array): per-measurement
        # arithmetic in plain floats, the same doubles as numpy's on 3-vectors, without its per-call cost
        self._offset = (r.uniform(-0.25, 0.25, 3) if offset_g is None else np.asarray(offset_g, float).reshape(3)).tolist()
        g = r.uniform(-SENSITIVITY_ACCURACY, SENSITIVITY_ACCURACY, 3) + 1.0 if gain is None else np.asarray(gain, float)
        x = (r.uniform(-TRANSVERSE_SENSITIVITY, TRANSVERSE_SENSITIVITY, (3, 3)) if cross is None
             else np.asarray(cross, float).reshape(3, 3))
        self.sensitivity = np.array(x, float)
        np.fill_diagonal(self.sensitivity, np.asarray(g, float).reshape(3))
        self.sensitivity.flags.writeable = False   # the part's for life (and ``S B`` is kept per field)
        self._sf_key: list | None = None   # the field (gauss) whose ``sensitivity @ field`` is in _sf
        self._sf: list = [0.0, 0.0, 0.0]
        self.noise = bool(noise)
        self.self_test_field_g = float(self_test_field_g)
        if not 0 <= idle <= 0xFF:
            raise ValueError(f"idle must be a byte, got {idle}")
        self.idle = int(idle)
        self.temperature_c = float(temperature_c)
        self.events = Events()
        self.faults: set[str] = set()
        # a variant that answers registers its own way (a `_read` of its own) is read register by register
        self._burst = type(self)._read is MMC5983MA._read
        self._field_g = [0.0, 0.0, 0.0]   # gauss, the part's axes
        self._now = 0.0
        self._power_up(0.0)

    # ------------------------------------------------------------------ the seam
    def set_field(self, field_t) -> None:
        """The field the part now feels: 3-vector, tesla, the part's axes; held until the next call.

        A list of 3 numbers takes a path without numpy (the same products, value for value)."""
        f = None
        if type(field_t) is list and len(field_t) == 3:
            try:
                f = [float(x) for x in field_t]
            except TypeError:   # not 3 numbers: numpy's reading of them below
                f = None
        if f is None:
            a = np.asarray(field_t, dtype=float)
            f = a.tolist() if a.shape == (3,) else None
        if f is None or not (math.isfinite(f[0]) and math.isfinite(f[1]) and math.isfinite(f[2])):
            raise ValueError(f"Expected `field_t` to be 3 finite numbers (tesla), got {field_t!r}.")
        fg = self._field_g = [f[0] * GAUSS_PER_TESLA, f[1] * GAUSS_PER_TESLA, f[2] * GAUSS_PER_TESLA]
        if max(abs(fg[0]), abs(fg[1]), abs(fg[2])) > DISTURBING_FIELD_G and not self._upset:
            self._polarity = -self._polarity if self._polarity else -1  # the film flips (DS p.10)
            self._upset = True  # once: it stays flipped until a SET or RESET

    def set_temperature(self, temperature_c: float) -> None:
        """The die temperature, °C (read through TM_T / Tout)."""
        self.temperature_c = float(temperature_c)

    def advance(self, now_s: float) -> None:
        """Run the part up to `now_s` (its time since power-on, seconds; never backwards)."""
        now_s = float(now_s)
        if now_s < self._now:
            raise ValueError(f"advance: time went backwards, {now_s} s after {self._now} s")
        while True:
            t = self._next_event_s()
            if t is None or t > now_s:
                break
            if t > self._now:
                self._now = t
            self._run_event(t)
        self._now = now_s

    def spi_transfer(self, tx: bytes) -> bytes:
        """One chip-select transaction, full duplex: as many bytes back as went out (DS p.5-7)."""
        tx = bytes(tx)
        if not tx:
            self._misuse("empty_transaction", "an empty chip-select transaction")
            return b""
        faults = self.faults
        if faults and "stuck_bus" in faults:
            return bytes(len(tx))
        booting = self._now < self._boot_end
        if booting or (faults and "no_answer" in faults):
            if booting and "no_answer" not in faults:
                self._misuse("ignored_while_booting", "a transaction during the power-on time")
            return bytes([self.idle]) * len(tx)
        addr = tx[0] & ADDR_MASK
        if tx[0] & READ_BIT:
            if self._ctrl[3] & SPI_3W:  # the answer went out on SDI (3-wire, DS p.8): SDO undriven
                for i in range(1, len(tx)):   # (the reads' side effects still happen)
                    self._read((addr + i - 1) & ADDR_MASK)
                return bytes([self.idle]) * len(tx)
            end = addr + len(tx) - 1
            if end <= _BLOCK_END and self._burst:   # data and Status: one burst of registers a read does not change
                return bytes([self.idle]) + self._block()[addr:end]
            out = bytearray([self.idle])
            for i in range(1, len(tx)):
                out.append(self._read((addr + i - 1) & ADDR_MASK))
        else:
            for i in range(1, len(tx)):
                self._write((addr + i - 1) & ADDR_MASK, tx[i])
            out = bytes([self.idle]) * len(tx)
        return bytes(out)

    def i2c_write_read(self, tx: bytes, n: int) -> bytes:
        """I2C at 0x30 (DS p.17): `tx` = register address then bytes to write; then `n` bytes read.

        A part that does not acknowledge (gone, stuck bus, booting) raises `BusNak`."""
        tx = bytes(tx)
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        if "no_answer" in self.faults or "stuck_bus" in self.faults or self._booting():
            raise BusNak("MMC5983MA: no acknowledge at I2C address 0x30")
        if tx:
            self._pointer = tx[0] & ADDR_MASK
            for b in tx[1:]:
                self._write(self._pointer, b)
                self._pointer = (self._pointer + 1) & ADDR_MASK
        out = bytearray()
        for _ in range(n):
            out.append(self._read(self._pointer))
            self._pointer = (self._pointer + 1) & ADDR_MASK
        return bytes(out)

    def inject(self, fault: str) -> None:
        """Break the part on demand: one of `FAULTS`."""
        if fault not in FAULTS:
            raise ValueError(f"unknown fault {fault!r}: one of {', '.join(FAULTS)}")
        self.faults.add(fault)
        if fault == "otp_fail":
            self._status &= ~OTP_READ_DONE

    def clear_faults(self) -> None:
        """Mend every injected fault (a part that comes back: the driver must still report it)."""
        self.faults.clear()

    # ------------------------------------------------------------------ introspection for tests
    @property
    def now_s(self) -> float:
        return self._now

    @property
    def polarity(self) -> int:
        """+1 after SET, -1 after RESET, 0 before either (the film's state)."""
        return self._polarity

    @property
    def int_pin(self) -> bool:
        """INT (DS p.11: active high) — a finished measurement with INT_meas_done_en written."""
        return bool(self._int_en and self._status & (MEAS_M_DONE | MEAS_T_DONE))

    def raw_outputs(self) -> tuple[int, int, int]:
        """The 18-bit outputs as the data registers hold them."""
        return tuple(int(v) for v in self._out)

    @property
    def offset_g(self) -> np.ndarray:
        """The null-field offset now, gauss, shape (3,) (it moves at every SET or RESET)."""
        return np.array(self._offset)

    @offset_g.setter
    def offset_g(self, value) -> None:
        self._offset = np.asarray(value, float).reshape(3).tolist()

    # ------------------------------------------------------------------ internals
    def _misuse(self, name: str, what: str) -> None:
        setattr(self.events, name, getattr(self.events, name) + 1)
        if len(self.events.log) < 100:
            self.events.log.append((self._now, what))

    def _tick_s(self, nominal_s: float) -> float:
        return nominal_s / (1.0 + self.clock_error)

    def _power_up(self, t: float) -> None:
        self._boot_end = t + self._tick_s(POWER_ON_S)
        self._status = 0
        self._ctrl = [0, 0, 0, 0]
        self._int_en = False
        self._auto_sr = False
        self._out = [0, 0, 0]  # data registers' reset value: not given; 0
        self._tout = 0
        self._polarity = 0  # the film's magnetisation: not known until a SET or RESET
        self._upset = False
        self._meas_end: float | None = None      # a field measurement in progress ends then
        self._temp_end: float | None = None      # a temperature measurement in progress ends then
        self._cm_next: float | None = None       # continuous mode's next start
        self._sr_busy_until = t                  # SET/RESET current flows until then
        self._cm_count = 0
        self._pointer = 0
        self._booted = False

    def _booting(self) -> bool:
        return self._now < self._boot_end

    def _next_event_s(self) -> float | None:
        t = None if self._booted else self._boot_end
        for x in (self._meas_end, self._temp_end, self._cm_next):
            if x is not None and (t is None or x < t):
                t = x
        return t

    def _run_event(self, t: float) -> None:
        if not self._booted and t >= self._boot_end:
            self._booted = True
            if "otp_fail" not in self.faults:
                self._status |= OTP_READ_DONE
            return
        if self._meas_end is not None and t >= self._meas_end:
            self._meas_end = None
            if "frozen" not in self.faults:
                self._finish_field()
            else:
                self._meas_end = float("inf")
            return
        if self._temp_end is not None and t >= self._temp_end:
            self._temp_end = None
            code = round((self.temperature_c - TOUT_ZERO_C) / TOUT_C_PER_LSB)
            self._tout = min(255, max(0, code))
            self._status |= MEAS_T_DONE
            return
        if self._cm_next is not None and t >= self._cm_next:
            freq = CM_FREQ_HZ[self._ctrl[2] & CM_FREQ_MASK]
            self._cm_next = t + self._tick_s(1.0 / freq)
            if self._meas_end is None:  # never two at once
                if self._auto_sr and self._ctrl[2] & EN_PRD_SET:
                    if self._cm_count % PRD_SET_MEASUREMENTS[(self._ctrl[2] >> PRD_SET_SHIFT) & 7] == 0:
                        self._set_reset(+1)
                self._cm_count += 1
                self._start_field(t)

    def _start_field(self, t: float) -> None:
        self._status &= ~MEAS_M_DONE
        self._meas_end = t + self._tick_s(MEAS_TIME_S[self._ctrl[1] & BW_MASK])

    def _finish_field(self) -> None:
        """The measurement's outputs, axis by axis in plain floats: the same operations, in the same
        order, as on numpy 3-vectors (p · (S B), + offset, + self-test field, + noise, rounded half
        to even, clamped), so the same counts. ``S B`` stays numpy's ``@`` (its summation is BLAS's,
        which a sum in Python does not reproduce to the last bit), computed once per field."""
        bw = self._ctrl[1] & BW_MASK
        p = self._polarity
        if self._sf_key != self._field_g:
            self._sf = (self.sensitivity @ np.array(self._field_g)).tolist()
            self._sf_key = self._field_g
        st = 0.0
        if self._ctrl[3] & ST_ENP:
            st += self.self_test_field_g
        if self._ctrl[3] & ST_ENM:
            st -= self.self_test_field_g
        off = self._offset
        g = [p * s + o + st for s, o in zip(self._sf, off)]
        if self.noise:
            z = self._rng.normal(0.0, NOISE_RMS_MG[bw] * 1e-3, 3).tolist()
            g = [a + b for a, b in zip(g, z)]
        raw = []
        for v in g:
            c = round(NULL_FIELD_COUNTS + COUNTS_PER_GAUSS * v)   # round half to even, as np.rint
            raw.append(0 if c < 0 else (RAW_MAX if c > RAW_MAX else c))
        if "dead_axis" in self.faults:
            raw[0] = RAW_MAX
        c1, out = self._ctrl[1], self._out   # an inhibited channel is not measured
        self._out = [out[0] if c1 & X_INHIBIT else raw[0], out[1] if c1 & YZ_INHIBIT else raw[1],
                     out[2] if c1 & YZ_INHIBIT else raw[2]]
        self._status |= MEAS_M_DONE
        self.events.measurements += 1

    def _set_reset(self, polarity: int) -> None:
        self._polarity = polarity
        self._upset = False
        self._sr_busy_until = self._now + self._tick_s(SET_RESET_S)
        if self.noise:
            # within ±SET_RESET_REPEATABILITY_G: uniform(-r, r, 3), the same doubles without its checks
            u = self._rng.random(3).tolist()
            self._offset = [a + (_SR_LOW + _SR_RANGE * b) for a, b in zip(self._offset, u)]
        if polarity > 0:
            self.events.sets += 1
        else:
            self.events.resets += 1

    def _block(self) -> bytes:
        """Xout0 .. Tout and Status (DS p.13-14) as the part answers them: the 18-bit outputs' bits
        17..10 and 9..2, then XYZout2 with each output's bits 1..0."""
        x, y, z = self._out
        return bytes(((x >> 10) & 0xFF, (x >> 2) & 0xFF, (y >> 10) & 0xFF, (y >> 2) & 0xFF,
                      (z >> 10) & 0xFF, (z >> 2) & 0xFF, ((x & 3) << 6) | ((y & 3) << 4) | ((z & 3) << 2),
                      self._tout, self._status))

    def _read(self, addr: int) -> int:
        if addr <= ZOUT1:
            v = self._out[addr // 2]
            return (v >> 10) & 0xFF if addr % 2 == 0 else (v >> 2) & 0xFF
        if addr == XYZOUT2:
            x, y, z = (v & 3 for v in self._out)
            return (x << 6) | (y << 4) | (z << 2)
        if addr == TOUT:
            return self._tout
        if addr == STATUS:
            return self._status
        if addr in _WRITE_ONLY:
            self._misuse("read_of_write_only", f"read of write-only register 0x{addr:02X}")
            return 0x00
        if addr == PRODUCT_ID_1:
            return 0x31 if "wrong_id" in self.faults else PRODUCT_ID_1_VALUE
        return 0x00

    def _write(self, addr: int, value: int) -> None:
        if addr == STATUS:
            self._status &= ~(value & (MEAS_M_DONE | MEAS_T_DONE))  # write 1 to clear (DS p.14)
        elif addr == INTERNAL_CONTROL_0:
            self._write_ctrl0(value)
        elif addr == INTERNAL_CONTROL_1:
            if value & SW_RST:
                self._power_up(self._now)  # like power-up (DS p.15)
                return
            self._ctrl[1] = value & 0x1F
        elif addr == INTERNAL_CONTROL_2:
            self._ctrl[2] = value
            freq = CM_FREQ_HZ[value & CM_FREQ_MASK]
            if value & CMM_EN and freq > 0:
                if self._cm_next is None:
                    self._cm_count = 0
                    self._cm_next = self._now  # the first measurement now
            else:
                self._cm_next = None
        elif addr == INTERNAL_CONTROL_3:
            self._ctrl[3] = value & (ST_ENP | ST_ENM | SPI_3W)
        elif addr in _READ_ONLY:
            self._misuse("write_to_read_only", f"write of 0x{value:02X} to read-only register 0x{addr:02X}")
        else:
            self._misuse("write_to_reserved", f"write of 0x{value:02X} to reserved address 0x{addr:02X}")

    def _write_ctrl0(self, value: int) -> None:
        self._int_en = bool(value & INT_MEAS_DONE_EN)
        self._auto_sr = bool(value & AUTO_SR_EN)
        if value & OTP_READ and "otp_fail" not in self.faults:
            self._status |= OTP_READ_DONE
        if value & SET:
            self._set_reset(+1)
        elif value & RESET:
            self._set_reset(-1)
        if value & TM_M and value & TM_T:
            self._misuse("tm_m_with_tm_t", "TM_M and TM_T written together")
            return
        if value & (TM_M | TM_T):
            if self._meas_end is not None or self._temp_end is not None:
                self._misuse("command_while_busy", "a measurement asked for while one runs")
                return
            start = self._now
            if self._now < self._sr_busy_until and not value & (SET | RESET):
                self._misuse("command_during_set_reset", "a measurement asked for during SET/RESET")
                start = self._sr_busy_until
            elif value & (SET | RESET):
                start = self._sr_busy_until  # one write with both: the measurement follows the pulse
            if value & TM_M:
                if self._auto_sr and not value & (SET | RESET):
                    self._set_reset(+1)
                    start = self._sr_busy_until
                self._start_field(start)
            else:
                self._status &= ~MEAS_T_DONE
                self._temp_end = start + self._tick_s(MEAS_TIME_S[self._ctrl[1] & BW_MASK])
