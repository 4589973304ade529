"""The chip model: one accelerometer chip's protocol behaviour, sans-I/O (docs/protocol.md §8).

A `ChipModel` takes the frames it hears and returns the frames it sends; time is passed in, never
read (as libcanard's ``canard_us_t``), so the same chip runs behind a pty, a CAN bus, a test at
simulated time or a benchmark. What it does with each command is `protocol.state.RULES`; this
file only adds what the table leaves to the implementation:

* Boot (power-on and after RESET): the chip speaks from ``provisional_node(uid, salt)`` with
  ``salt`` = the number of ANNOUNCE rounds already left unanswered (0 at power-on and after
  RESET), sends ANNOUNCE then INFO at once and every `ANNOUNCE_PERIOD_S` until it is assigned.
* ASSIGN is for this chip only if ``uid_low`` matches its uid and it is addressed to its current
  node id — or, in BOOT, to the provisional id of the round before (an ASSIGN that crossed the
  next ANNOUNCE on the wire, docs §3.3); otherwise it is ignored silently. The ACK comes from the
  new node id.
* SYNC: a STREAMING chip answers every SYNC frame with one SAMPLE carrying the counter; a FAULT
  chip that has had a START answers with an INVALID sample (counts 0). ``missed_syncs`` adds the
  counter gap ``(counter - last - 1) mod 2**16`` while answering SYNC (a repeated counter or a gap
  of 0x7FFF or more — an older SYNC — adds nothing); the counter becomes ``last`` whatever it was;
  START forgets ``last``; saturating at 255.
* STATUS heartbeat every ``heartbeat_ms`` (1000 from ASSIGN until a CONFIG sets another, 0 = off)
  while assigned, from `poll`; the first one ``heartbeat_ms`` after the ASSIGN that left BOOT, and
  ``heartbeat_ms`` after every accepted CONFIG. ``uptime_s`` counts from power-on (RESET does not
  restart it).
* What a frame heard does, in the order of docs §8.1 (`handle`): a damaged frame is counted in
  ``rx_errors`` and dropped; a frame for another node, or of a node -> host type (0x01..0x0F,
  defined or not), is ignored and not counted; another version, an undefined type, a wrong length
  or a field out of range is counted, and NACKed (BAD_VERSION, UNKNOWN_COMMAND, BAD_LENGTH,
  BAD_VALUE) only when addressed to this chip; then the ASSIGN uid check, `protocol.state.RULES`
  (BAD_STATE) and the CONFIG / CAL_WRITE field checks (BAD_VALUE, UNSUPPORTED). **A broadcast is
  never answered with a NACK** — whatever is wrong with it, the chip drops it and changes nothing.
* CONFIG ``range`` r scales the sensor's ±2 g counts by an arithmetic shift ``counts >> r``
  (the sensor source always reports ±2 g counts); ``filter`` and ``rate_hz`` are stored only.
  ``range`` != 0 needs MULTI_RANGE and ``filter`` != 0 needs FILTER (else NACK UNSUPPORTED).
* A sample the sensor flags INVALID (the ADC did not answer) puts an assigned chip in FAULT; so
  does `fault`. Only RESET (or a power cycle) leaves FAULT. An INVALID sample has counts 0 and
  status INVALID alone. SATURATED is set exactly when a count sent is -2048 or 2047 (§5.2): the chip
  computes it from what it sends; the sensor's other bits (STALE, SELF_TEST) pass through.

* new in 1.2 (docs §16): built with ``sensors="accel+gyro"`` or ``"accel+gyro+mag"`` and an ``imu``
  source, the chip reports GYRO (and MAG) and SAMPLE_TIME, takes CONFIG_IMU (checked as §16.2
  says) and, in format 1 or 2, answers SYNC with one IMU record: an IMU_SAMPLE on serial and with
  CONFIG_IMU flag FD on CAN, else IMU_GYRO (+ IMU_MAG) + IMU_ACCEL on classic CAN. SATURATED covers
  every count sent; an INVALID record has counts 0 and ``time_us`` unknown.

The interface (protocol/chip_interface.py) is shared with the C firmware
(`firmware_ref.chip.CFirmwareChip`), so a virtual sheet runs on either through its ``chip_factory``.
"""

from __future__ import annotations

import binascii
import struct

import numpy as np
from cobs import cobs

from protocol.can import CanFrame, decode_can, imu_can_frames, make_id, split_id, to_can
from protocol.chip_interface import DEFAULT_CAPABILITIES, ChipFactory, Out, SensorSource, check_chip_args
from protocol.constants import SampleStatus
from protocol.imu_units import accel_g_of_counts, corrected_gyro_counts, corrected_mag_counts, nominal_imu_cal
from protocol.framing import HEADER, DecodeError, ErrorReason, decode_frame, encode
from protocol.messages import (NODE_BROADCAST, PROTOCOL_VERSION, Ack, Announce, Assign, CalData,
                               CalImuData, CalImuRead, CalImuWrite, CalBlock,
                               CalRead, CalWrite, Capability, ChipState, Config, Direction, Info,
                               Message, MsgType, Nack, NackReason, Status, StatusFlag, Sync,
                               is_node_to_host_type, provisional_node, ConfigImu, ConfigImuFlag, ImuSample,
                               SampleFormat, TIME_UNKNOWN)
from protocol.state import ANNOUNCE_PERIOD_S, DEFAULT_HEARTBEAT_MS, DEFAULT_RATE_HZ, Reply, next_deadline, rule_for

__all__ = ["Out", "SensorSource", "ChipModel", "ChipFactory", "DEFAULT_CAPABILITIES",
           "FIRMWARE_VERSION", "DEFAULT_HEARTBEAT_MS", "frame_header", "check_chip_args"]

FIRMWARE_VERSION = (0, 1, 0)  #: INFO fw_major, fw_minor, fw_patch of the model
_SAT = 255
_INTEGRITY = (ErrorReason.BAD_COBS, ErrorReason.SHORT, ErrorReason.BAD_CRC, ErrorReason.OVERSIZE)
_NACK_FOR = {ErrorReason.BAD_VERSION: NackReason.BAD_VERSION, ErrorReason.UNKNOWN_TYPE: NackReason.UNKNOWN_COMMAND,
             ErrorReason.BAD_LENGTH: NackReason.BAD_LENGTH, ErrorReason.BAD_FIELD: NackReason.BAD_VALUE}
_STREAM_STATES = (ChipState.STREAMING, ChipState.FAULT)
_SAMPLE_HDR = struct.Struct("<BBHH")  # version, type, node, counter
_INVALID = int(SampleStatus.INVALID)
_SAT_BIT = int(SampleStatus.SATURATED)
_RAILS = (-2048, 2047)
_FAULT = ChipState.FAULT
_I16_RAILS = (-32768, 32767)
#: INFO capability bits by ``sensors`` (new in 1.2, docs §16)
_SENSOR_CAPS = {"accel": 0, "accel+gyro": int(Capability.GYRO | Capability.SAMPLE_TIME),
                "accel+gyro+mag": int(Capability.GYRO | Capability.MAG | Capability.SAMPLE_TIME)}


def frame_header(frame: Out) -> tuple[int, int, int] | None:
    """``(version, type, node)`` of a frame whose bytes are intact (CRC good), else None."""
    if isinstance(frame, CanFrame):
        _p, t, v, n = split_id(frame.arbitration_id)
        return v, t, n
    try:
        body = cobs.decode(bytes(frame).rstrip(b"\x00"))
    except cobs.DecodeError:
        return None
    if len(body) < 6 or binascii.crc_hqx(body, 0xFFFF) != 0:
        return None
    return HEADER.unpack_from(body)



class ChipModel:
    """One chip. See the module docstring for the behaviour.

    Parameters
    ----------
    uid : int
        64-bit unique id.
    sensor : SensorSource
        ``now_s -> ((x, y, z), status)``: ±2 g ADC counts and SampleStatus bits, read at SYNC.
    transport : {"serial", "can"}
        What `handle` takes and the frames return: serial frames (bytes with the 0x00) or
        `protocol.can.CanFrame`.
    fd : bool
        CAN FD capable (sets Capability.CAN_FD; FD frames are accepted).
    capabilities : int
        INFO capability bits (CAN_FD is added when ``fd``).
    calibration : ((offset_q4, sensitivity),) * 3
        Factory calibration per axis (stored in non-volatile memory if CAL_STORAGE).
    seed : int
        Unused by the model (it has no randomness); kept for chip classes that do.
    sensors : {"accel", "accel+gyro", "accel+gyro+mag"}
        The chip's sensors (docs §16); anything but "accel" needs ``imu``.
    imu : callable, optional
        ``(now_s, gyro_range, mag_range) -> ((gx, gy, gz), (mx, my, mz) or None, time_us)``: the
        gyroscope's and magnetometer's 16-bit counts at those range codes and the sample's time after
        the SYNC in µs, read at SYNC beside ``sensor``.
    """

    def __init__(self, uid: int, sensor: SensorSource, *, transport: str = "serial", fd: bool = False,
                 capabilities: int = DEFAULT_CAPABILITIES,
                 calibration: tuple[tuple[int, float], ...] = ((0, 1024.0),) * 3, seed: int = 0,
                 sensors: str = "accel", imu=None) -> None:
        check_chip_args(uid, transport, calibration)
        if sensors not in _SENSOR_CAPS:
            raise ValueError(f"Invalid sensors: {sensors!r} (expected one of {', '.join(_SENSOR_CAPS)})")
        if sensors != "accel" and imu is None:
            raise ValueError(f"Invalid imu: None (sensors {sensors!r} need an imu source)")
        self.sensors = sensors
        self.imu = imu
        capabilities = int(capabilities) | _SENSOR_CAPS[sensors]
        self.uid = uid
        self.sensor = sensor
        self.transport = transport
        self.fd = fd
        self.capabilities = Capability(int(capabilities) | (Capability.CAN_FD if fd else 0))
        self.seed = seed
        self._can = transport == "can"
        self._factory_cal = [(int(o), float(s), 1 if self.capabilities & Capability.CAL_STORAGE else 0)
                             for o, s in calibration]
        self._stored_cal = list(self._factory_cal)
        # new in 1.3 (§17): block -> [(value, stored)] per element; none stored at the factory
        self._stored_imu_cal = {b: [(v, 0) for v in vals] for b, vals in nominal_imu_cal().items()}
        self.powered = False
        self.boot_s = 0.0
        self._boot_vars(0.0)

    # ------------------------------------------------------------------ state
    def _boot_vars(self, now_s: float) -> None:
        self.state = ChipState.BOOT
        self.salt = 0
        self.node = provisional_node(self.uid, 0)
        self.prev_node: int | None = None  # BOOT: the provisional id of the round before (§3.3)
        self.link: int | None = None
        self.rate_hz = DEFAULT_RATE_HZ
        self.range = 0
        self.filter = 0
        self.heartbeat_ms = DEFAULT_HEARTBEAT_MS
        self.imu_format = SampleFormat.ACCEL_12  # CONFIG_IMU (§16.2) defaults
        self.gyro_range, self.mag_range, self.imu_flags = 3, 0, 0
        self.configured = False
        self.streaming = False  # START received (FAULT answers SYNC only then)
        self.rx_errors = 0
        self.missed_syncs = 0
        self.last_counter: int | None = None
        self.cal = list(self._stored_cal)
        self.imu_cal = {b: list(v) for b, v in self._stored_imu_cal.items()}
        self._imu_cal_changed()
        self.next_announce_s = now_s + ANNOUNCE_PERIOD_S
        self.next_heartbeat_s: float | None = None
        self._set_node(self.node)

    def _imu_cal_changed(self) -> None:
        """Derive what §17.3 applies from ``imu_cal``: ``gyro_cal`` ``(A, b, Γ)`` and ``mag_cal``
        ``(S, h)`` as arrays, or None where every element of the sensor's blocks is nominal."""
        nominal = nominal_imu_cal()
        vals = {b: [v for v, _ in e] for b, e in self.imu_cal.items()}

        def blocks(*bs):
            if all(vals[b] == nominal[b] for b in bs):
                return None
            return tuple(np.array(vals[b]).reshape(3, 3) if len(vals[b]) == 9 else np.array(vals[b]) for b in bs)

        self.gyro_cal = blocks(CalBlock.GYRO_MATRIX, CalBlock.GYRO_BIAS, CalBlock.GYRO_G_SENS)
        self.mag_cal = blocks(CalBlock.MAG_MATRIX, CalBlock.MAG_HARD_IRON)

    def _set_node(self, node: int) -> None:
        self.node = node
        if self._can:
            self._sample_id = make_id(MsgType.SAMPLE, node)
        else:
            self._sample_hdr = node

    def _boot(self, now_s: float) -> list[Out]:
        self._boot_vars(now_s)
        return self._announce_info()

    def fault(self) -> None:
        """Put the chip in FAULT (its sensor stopped answering), as an INVALID sample does."""
        if self.state != ChipState.BOOT:
            self.state = ChipState.FAULT

    @property
    def status_flags(self) -> StatusFlag:
        f = StatusFlag.NONE
        if any(c[2] for c in self.cal):
            f |= StatusFlag.CAL_VALID
        if self.state == ChipState.FAULT:
            f |= StatusFlag.ADC_FAULT
        if self.configured:
            f |= StatusFlag.CONFIGURED
        return f

    # ------------------------------------------------------------------ output
    def _out(self, msg: Message) -> Out:
        return to_can(msg) if self._can else encode(msg)

    def _announce_info(self) -> list[Out]:
        return [self._out(Announce(self.node, self.uid)),
                self._out(Info(self.node, *FIRMWARE_VERSION, PROTOCOL_VERSION, int(self.capabilities), 12,
                               self.state))]

    def _nack(self, command: int, reason: NackReason) -> list[Out]:
        return [self._out(Nack(self.node, command & 0xFF, reason))]

    def _status(self, now_s: float) -> Out:
        return self._out(Status(self.node, self.state, int(self.status_flags), self.rx_errors,
                                self.missed_syncs, int(max(0.0, now_s - self.boot_s)) & 0xFFFFFFFF))

    def _sample(self, counter: int, now_s: float) -> Out:
        if self.state is _FAULT:
            x = y = z = 0
            st = _INVALID
        else:
            (x, y, z), st = self.sensor(now_s)
            st = int(st)
            if st & _INVALID:  # the conversion failed: FAULT, and an INVALID sample (§8.6)
                self.state = _FAULT
                x = y = z = 0
                st = _INVALID
            else:
                if self.range:
                    r = self.range
                    x, y, z = x >> r, y >> r, z >> r
                # SATURATED exactly when a count sent is at a rail (§5.2), whatever the ADC flagged
                st = (st & ~_SAT_BIT) | (_SAT_BIT if (x in _RAILS or y in _RAILS or z in _RAILS) else 0)
        word = (x & 0xFFF) | ((y & 0xFFF) << 12) | ((z & 0xFFF) << 24) | ((st & 0xF) << 36)
        if self._can:
            return CanFrame(self._sample_id, counter.to_bytes(2, "little") + word.to_bytes(5, "little"), False)
        body = _SAMPLE_HDR.pack(PROTOCOL_VERSION, MsgType.SAMPLE, self._sample_hdr, counter) + word.to_bytes(5, "little")
        return cobs.encode(body + binascii.crc_hqx(body, 0xFFFF).to_bytes(2, "big")) + b"\x00"

    def _imu_sample(self, counter: int, now_s: float) -> list[Out]:
        """One IMU record (docs §16.1) for this SYNC, in the frames the transport and CONFIG_IMU ask for."""
        nine = self.imu_format == SampleFormat.IMU9
        frame = self._sample(counter, now_s)  # the accelerometer word, its range, SATURATED and FAULT rules
        if isinstance(frame, CanFrame):
            data = frame.data
        else:
            data = decode_frame(frame.rstrip(b"\x00")).payload()
        w = int.from_bytes(data[2:7], "little")
        x, y, z = (((w >> sh) & 0xFFF) - (((w >> sh) & 0x800) << 1) for sh in (0, 12, 24))
        st = (w >> 36) & 0xF
        if st & _INVALID:
            g, m, t_us = (0, 0, 0), ((0, 0, 0) if nine else None), TIME_UNKNOWN
        else:
            g, m, t_us = self.imu(now_s, self.gyro_range, self.mag_range)
            m = tuple(m) if nine else None
            if self.gyro_cal is not None or (nine and self.mag_cal is not None):
                g, m = self.corrected(g, m, (x, y, z))
            if any(v in _I16_RAILS for v in (*g, *(m or ()))):
                st |= _SAT_BIT
        msg = ImuSample(self.node, counter, x, y, z, st, int(t_us), *g, *(m if m is not None else (None,) * 3))
        if self._can:
            return imu_can_frames(msg, fd=bool(self.imu_flags & ConfigImuFlag.FD))
        return [encode(msg)]

    def corrected(self, gyro, mag, accel_sent):
        """§17.3: the gyroscope (and magnetometer, if not None) counts this chip sends for a reading
        ``gyro``, ``mag`` whose accelerometer counts sent are ``accel_sent``; unchanged for a sensor
        with the nominal calibration."""
        if self.gyro_cal is not None:
            A, b, G = self.gyro_cal
            f = accel_g_of_counts([accel_sent], self.range)
            gyro = tuple(corrected_gyro_counts([gyro], self.gyro_range, A[None], b[None], G[None], f)[0].tolist())
        if mag is not None and self.mag_cal is not None:
            S, h = self.mag_cal
            mag = tuple(corrected_mag_counts([mag], self.mag_range, S[None], h[None])[0].tolist())
        return tuple(int(v) for v in gyro), (None if mag is None else tuple(int(v) for v in mag))

    # ------------------------------------------------------------------ public API
    def power_on(self, now_s: float) -> list[Out]:
        """Boot: ANNOUNCE then INFO from the provisional node id. ``uptime_s`` counts from here."""
        self.powered = True
        self.boot_s = now_s
        return self._boot(now_s)

    def poll(self, now_s: float) -> list[Out]:
        """Time-driven output: re-ANNOUNCE (BOOT), STATUS heartbeat (assigned)."""
        if not self.powered:
            return []
        if self.state == ChipState.BOOT:
            if now_s >= self.next_announce_s:
                self.salt += 1
                self.prev_node = self.node
                self._set_node(provisional_node(self.uid, self.salt))
                self.next_announce_s = next_deadline(self.next_announce_s, ANNOUNCE_PERIOD_S, now_s)
                return self._announce_info()
            return []
        if self.heartbeat_ms and self.next_heartbeat_s is not None and now_s >= self.next_heartbeat_s:
            period = self.heartbeat_ms / 1000.0
            self.next_heartbeat_s = next_deadline(self.next_heartbeat_s, period, now_s)
            return [self._status(now_s)]
        return []

    def decode(self, frame: Out) -> Message | DecodeError:
        """Decode one frame as this chip's transport carries it."""
        if isinstance(frame, CanFrame):
            if frame.is_fd and not self.fd:
                return DecodeError(ErrorReason.BAD_LENGTH, "CAN FD frame on a classic CAN chip")
            return decode_can(frame.arbitration_id, frame.data, is_fd=frame.is_fd)
        return decode_frame(bytes(frame).rstrip(b"\x00"))

    def handle(self, frame: Out, now_s: float, decoded: Message | DecodeError | None = None) -> list[Out]:
        """React to one frame heard on the bus; returns the frames sent in answer.

        ``decoded`` is the bus's decode of this very frame (saves decoding it once per chip).
        """
        if not self.powered:
            return []
        msg = self.decode(frame) if decoded is None else decoded
        cls = type(msg)
        if cls is Sync:  # the hot path
            if self.streaming and self.state in _STREAM_STATES:
                c = msg.counter
                last = self.last_counter
                if last is not None:
                    gap = (c - last - 1) & 0xFFFF
                    if gap < 0x7FFF and self.missed_syncs < _SAT:
                        self.missed_syncs = min(_SAT, self.missed_syncs + gap)
                self.last_counter = c
                if self.imu_format:
                    return self._imu_sample(c, now_s)
                return [self._sample(c, now_s)]
            return []
        if cls is DecodeError:
            return self._on_error(frame, msg)
        node = msg.node
        if node != NODE_BROADCAST and node != self.node:
            if node == self.prev_node and cls is Assign and self.state == ChipState.BOOT:
                node = self.node  # §3.3: the ASSIGN crossed this chip's next ANNOUNCE on the wire
            else:
                return []
        if msg.DIRECTION != Direction.HOST_TO_CHIP:
            return []
        t = msg.TYPE
        if t == MsgType.ASSIGN and msg.uid_low != (self.uid & 0xFFFFFFFF):
            return []
        rule = rule_for(self.state, t)
        if rule is None:
            return self._nack(t, NackReason.BAD_STATE) if node != NODE_BROADCAST else []
        if rule.validate:
            reason = self._check(msg)
            if reason is not None:
                return self._nack(t, reason) if node != NODE_BROADCAST else []
        return self._apply(msg, rule, now_s)

    # ------------------------------------------------------------------ internals
    def _on_error(self, frame: Out, err: DecodeError) -> list[Out]:
        """A frame that did not decode (docs §8.1): integrity failures are counted and dropped; a
        frame whose header names another node or a node -> host type is not this chip's business;
        the rest is counted, and NACKed only when addressed to this chip."""
        if err.reason in _INTEGRITY:
            self._count_rx_error()
            return []
        hdr = frame_header(frame)
        if hdr is None:  # pragma: no cover - every non-integrity error has an intact header
            return []
        _v, t, node = hdr
        if (node != NODE_BROADCAST and node != self.node) or is_node_to_host_type(t):
            return []
        self._count_rx_error()
        if node == NODE_BROADCAST:
            return []  # a broadcast is never NACKed (§8.1): one frame must not draw an answer from every chip
        return self._nack(t, _NACK_FOR[err.reason])

    def _count_rx_error(self) -> None:
        if self.rx_errors < _SAT:
            self.rx_errors += 1

    def _check(self, msg: Message) -> NackReason | None:
        if isinstance(msg, Config):
            if msg.range > 3 or msg.filter > 3 or not 1 <= msg.rate_hz <= 4000:
                return NackReason.BAD_VALUE
            if msg.range != 0 and not self.capabilities & Capability.MULTI_RANGE:
                return NackReason.UNSUPPORTED
            if msg.filter != 0 and not self.capabilities & Capability.FILTER:
                return NackReason.UNSUPPORTED
        elif isinstance(msg, CalWrite):
            if msg.flags & 1 and not self.capabilities & Capability.CAL_STORAGE:
                return NackReason.UNSUPPORTED
        elif isinstance(msg, (CalImuWrite, CalImuRead)):  # §17.2, in this order
            need = Capability.GYRO if msg.block <= CalBlock.GYRO_G_SENS else Capability.MAG
            if not self.capabilities & need:
                return NackReason.UNSUPPORTED
            if isinstance(msg, CalImuWrite) and msg.flags & 1 and not self.capabilities & Capability.CAL_STORAGE:
                return NackReason.UNSUPPORTED
        elif isinstance(msg, ConfigImu):  # §16.2, in this order
            if msg.format > 2 or msg.gyro_range > 4 or msg.mag_range > 3:
                return NackReason.BAD_VALUE
            caps = self.capabilities
            if ((msg.format >= 1 and not caps & Capability.GYRO) or (msg.format == 2 and not caps & Capability.MAG)
                    or (msg.flags & ConfigImuFlag.FD and not caps & Capability.CAN_FD)):
                return NackReason.UNSUPPORTED
        return None

    def _apply(self, msg: Message, rule, now_s: float) -> list[Out]:
        reply = rule.reply
        t = msg.TYPE
        if reply is Reply.ACK_THEN_BOOT:
            ack = self._out(Ack(self.node, t, 0))
            return [ack] + self._boot(now_s)
        out: list[Out] = []
        if t == MsgType.ASSIGN:
            assert isinstance(msg, Assign)
            first = self.state == ChipState.BOOT
            self.prev_node = None
            self._set_node(msg.new_node)
            self.link = msg.link
            if first or self.next_heartbeat_s is None:
                self.next_heartbeat_s = now_s + self.heartbeat_ms / 1000.0
        elif t == MsgType.CONFIG:
            assert isinstance(msg, Config)
            self.rate_hz, self.range, self.filter = msg.rate_hz, msg.range, msg.filter
            self.heartbeat_ms = msg.heartbeat_ms
            self.configured = True
            self.next_heartbeat_s = now_s + msg.heartbeat_ms / 1000.0 if msg.heartbeat_ms else None
        elif t == MsgType.CONFIG_IMU:
            assert isinstance(msg, ConfigImu)
            self.imu_format = SampleFormat(msg.format)
            self.gyro_range, self.mag_range, self.imu_flags = msg.gyro_range, msg.mag_range, msg.flags
        elif t == MsgType.START:
            self.streaming = True
            self.last_counter = None
        elif t == MsgType.STOP:
            self.streaming = False
        elif t == MsgType.CAL_WRITE:
            assert isinstance(msg, CalWrite)
            entry = (msg.offset_q4, msg.sensitivity, msg.flags & 1)
            self.cal[msg.axis] = entry
            if msg.flags & 1:
                self._stored_cal[msg.axis] = entry
        elif t == MsgType.CAL_IMU_WRITE:
            assert isinstance(msg, CalImuWrite)
            entry = (msg.value, msg.flags & 1)
            self.imu_cal[msg.block][msg.index] = entry
            if msg.flags & 1:
                self._stored_imu_cal[msg.block][msg.index] = entry
            self._imu_cal_changed()
        if rule.next_state is not None:
            self.state = rule.next_state
        if reply is Reply.ACK:
            out.append(self._out(Ack(self.node, t, 0)))
        elif reply is Reply.ANNOUNCE_INFO:
            out.extend(self._announce_info())
        elif reply is Reply.CAL_DATA:
            assert isinstance(msg, CalRead)
            o, s, stored = self.cal[msg.axis]
            out.append(self._out(CalData(self.node, msg.axis, stored, o, s)))
        elif reply is Reply.CAL_IMU_DATA:
            assert isinstance(msg, CalImuRead)
            v, stored = self.imu_cal[msg.block][msg.index]
            out.append(self._out(CalImuData(self.node, msg.block, msg.index, stored, 0, v)))
        elif reply is Reply.SAMPLE:  # pragma: no cover - SYNC takes the fast path
            pass
        return out

    def __repr__(self) -> str:
        return (f"ChipModel(uid=0x{self.uid:016X}, node=0x{self.node:04X}, state={self.state.name}, "
                f"link={self.link})")
