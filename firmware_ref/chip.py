"""`CFirmwareChip`: the C reference firmware behind the chip interface of protocol/chip_interface.py.

Same constructor and methods as `virtual_sheet.chip.ChipModel`, so a virtual sheet runs every chip
on the C firmware (software in the loop, ``capsheet virtual --firmware c``). The HAL is Python:
the sensor source is read at SYNC, sent frames are collected and returned, calibration storage is
a per-chip list that survives RESET (like flash) but not a new instance.

Time: ``now_s`` (float seconds) is passed to C as integer microseconds, ``round(now_s * 1e6)``.

6/9-axis chips (docs §16): ``sensors="accel+gyro"`` or ``"accel+gyro+mag"`` with an ``imu`` source, as
`virtual_sheet.chip.ChipModel` takes them: the chip reports GYRO (MAG) and SAMPLE_TIME, and the C HAL's
``read_imu`` reads the source — its ``time_us`` becomes the latch instant ``now_us + time_us`` that the
firmware turns back into the record's ``time_us``.
"""

from __future__ import annotations

from protocol.can import CanFrame
from protocol.chip_interface import DEFAULT_CAPABILITIES, Out, SensorSource, check_chip_args
from protocol.messages import Capability, ChipState

from ._ffi import ffi, lib

__all__ = ["CFirmwareChip", "Out", "SensorSource", "DEFAULT_CAPABILITIES", "FIRMWARE_VERSION", "FirmwareError",
           "C_MUTANTS", "mutant_library", "SENSOR_CAPABILITIES"]

FIRMWARE_VERSION = (lib.CAPSHEET_FW_VERSION_MAJOR, lib.CAPSHEET_FW_VERSION_MINOR, lib.CAPSHEET_FW_VERSION_PATCH)

#: the mutants of the test build (capsheet_fw.h ``capsheet_mutant_t``), by name: ``dead_sensor`` ...
C_MUTANTS: tuple[str, ...] = tuple(
    name[len("CAPSHEET_MUT_"):].lower() for name in sorted(
        (n for n in dir(lib) if n.startswith("CAPSHEET_MUT_") and n not in ("CAPSHEET_MUT_NONE", "CAPSHEET_MUT_COUNT")),
        key=lambda n: getattr(lib, n)))


#: INFO capability bits a chip gets by its ``sensors`` (docs §16), as `virtual_sheet.chip.ChipModel` adds them
SENSOR_CAPABILITIES = {"accel": Capability.NONE, "accel+gyro": Capability.GYRO | Capability.SAMPLE_TIME,
                       "accel+gyro+mag": Capability.GYRO | Capability.MAG | Capability.SAMPLE_TIME}


class FirmwareError(RuntimeError):
    """The C firmware returned an error code (a HAL failure or a broken invariant)."""


def _us(now_s: float) -> int:
    return max(0, int(round(now_s * 1e6)))


class CFirmwareChip:
    """One chip running firmware_ref/src/chip.c.

    Parameters are those of `virtual_sheet.chip.ChipModel`: ``uid`` (64-bit), ``sensor``
    (``now_s -> ((x, y, z) ±2 g ADC counts, SampleStatus bits)``), ``transport`` ("serial" or
    "can"), ``fd`` (CAN FD capable), ``capabilities`` (INFO bits; CAN_FD is added when ``fd``),
    ``calibration`` (factory ``(offset_q4, sensitivity)`` per axis, in the calibration store when
    the chip has CAL_STORAGE) and ``seed`` (unused: the firmware is deterministic).
    ``rx_buffer`` is the serial receive buffer in bytes (default CAPSHEET_MAX_ENCODED_SIZE, 1029:
    every frame the spec allows, so the chip's ``rx_errors`` count the same frames as the Python
    model's; the C build's own default, CAPSHEET_RX_BUFFER_SIZE, is 64).
    ``sensors`` ("accel", "accel+gyro", "accel+gyro+mag") and ``imu`` (``(now_s, gyro_range,
    mag_range) -> ((gx, gy, gz), (mx, my, mz) or None, time_us)``, needed for anything but "accel") as
    `virtual_sheet.chip.ChipModel`.
    """

    def __init__(self, uid: int, sensor: SensorSource, *, transport: str = "serial", fd: bool = False,
                 capabilities: int = DEFAULT_CAPABILITIES,
                 calibration: tuple[tuple[int, float], ...] = ((0, 1024.0),) * 3, seed: int = 0,
                 rx_buffer: int | None = None, mutant: str | None = None, sensors: str = "accel",
                 imu=None, sensor_stack=None) -> None:
        check_chip_args(uid, transport, calibration)
        if sensors not in SENSOR_CAPABILITIES:
            raise ValueError(f"Invalid sensors: {sensors!r} (expected one of {', '.join(SENSOR_CAPABILITIES)})")
        if sensors != "accel" and imu is None:
            raise ValueError(f"Invalid imu: None (sensors {sensors!r} need an imu source)")
        capabilities = int(capabilities) | int(SENSOR_CAPABILITIES[sensors])
        if mutant is None:
            ffi_, lib_ = ffi, lib
        else:
            ffi_, lib_ = mutant_library()
            if mutant not in C_MUTANTS:
                raise ValueError(f"Invalid mutant {mutant!r} (known: {', '.join(C_MUTANTS)})")
        self._ffi, self._lib = ffi_, lib_
        self.mutant = mutant
        self.uid = uid
        self.sensor = sensor
        self.transport = transport
        self.fd = bool(fd)
        self.seed = seed
        self.sensors = sensors
        self.imu = imu
        self.capabilities = Capability(int(capabilities) | (Capability.CAN_FD if fd else 0))
        stored = 1 if self.capabilities & Capability.CAL_STORAGE else 0
        #: the chip's non-volatile calibration: (offset_q4, sensitivity, stored flag) per axis
        self.cal_store = [(int(o), float(s), stored) for o, s in calibration]
        #: the gyro/mag calibration elements stored (§17): element -> float32 bits
        self.cal_imu_store: dict[int, int] = {}
        self._out: list[Out] = []
        self._exc: BaseException | None = None
        self._handle = self._ffi.new_handle(self)
        self._hal = self._ffi.new("capsheet_hal_t *")
        self._hal.user = self._handle
        self._hal.read_axes = self._lib.capsheet_py_read_axes
        self._hal.send_bytes = self._lib.capsheet_py_send_bytes
        self._hal.send_can = self._lib.capsheet_py_send_can
        self._hal.read_uid = self._lib.capsheet_py_read_uid
        self._hal.cal_load = self._lib.capsheet_py_cal_load
        self._hal.cal_store = self._lib.capsheet_py_cal_store
        self._hal.cal_imu_load = self._lib.capsheet_py_cal_imu_load
        self._hal.cal_imu_store = self._lib.capsheet_py_cal_imu_store
        self._hal.read_imu = self._lib.capsheet_py_read_imu if imu is not None else self._ffi.NULL
        cfg = self._ffi.new("capsheet_chip_config_t *")
        cfg.transport = self._lib.CAPSHEET_TRANSPORT_CAN if transport == "can" else self._lib.CAPSHEET_TRANSPORT_SERIAL
        cfg.can_fd = self.fd
        cfg.capabilities = int(capabilities) & 0xFFFF
        self._cfg = cfg
        self._rx_cap = rx_buffer or self._lib.CAPSHEET_MAX_ENCODED_SIZE
        self._rx = self._ffi.new("uint8_t[]", self._rx_cap)
        self._chip = self._ffi.new("capsheet_chip_t *")
        rc = self._lib.capsheet_chip_init(self._chip, cfg, self._hal, self._rx if transport == "serial" else self._ffi.NULL,
                                    self._rx_cap if transport == "serial" else 0)
        if rc < 0:
            raise FirmwareError(f"capsheet_chip_init failed: {rc}")
        #: a link MCU's sensor stack (`firmware_ref.part_chip.LinkSensors`), or None: the HAL's
        #: read_axes / read_imu are then its C glue's, and its main loop runs before every poll
        self.sensor_stack = sensor_stack
        if sensor_stack is not None:
            sensor_stack.attach(self, self._chip)
            self._hal.read_axes = self._lib.capsheet_py_part_read_axes
            if self._hal.read_imu != self._ffi.NULL:
                self._hal.read_imu = self._lib.capsheet_py_part_read_imu
        if mutant is not None:
            self._chip.mutant = getattr(lib_, f"CAPSHEET_MUT_{mutant.upper()}")

    # ------------------------------------------------------------------ state, read from C
    @property
    def node(self) -> int:
        return int(self._chip.node)

    @property
    def state(self) -> ChipState:
        return ChipState(self._chip.state)

    @property
    def link(self) -> int | None:
        return int(self._chip.link) if self._chip.has_link else None

    @property
    def rx_errors(self) -> int:
        return int(self._chip.rx_errors)

    @property
    def missed_syncs(self) -> int:
        return int(self._chip.missed_syncs)

    @property
    def last_counter(self) -> int | None:
        """The last SYNC counter answered in this stream (None after START)."""
        return int(self._chip.last_sync) if self._chip.have_sync else None

    @property
    def prev_node(self) -> int | None:
        """BOOT: the provisional id of the round before, which still takes an ASSIGN (§3.3)."""
        return int(self._chip.prev_node) if self._chip.has_prev and self._chip.state == 0 else None

    @property
    def salt(self) -> int:
        return int(self._chip.salt)

    @property
    def powered(self) -> bool:
        return bool(self._chip.powered)

    @property
    def imu_config(self) -> tuple[int, int, int, int]:
        """CONFIG_IMU in use (§16.2): ``(format, gyro_range, mag_range, flags)``."""
        c = self._chip
        return int(c.imu_format), int(c.gyro_range), int(c.mag_range), int(c.imu_flags)

    # ------------------------------------------------------------------ the interface
    def _run(self, rc: int) -> list[Out]:
        out, self._out = self._out, []
        exc, self._exc = self._exc, None
        if exc is not None:
            raise exc
        if rc < 0:
            raise FirmwareError(f"C firmware returned {rc}")
        return out

    def power_on(self, now_s: float) -> list[Out]:
        """Boot: ANNOUNCE then INFO from the provisional node id."""
        return self._run(self._lib.capsheet_chip_power_on(self._chip, _us(now_s)))

    def handle(self, frame: Out, now_s: float, decoded=None) -> list[Out]:
        """React to one frame heard on the bus (``decoded`` is ignored: the C firmware decodes)."""
        if isinstance(frame, CanFrame):
            if self.transport != "can":
                return []
            data = bytes(frame.data)
            rc = self._lib.capsheet_chip_rx_can(self._chip, frame.arbitration_id & 0xFFFFFFFF, True, bool(frame.is_fd),
                                          data, len(data), _us(now_s))
        else:
            if self.transport != "serial":
                return []
            data = bytes(frame)
            rc = self._lib.capsheet_chip_rx_bytes(self._chip, data, len(data), _us(now_s))
        return self._run(rc)

    def feed(self, data: bytes, now_s: float) -> list[Out]:
        """Serial only: any chunk of received bytes (frames may span calls)."""
        return self._run(self._lib.capsheet_chip_rx_bytes(self._chip, bytes(data), len(data), _us(now_s)))

    def poll(self, now_s: float) -> list[Out]:
        """Time-driven output: re-ANNOUNCE (BOOT), STATUS heartbeat (assigned). With a sensor stack,
        the link MCU's main loop runs up to ``now_s`` first."""
        if self.sensor_stack is not None:
            self.sensor_stack.main_loop(now_s)
        return self._run(self._lib.capsheet_chip_poll(self._chip, _us(now_s)))

    def fail(self, exc: BaseException) -> None:
        """An exception raised inside a HAL callback: kept, and raised when the C call returns."""
        self._exc = exc

    def fault(self) -> None:
        """The sensor stopped answering: an assigned chip enters FAULT now (as ChipModel.fault)."""
        self._lib.capsheet_chip_sensor_fault(self._chip)

    def __repr__(self) -> str:
        return (f"CFirmwareChip(uid=0x{self.uid:016X}, node=0x{self.node:04X}, state={self.state.name}, "
                f"link={self.link})")


# ---------------------------------------------------------------------------------------------
# HAL callbacks: C -> Python. An exception is kept and re-raised when the C call returns.
# ---------------------------------------------------------------------------------------------

def _register(ffi_) -> None:
    """Define the HAL callbacks (``extern "Python"``) of one cffi module."""

    def chip(user) -> CFirmwareChip:
        return ffi_.from_handle(user)

    @ffi_.def_extern()
    def capsheet_py_read_axes(user, now_us, xyz, status):
        c = chip(user)
        try:
            (x, y, z), st = c.sensor(now_us / 1e6)
            xyz[0], xyz[1], xyz[2] = int(x), int(y), int(z)
            status[0] = int(st) & 0xF
            return 0
        except BaseException as exc:  # noqa: BLE001 - re-raised after the C call
            c.fail(exc)
            return -1

    @ffi_.def_extern()
    def capsheet_py_read_imu(user, now_us, gyro_range, mag_range, want_mag, out):
        c = chip(user)
        try:
            g, m, t_us = c.imu(now_us / 1e6, int(gyro_range), int(mag_range))
            out.gyro[0], out.gyro[1], out.gyro[2] = (int(v) for v in g)
            if want_mag:
                out.mag[0], out.mag[1], out.mag[2] = (int(v) for v in m)
            out.latch_us = max(0, int(now_us) + int(t_us))  # the firmware sends latch - now
            out.status = 0
            return 0
        except BaseException as exc:  # noqa: BLE001 - re-raised after the C call
            c.fail(exc)
            return -1

    @ffi_.def_extern()
    def capsheet_py_send_bytes(user, data, length):
        chip(user)._out.append(bytes(ffi_.buffer(data, length)))
        return 0

    @ffi_.def_extern()
    def capsheet_py_send_can(user, can_id, data, length, is_fd):
        chip(user)._out.append(CanFrame(int(can_id), bytes(ffi_.buffer(data, length)), bool(is_fd)))
        return 0

    @ffi_.def_extern()
    def capsheet_py_read_uid(user):
        return chip(user).uid

    @ffi_.def_extern()
    def capsheet_py_cal_load(user, axis, cal):
        offset, sens, stored = chip(user).cal_store[axis]
        cal.axis = axis
        cal.flags = stored
        cal.offset_q4 = offset
        cal.sensitivity = sens
        return 0

    @ffi_.def_extern()
    def capsheet_py_cal_store(user, axis, cal):
        chip(user).cal_store[axis] = (int(cal.offset_q4), float(cal.sensitivity), 1)
        return 0

    @ffi_.def_extern()
    def capsheet_py_cal_imu_load(user, element, bits):
        stored = chip(user).cal_imu_store.get(int(element))
        if stored is None:
            return -1
        bits[0] = stored
        return 0

    @ffi_.def_extern()
    def capsheet_py_cal_imu_store(user, element, bits):
        chip(user).cal_imu_store[int(element)] = int(bits)
        return 0


_register(ffi)
_MUTANT_LIB = None


def mutant_library():
    """``(ffi, lib)`` of the mutant test build (``firmware_ref._capsheet_fw_mutants``)."""
    global _MUTANT_LIB
    if _MUTANT_LIB is None:
        try:
            from ._capsheet_fw_mutants import ffi as mffi, lib as mlib
        except ImportError as exc:  # pragma: no cover - depends on the installation
            raise ImportError("the mutant test build firmware_ref._capsheet_fw_mutants is not built "
                              f"(pip install -e . builds it): {exc}") from exc
        _register(mffi)
        _MUTANT_LIB = (mffi, mlib)
    return _MUTANT_LIB
