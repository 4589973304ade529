"""C chips that read a real part through its driver, in the loop: ``capsheet virtual --firmware c
--part icm42688p``.

Every chip is a `firmware_ref.chip.CFirmwareChip` (the C reference firmware) whose sensor is not a
source of finished counts but one link MCU's sensor stack: the C glue (firmware_ref/drivers/
link_sensors.c) over the C ICM-42688-P driver (icm42688p.c), over an SPI bus (`sil_bus.SilBus`)
served by the register emulator (`virtual_sheet.parts.icm42688p.ICM42688P`), fed with the truth the
virtual sheet computes for that link (specific force and rate, sensor frame)::

    physics (sheet) -> ICM42688P registers -> C driver -> C glue -> C chip -> protocol -> host

The HAL's read_axes / read_imu are the C glue's own functions, called with the chip's arguments
(through a thin ``extern "Python"`` that first runs the emulated link to the call's instant): the C
chip gets exactly what the glue answers, and a negative answer is its sensor fault (INVALID, FAULT).
The part's INT1 data-ready edge is timestamped (as a port's timer capture would) and is the record's
latch instant. ``icm42688p+mmc5983ma``: the MEMSIC MMC5983MA magnetometer on chip select 1 of the same
bus (its driver, firmware_ref/drivers/mmc5983ma.c, through the glue's capsheet_mag_driver_t), fed with
the sheet's field in the link's frame.

The link MCU's main loop runs between the chip's calls: at every call (SYNC, poll) the glue runs up
to ``now``, each step at the instant it asked for, the emulator's clock with it. The motion is the
truth at the call's instant, held until the next call.

Boot: the link MCU brings its sensors up (probe, reset, self-test, configuration: about 1.2 s of the
part's time) before its protocol stack starts, as a port's main() would: the MCU's clock (the
drivers', the part's) is the chip's plus ``boot_s``, and `PartChipFactory.bind` runs every link's
bring-up over those first ``boot_s`` at once. The chip's ``time_us`` is a difference of instants on
one clock and does not see the offset.

The truth reaches the parts as plain lists, converted once per instant for the whole sheet
(`TruthRows`): the emulators' arithmetic on 3 numbers is cheaper in floats than in numpy.
"""

from __future__ import annotations

from ._ffi import ffi, lib
from .chip import CFirmwareChip
from .sil_bus import SilBus

__all__ = ["PARTS", "PartChipFactory", "LinkSensors", "TruthRows"]

#: the parts a chip can read through its driver (``--part``)
PARTS = ("icm42688p", "icm42688p+mmc5983ma")
#: the magnetometer's measurement bandwidth code (Internal control 1 BW: 1 = 4 ms, within a 100 Hz SYNC)
MAG_BW = 1
#: how long a link MCU runs before its protocol stack starts: the part's bring-up with its self-test
BOOT_S = 1.5


def _us(now_s: float) -> int:
    return max(0, int(round(now_s * 1e6)))


def _rows(a) -> list:
    return a.tolist() if hasattr(a, "tolist") else [[float(x) for x in r] for r in a]


class TruthRows:
    """A truth's ``at(now_s)`` as lists (one ``[x, y, z]`` per link), converted once per instant and
    shared by every link of the sheet: the chips of one SYNC all ask for the same instant."""

    def __init__(self, truth) -> None:
        self.truth = truth
        self._t: float | None = None
        self._rows: tuple = ()

    def at(self, now_s: float) -> tuple:
        if now_s != self._t:
            self._rows = tuple(_rows(a) for a in self.truth.at(now_s))
            self._t = now_s
        return self._rows


class LinkSensors:
    """One link MCU's sensor stack: the parts, their bus and the C glue (module docstring)."""

    def __init__(self, part, truth, link: int, *, mag=None, self_test: bool = True,
                 boot_s: float = BOOT_S) -> None:
        self.part = part
        self.mag = mag
        self.boot_us = _us(boot_s)
        self.truth = truth
        self.rows: TruthRows | None = None   # the truth as lists (`PartChipFactory.bind` shares one)
        self.link = link
        self.self_test = bool(self_test)
        self.bus = SilBus(spi={0: part, **({1: mag} if mag is not None else {})})
        self.ls = ffi.new("capsheet_link_sensors_t *")
        self.mag_dev = self.mag_drv = None
        if mag is not None:
            self.mag_dev = ffi.new("mmc5983ma_t *")
            if lib.mmc5983ma_init(self.mag_dev, self.bus.c_bus, 1, MAG_BW) < 0:
                raise RuntimeError("mmc5983ma_init failed")
            self.mag_drv = ffi.new("capsheet_mag_driver_t *")
            lib.mmc5983ma_mag_driver(self.mag_dev, self.mag_drv)
        self.t_us = 0
        self._settled = False    # the bring-up is over (running or failed)
        self._drdy_told: float | None = None
        self.faults = 0          # reads the glue answered with a sensor fault
        self.chip = None

    def attach(self, chip: CFirmwareChip, c_chip) -> None:
        """Wire the glue to the chip's state (its CONFIG / CONFIG_IMU): `CFirmwareChip` calls it
        with its ``capsheet_chip_t *`` when built with this stack, and points its HAL at the glue."""
        self.chip = chip
        rc = lib.capsheet_link_sensors_init(self.ls, self.bus.c_bus, 0,
                                            self.mag_drv if self.mag_drv is not None else ffi.NULL,
                                            c_chip, self.self_test)
        if rc < 0:
            raise RuntimeError(f"capsheet_link_sensors_init failed: {rc}")

    def main_loop(self, now_s: float) -> None:
        """The link MCU's main loop between the chip's calls: a bring-up still running goes on; a
        new CONFIG / CONFIG_IMU that started a wait (a sensor turned on) is run again."""
        if not self._settled:
            self.run_to(now_s)
        elif lib.capsheet_link_sensors_poll(self.ls, self.t_us) > 0:
            self._settled = False

    def _feed(self, t_us: int) -> None:
        t = t_us * 1e-6
        self.part.advance(t)
        if self.mag is not None:
            self.mag.advance(t)
        d = self.part.drdy_s
        if d is not None and d != self._drdy_told:  # the INT1 edge, timestamped once
            self._drdy_told = d
            lib.capsheet_link_data_ready(self.ls, int(round(d * 1e6)))

    def boot(self) -> int:
        """The MCU's first ``boot_s``: the sensors' bring-up before the chip's clock starts."""
        return self.run_to_us(0)

    def run_to(self, now_s: float) -> int:
        return self.run_to_us(int(round(now_s * 1e6)))

    def run_to_us(self, chip_us: int) -> int:
        """The link MCU's main loop up to the chip's instant ``chip_us``; returns the MCU's, µs."""
        now_us = max(self.t_us, max(0, chip_us) + self.boot_us)
        if self.truth is not None:
            rows = self.rows
            if rows is None or rows.truth is not self.truth:
                rows = self.rows = TruthRows(self.truth)
            f, w, b = rows.at(max(0, chip_us) * 1e-6)
            link = self.link
            self.part.set_motion(f[link], w[link])
            if self.mag is not None:
                self.mag.set_field(b[link])
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


@ffi.def_extern()
def capsheet_py_part_read_axes(user, now_us, xyz, status):
    """HAL read_axes: the link runs to the SYNC's instant, then the C glue answers the chip."""
    chip = ffi.from_handle(user)
    try:
        ls = chip.sensor_stack
        rc = lib.capsheet_link_read_axes(ls.ls, ls.run_to_us(int(now_us)), xyz, status)
    except BaseException as exc:  # noqa: BLE001 - re-raised after the C call (chip.py's rule)
        chip.fail(exc)
        return -1
    if rc < 0:
        ls.faults += 1
    return rc


@ffi.def_extern()
def capsheet_py_part_read_imu(user, now_us, gyro_range, mag_range, want_mag, out):
    """HAL read_imu: the C glue's, its latch brought back to the chip's clock."""
    chip = ffi.from_handle(user)
    try:
        ls = chip.sensor_stack
        mcu_us = max(ls.t_us, int(now_us) + ls.boot_us)
        rc = lib.capsheet_link_read_imu(ls.ls, mcu_us, gyro_range, mag_range, want_mag, out)
        if rc >= 0:
            out.latch_us = max(0, int(out.latch_us) - ls.boot_us)
    except BaseException as exc:  # noqa: BLE001
        chip.fail(exc)
        return -1
    return rc


def _unused_source(*_args):
    raise RuntimeError("a part chip's HAL reads the C glue, not a counts source")


class PartChipFactory:
    """A `VirtualSheet` ``chip_factory``: C chips reading ``part`` through its driver.

    The parts' register emulators and the sheet's truth come from the caller (firmware_ref imports
    nothing of the simulator; ``host.cli.virtual.part_chip_factory`` wires the simulator's):
    ``imu_part(seed=...)`` and ``mag_part(seed=...)`` make one emulator, ``truth(sheet)`` an object
    whose ``at(now_s)`` gives every link's specific force (m/s²), rate (rad/s) and field (T), a
    function of the instant (it is asked once per instant, `TruthRows`).
    Build the sheet with it, then `bind` the sheet (its truth feeds the parts)::

        factory = PartChipFactory("icm42688p", imu_part=ICM42688P, mag_part=MMC5983MA, truth=SheetTruth)
        sheet = VirtualSheet(..., chip_factory=factory, sensors="accel+gyro")
        factory.bind(sheet)
    """

    def __init__(self, part: str = "icm42688p", *, imu_part, mag_part=None, truth,
                 self_test: bool = True) -> None:
        if part not in PARTS:
            raise ValueError(f"Unknown part {part!r} (expected one of {', '.join(PARTS)})")
        if part.endswith("+mmc5983ma") and mag_part is None:
            raise ValueError(f"Invalid mag_part: None (part {part} has a magnetometer)")
        self.part = part
        self.self_test = bool(self_test)
        self.imu_part, self.mag_part, self.make_truth = imu_part, mag_part, truth
        self.truth = None
        self.links: list[LinkSensors] = []
        self.pending: list[tuple[int, LinkSensors]] = []  # links built before `bind` told their places

    def bind(self, sheet) -> None:
        """The sheet whose truth feeds every part (after the sheet built its chips)."""
        self.truth = self.make_truth(sheet)
        rows = TruthRows(self.truth)
        for uid, ls in self.pending:
            ls.truth, ls.rows = self.truth, rows
            ls.link = sheet.link_of_uid[uid]
            ls.boot()
        self.pending.clear()

    def __call__(self, uid: int, sensor, *, seed: int = 0, sensors: str = "accel", imu=None, **kw):
        has_mag = self.part.endswith("+mmc5983ma")
        if ("mag" in sensors) != has_mag:
            raise ValueError(f"Invalid sensors {sensors!r} for part {self.part}: "
                             + ("accel+gyro+mag" if has_mag else "accel or accel+gyro (a 6-axis part)"))
        mag = self.mag_part(seed=seed + 0x5983) if has_mag else None
        ls = LinkSensors(self.imu_part(seed=seed), self.truth, 0, mag=mag, self_test=self.self_test)
        self.pending.append((uid, ls))
        chip = CFirmwareChip(uid, _unused_source, seed=seed, sensors=sensors,
                             imu=_unused_source if sensors != "accel" else None, sensor_stack=ls, **kw)
        self.links.append(ls)
        return chip
