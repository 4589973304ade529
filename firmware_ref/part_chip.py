"""C chips that read a real part through its driver, in the loop: ``capsheet virtual --firmware c
--part icm42688p``.

Every chip is a `firmware_ref.chip.CFirmwareChip` (the C reference firmware) whose sensor is not a
source of finished counts but one link MCU's sensor stack: the C glue (firmware_ref/drivers/
link_sensors.c) over the C ICM-42688-P driver (icm42688p.c), over an SPI bus (`sil_bus.SilBus`)
served by the register emulator (`virtual_sheet.parts.icm42688p.ICM42688P`), fed with the truth the
virtual sheet computes for that link (specific force and rate, sensor frame)::

    physics (sheet) -> ICM42688P registers -> C driver -> C glue -> C chip -> protocol -> host

The HAL's read_axes / read_imu hand the chip exactly what the C glue answers (a negative answer, a
sensor fault, becomes an INVALID reading: the chip enters FAULT). The part's INT1 data-ready edge is
timestamped (as a port's timer capture would) and is the record's latch instant.

The link MCU's main loop runs between the chip's calls: at every call (SYNC, poll) the glue runs up
to ``now``, each step at the instant it asked for, the emulator's clock with it. The motion is the
truth at the call's instant, held until the next call.

Boot: the link MCU brings its sensors up (probe, reset, self-test, configuration: about 1.2 s of the
part's time) before its protocol stack starts, as a port's main() would: the MCU's clock (the
drivers', the part's) is the chip's plus ``boot_s``, and `PartChipFactory.bind` runs every link's
bring-up over those first ``boot_s`` at once. The chip's ``time_us`` is a difference of instants on
one clock and does not see the offset.
"""

from __future__ import annotations

import math

import numpy as np

from protocol.constants import SampleStatus

from ._ffi import ffi, lib
from .chip import CFirmwareChip
from .sil_bus import SilBus

__all__ = ["PARTS", "PartChipFactory", "SheetTruth"]

#: the parts a chip can read through its driver (``--part``)
PARTS = ("icm42688p",)
#: how long a link MCU runs before its protocol stack starts: the part's bring-up with its self-test
BOOT_S = 1.5
_INVALID = int(SampleStatus.INVALID)


def _us(now_s: float) -> int:
    return max(0, int(round(now_s * 1e6)))


class SheetTruth:
    """Every link's specific force (m/s²) and rate (rad/s), sensor frame, at ``now_s``: the moving
    scene's exact truth (`imu_source.ImuSource`, at its grid instant), or a static shape's gravity."""

    def __init__(self, sheet) -> None:
        self.sheet = sheet
        self._at: float | None = None
        self._value: tuple[np.ndarray, np.ndarray] | None = None

    def at(self, now_s: float) -> tuple[np.ndarray, np.ndarray]:
        if self._at == now_s and self._value is not None:
            return self._value
        src = self.sheet.imu_source
        if src is not None:
            k = max(0, int(math.floor(now_s * src.grid_hz + 1e-9)))
            with src._lock:  # the source's own cache of solved instants
                e = src._truth(k)
            f, w = np.asarray(e.specific_force, dtype=float), np.asarray(e.angular_velocity, dtype=float)
        else:
            f = np.asarray(self.sheet._geometry(now_s)[2], dtype=float)
            w = np.zeros_like(f)
        self._at, self._value = now_s, (f, w)
        return self._value


class LinkSensors:
    """One link MCU's sensor stack: the part, its bus and the C glue (module docstring)."""

    def __init__(self, part, truth: SheetTruth | None, link: int, *, self_test: bool = True,
                 boot_s: float = BOOT_S) -> None:
        self.part = part
        self.boot_us = _us(boot_s)
        self.truth = truth
        self.link = link
        self.self_test = bool(self_test)
        self.bus = SilBus(spi={0: part})
        self.ls = ffi.new("capsheet_link_sensors_t *")
        self._xyz = ffi.new("int16_t[3]")
        self._st = ffi.new("uint8_t *")
        self._rd = ffi.new("capsheet_imu_reading_t *")
        self.t_us = 0
        self._settled = False    # the bring-up is over (running or failed)
        self._drdy_told: float | None = None
        self.faults = 0          # reads the glue answered with a sensor fault
        self.chip = None

    def attach(self, chip: CFirmwareChip) -> None:
        """Wire the glue to the chip's state (its CONFIG / CONFIG_IMU)."""
        self.chip = chip
        rc = lib.capsheet_link_sensors_init(self.ls, self.bus.c_bus, 0, ffi.NULL, chip._chip, self.self_test)
        if rc < 0:
            raise RuntimeError(f"capsheet_link_sensors_init failed: {rc}")

    def _feed(self, t_us: int) -> None:
        self.part.advance(t_us * 1e-6)
        d = self.part.drdy_s
        if d is not None and d != self._drdy_told:  # the INT1 edge, timestamped once
            self._drdy_told = d
            lib.capsheet_link_data_ready(self.ls, int(round(d * 1e6)))

    def boot(self) -> int:
        """The MCU's first ``boot_s``: the sensors' bring-up before the chip's clock starts."""
        return self.run_to(0.0)

    def run_to(self, now_s: float) -> int:
        """The link MCU's main loop up to the chip's ``now_s``; returns the MCU's instant reached, µs."""
        now_us = max(self.t_us, int(round(now_s * 1e6)) + self.boot_us)
        if self.truth is not None:
            f, w = self.truth.at(max(0.0, now_s))
            self.part.set_motion(f[self.link], w[self.link])
        if not self._settled:
            t = self.t_us
            while True:
                self._feed(t)
                rc = lib.capsheet_link_sensors_poll(self.ls, t)
                if rc <= 0 or t + rc > now_us:
                    break
                t += rc
            # running (0) or failed (< 0): the main loop has nothing to wait for; the reads poll the
            # glue themselves (a CONFIG is applied there)
            self._settled = rc <= 0
        self._feed(now_us)
        self.t_us = now_us
        return now_us

    def read_axes(self, now_s: float):
        now_us = self.run_to(now_s)
        if lib.capsheet_link_read_axes(self.ls, now_us, self._xyz, self._st) < 0:
            self.faults += 1
            return (0, 0, 0), _INVALID   # the chip sends INVALID and enters FAULT (§8.6)
        return (self._xyz[0], self._xyz[1], self._xyz[2]), self._st[0]

    def read_imu(self, now_s: float, gyro_range: int, mag_range: int):
        now_us = max(self.t_us, _us(now_s) + self.boot_us)
        if lib.capsheet_link_read_imu(self.ls, now_us, gyro_range, mag_range, False, self._rd) < 0:
            raise RuntimeError("read_imu after a valid read_axes failed")  # the glue cannot: same reading
        g = self._rd.gyro
        return (g[0], g[1], g[2]), None, int(self._rd.latch_us) - now_us


class PartChipFactory:
    """A `VirtualSheet` ``chip_factory``: C chips reading ``part`` through its driver.

    Build the sheet with it, then `bind` the sheet (its truth feeds the parts)::

        factory = PartChipFactory("icm42688p")
        sheet = VirtualSheet(..., chip_factory=factory, sensors="accel+gyro")
        factory.bind(sheet)
    """

    def __init__(self, part: str = "icm42688p", *, self_test: bool = True) -> None:
        if part not in PARTS:
            raise ValueError(f"Unknown part {part!r} (expected one of {', '.join(PARTS)})")
        self.part = part
        self.self_test = bool(self_test)
        self.truth: SheetTruth | None = None
        self.links: list[LinkSensors] = []
        self._pending: list[tuple[int, LinkSensors]] = []

    def bind(self, sheet) -> None:
        """The sheet whose truth feeds every part (after the sheet built its chips)."""
        self.truth = SheetTruth(sheet)
        for uid, ls in self._pending:
            ls.truth = self.truth
            ls.link = sheet.link_of_uid[uid]
            ls.boot()
        self._pending.clear()

    def __call__(self, uid: int, sensor, *, seed: int = 0, sensors: str = "accel", imu=None, **kw):
        from virtual_sheet.parts.icm42688p import ICM42688P
        if "mag" in sensors:
            raise ValueError(f"Invalid sensors {sensors!r} for part {self.part}: a 6-axis part "
                             "(accel or accel+gyro; no magnetometer part is wired yet)")
        ls = LinkSensors(ICM42688P(seed=seed), self.truth, 0, self_test=self.self_test)
        self._pending.append((uid, ls))
        chip = CFirmwareChip(uid, lambda now_s: ls.read_axes(now_s), seed=seed, sensors=sensors,
                             imu=(lambda now_s, gr, mr: ls.read_imu(now_s, gr, mr)) if sensors != "accel" else None,
                             **kw)
        ls.attach(chip)
        chip.link_sensors = ls
        inner_poll = chip.poll

        def poll(now_s: float):
            if not ls._settled:  # the link MCU's main loop: a bring-up still running goes on between SYNCs
                ls.run_to(now_s)
            elif lib.capsheet_link_sensors_poll(ls.ls, ls.t_us) > 0:
                ls._settled = False  # a new CONFIG / CONFIG_IMU started a wait (a sensor turned on)
            return inner_poll(now_s)
        chip.poll = poll
        self.links.append(ls)
        return chip
