"""All the chips of a sheet as arrays: one SYNC answered by every chip in one numpy step.

`ChipArray` holds the per-chip state the hot paths need (power, state, node id, link, START seen,
last counter, missed SYNCs, range, timers) in arrays of length N. Its two hot paths are vectorised:

* **SYNC** (`ChipArray.sync`): which chips answer, the missed-SYNC bookkeeping, one batch read of
  the sensors, the FAULT transition of an INVALID sample, the range shift, the 40-bit sample
  words, and — per-chip mode — every SAMPLE frame encoded at once (`SampleCodec`: one table
  entry per 12-bit count, status, node and counter, XORed — CRC as a sum of per-input terms, the
  bytes, zero flags — then COBS by a table keyed on where the zeros are, two 64-bit lanes a frame,
  about a dozen numpy calls per SYNC whatever the chip count; `ChipArray.sync_wire` gives the
  frames as one byte string), or — packed mode
  (`ChipArray.sync_words`) — the sample words handed to the gateway with nothing encoded.
  In the streaming steady state nothing is re-derived per SYNC: which chips answer, the gap to
  count, the range and the first due timer are kept and invalidated by any write through a view.
* **Timers** (`ChipArray.poll`): the due re-ANNOUNCEs and STATUS heartbeats are found by one
  comparison; the heartbeats are advanced and their STATUS frames encoded in one batch; a due
  re-ANNOUNCE (rare: unassigned chips) runs the scalar timer code.

Everything else — every command but SYNC, the rare timer events, and every chip with an injected
fault (dead, babbling: `faults.wrap_chip`) — runs the reference model's own code: each chip has a
*view* (`ArrayChip`, a `chip.ChipModel` whose state lives in the arrays), so the array answers
exactly as N `ChipModel` s would. tests/virtual_sheet/test_chiparray.py drives both with the same
random command sequences, faults and timers and compares every frame, byte for byte.

6/9-axis chips (docs/protocol.md §16): built with ``sensors`` and a batch ``imu`` source, every chip
takes CONFIG_IMU through its view; a SYNC answered by chips in format 1 or 2 reads the gyroscopes
(and magnetometers) of those chips in one batch and encodes their IMU records at once (serial:
CRC and COBS by rows; CAN: the classic frames of §16.4 or one FD IMU_SAMPLE each), the records'
accelerometer part being the vectorised SAMPLE path's counts and status.

Sans-I/O and time as an argument, as `chip.ChipModel`.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from protocol.can import CanFrame, make_id
from protocol.chip_interface import DEFAULT_CAPABILITIES, Out, check_chip_args
from protocol.constants import SampleStatus
from protocol.crc import crc16_rows
from protocol.messages import (IMU_RECORD_SIZE, NODE_BROADCAST, PROTOCOL_VERSION, TIME_UNKNOWN, ChipState,
                               ConfigImuFlag, MsgType, SampleFormat, Status, StatusFlag, Sync, pack_imu_records)

from .chip import ChipModel
from .faults import FaultSpec, FaultStats, wrap_chip
from .wire_batch import SampleEncoder, cobs_encode_batch, encode_samples_serial, sample_codec, word_fields  # noqa: F401 -- the batch encoder's names, importable from here as before

__all__ = ["ChipArray", "ArrayChip", "BatchSensor", "encode_samples_serial", "cobs_encode_batch"]

#: ``(now_s, idx) -> (counts (m, 3) int64 ±2 g ADC counts, status (m,) int64 SampleStatus bits)``
BatchSensor = Callable[[float, np.ndarray], tuple[np.ndarray, np.ndarray]]

_BOOT, _IDLE, _STREAMING, _FAULT = (int(ChipState.BOOT), int(ChipState.IDLE), int(ChipState.STREAMING),
                                    int(ChipState.FAULT))
_INVALID = int(SampleStatus.INVALID)
_SAT = 255
_FIELD_SHIFT = np.array([1, 1 << 12, 1 << 24], dtype=np.int64)  # x, y, z into the sample word
_SAT_BIT = int(SampleStatus.SATURATED)


def _saturated(counts: np.ndarray, status: np.ndarray) -> np.ndarray:
    """``status`` with SATURATED set exactly where a count sent is -2048 or 2047 (docs §5.2), as
    `chip.ChipModel` computes it."""
    rail = ((counts == 2047) | (counts == -2048)).any(axis=1)
    return (np.asarray(status, dtype=np.int64) & ~_SAT_BIT) | (rail * _SAT_BIT)


# ---------------------------------------------------------------------------------------------
# the per-chip view: a ChipModel whose state lives in the arrays
# ---------------------------------------------------------------------------------------------

#: the array's derived values (None: derive again) that a field written through a view invalidates
_STALE_ON_SET = {
    "node": ("_encoder", "_can_ids"),
    "last_counter": ("_all_last",),
    "state": ("_steady", "_next_due"),
    "powered": ("_steady", "_next_due"),
    "streaming": ("_steady",),
    "range": ("_range_any",),
    "imu_format": ("_imu_any",),
    "heartbeat_ms": ("_next_due",),
    "next_heartbeat_s": ("_next_due",),
    "next_announce_s": ("_next_due",),
}


class _F:
    """A ChipModel attribute stored at ``arr.<name>[k]``; ``none`` is the stored value of None."""

    def __init__(self, conv, none=None) -> None:
        self.conv, self.none = conv, none

    def __set_name__(self, owner, name) -> None:
        self.name = name
        self.stale = _STALE_ON_SET.get(name, ())

    def __get__(self, obj, owner=None):
        if obj is None:
            return self
        v = getattr(obj._arr, self.name)[obj._k]
        if self.none is not None and (v == self.none or (self.none == "nan" and np.isnan(v))):
            return None
        return self.conv(v)

    def __set__(self, obj, value) -> None:
        arr = obj._arr
        a = getattr(arr, self.name)
        for c in self.stale:  # what the array derived from this field is derived again
            setattr(arr, c, None)
        if value is None:
            a[obj._k] = np.nan if self.none == "nan" else self.none
        else:
            a[obj._k] = value


class ArrayChip(ChipModel):
    """Chip ``k`` of a `ChipArray`: the reference model's code on the array's state (every
    frame but the vectorised SYNC goes through here)."""

    state = _F(ChipState)
    node = _F(int)
    prev_node = _F(int, none=-1)
    link = _F(int, none=-1)
    streaming = _F(bool)
    last_counter = _F(int, none=-1)
    missed_syncs = _F(int)
    range = _F(int)
    powered = _F(bool)
    heartbeat_ms = _F(int)
    next_heartbeat_s = _F(float, none="nan")
    next_announce_s = _F(float)
    rx_errors = _F(int)
    configured = _F(bool)
    boot_s = _F(float)
    imu_format = _F(SampleFormat)
    gyro_range = _F(int)
    mag_range = _F(int)
    imu_flags = _F(int)

    def __init__(self, arr: "ChipArray", k: int, uid: int, sensor, *, transport: str, fd: bool,
                 capabilities: int, calibration, sensors: str = "accel", imu=None) -> None:
        self._arr, self._k = arr, k
        super().__init__(uid, sensor, transport=transport, fd=fd, capabilities=capabilities,
                         calibration=calibration, sensors=sensors, imu=imu)

    def _imu_cal_changed(self) -> None:
        super()._imu_cal_changed()
        if hasattr(self, "_arr"):  # the model's __init__ boots before the view is bound
            self._arr.imu_cal_on[self._k] = self.gyro_cal is not None or self.mag_cal is not None

    def __repr__(self) -> str:
        return "Array" + super().__repr__()


# ---------------------------------------------------------------------------------------------
# the array
# ---------------------------------------------------------------------------------------------

class ChipArray:
    """N chips (module docstring).

    Parameters
    ----------
    uids : sequence of int
        64-bit uid of chip k (its index in every array).
    sensor : BatchSensor
        Batch sensor read: ``sensor(now_s, idx) -> (counts (m, 3), status (m,))``.
    transport : {"serial", "can"}
    fd : bool
        CAN FD chips.
    capabilities : int
        INFO capability bits, every chip.
    calibrations : sequence of ((offset_q4, sensitivity),) * 3, optional
        Factory calibration per chip (default: 0 and 1024 on every axis).
    sensors : dict {k: SensorSource}, optional
        Chip k reads this scalar source instead of the batch (e.g. a `faults.DriftingSensor`).
    faults : FaultSpec, optional
        Chip faults (dead, babbling) for chip index = link, applied with `faults.wrap_chip`.
    fault_stats : FaultStats, optional
    """

    def __init__(self, uids: Sequence[int], sensor: BatchSensor, *, transport: str = "serial", fd: bool = False,
                 capabilities: int = DEFAULT_CAPABILITIES, calibrations=None, sensors: dict | None = None,
                 faults: FaultSpec | None = None, fault_stats: FaultStats | None = None,
                 imu_sensors: str = "accel", imu=None) -> None:
        n = self.n = len(uids)
        self.imu_sensors = imu_sensors
        self.imu = imu  #: batch IMU source: (now_s, idx, gyro_range (m,), mag_range (m,)) -> (gyro, mag, time_us)
        cal0 = ((0, 1024.0),) * 3
        calibrations = [cal0] * n if calibrations is None else list(calibrations)
        if len(calibrations) != n:
            raise ValueError(f"Expected {n} calibrations (one per uid), got {len(calibrations)}")
        for u, c in zip(uids, calibrations):
            check_chip_args(u, transport, c)
        self.transport = transport
        self.can = transport == "can"
        self.sensor = sensor
        self.uid = np.array(uids, dtype=np.uint64)
        self.state = np.full(n, _BOOT, dtype=np.int64)
        self.node = np.zeros(n, dtype=np.int64)
        self.prev_node = np.full(n, -1, dtype=np.int64)  # BOOT: the previous round's provisional id
        self.link = np.full(n, -1, dtype=np.int64)
        self.streaming = np.zeros(n, dtype=bool)
        self.last_counter = np.full(n, -1, dtype=np.int64)
        self.missed_syncs = np.zeros(n, dtype=np.int64)
        self.range = np.zeros(n, dtype=np.int64)
        self.powered = np.zeros(n, dtype=bool)
        self.heartbeat_ms = np.zeros(n, dtype=np.int64)
        self.next_heartbeat_s = np.full(n, np.nan)
        self.next_announce_s = np.zeros(n)
        self.rx_errors = np.zeros(n, dtype=np.int64)
        self.configured = np.zeros(n, dtype=bool)
        self.boot_s = np.zeros(n)
        self.imu_format = np.zeros(n, dtype=np.int64)  # CONFIG_IMU (§16.2), per chip
        self.gyro_range = np.full(n, 3, dtype=np.int64)
        self.mag_range = np.zeros(n, dtype=np.int64)
        self.imu_flags = np.zeros(n, dtype=np.int64)
        self._imu_any: bool | None = None  # some chip is in format 1 or 2
        self.imu_cal_on = np.zeros(n, dtype=bool)  # a chip whose §17 calibration is not nominal
        # derived values, None until needed (and again after a view writes what they come from)
        self._encoder: SampleEncoder | None = None  # serial: the SAMPLE encoder of `node`
        self._can_ids: tuple[np.ndarray, list[int]] | None = None  # CAN: each chip's SAMPLE identifier
        self._all_last: int | None = None  # every chip's last_counter, when they are all this one
        self._steady: bool | None = None  # every chip powered, started, STREAMING, no fault wrapper
        self._range_any: bool | None = None  # some chip has CONFIG range != 0
        self._next_due: float | None = None  # no chip timer is due before this time
        sensors = dict(sensors or {})
        self._scalar = np.zeros(n, dtype=bool)  # read a scalar sensor source
        self.views: list[ArrayChip] = []
        for k, u in enumerate(uids):
            src = sensors.get(k) or self._scalar_source(k)
            if k in sensors:
                self._scalar[k] = True
            self.views.append(ArrayChip(self, k, int(u), src, transport=transport, fd=fd,
                                        capabilities=capabilities, calibration=calibrations[k],
                                        sensors=imu_sensors, imu=self._scalar_imu(k) if imu is not None else None))
        self.faults = faults if faults is not None else FaultSpec()
        self.fault_stats = fault_stats if fault_stats is not None else FaultStats()
        #: what the gateway talks to, per chip: the view, or the view inside its fault wrapper
        self.chips = [wrap_chip(v, k, self.faults, self.fault_stats, can=self.can) for k, v in enumerate(self.views)]
        self._wrapped = np.array([c is not v for c, v in zip(self.chips, self.views)], dtype=bool)
        self._wrapped_idx = np.flatnonzero(self._wrapped).tolist()
        self._plain = ~self._wrapped
        self._all = np.ones(n, dtype=bool)
        self._every = np.arange(n)
        self._no_scalar = not self._scalar.any()
        if not self.can:
            sample_codec()  # the SAMPLE tables now, not in the first SYNC's answer time

    def _scalar_imu(self, k: int):
        idx = np.array([k])

        def source(now_s: float, gyro_range: int, mag_range: int):
            g, m, t = self.imu(now_s, idx, np.array([gyro_range]), np.array([mag_range]))
            return tuple(g[0].tolist()), (None if m is None else tuple(m[0].tolist())), int(t[0])
        return source

    def _imu_active(self) -> bool:
        a = self._imu_any
        if a is None:
            a = self._imu_any = bool(self.imu_format.any())
        return a

    def _imu_frames(self, ans: np.ndarray, counter: int, now_s: float, counts: np.ndarray,
                    status: np.ndarray | None) -> list:
        """The answers of chips ``ans`` when some are in format 1 or 2: per chip in chip order, its
        SAMPLE (format 0) or its IMU record's frames (docs §16.3, §16.4)."""
        fmt = self.imu_format[ans]
        st = np.zeros(ans.size, dtype=np.int64) if status is None else np.asarray(status, dtype=np.int64)
        per: list = [None] * ans.size
        plain = np.flatnonzero(fmt == 0)
        if plain.size:
            word = self._words(counts[plain], None if status is None else st[plain])
            frames = self._can_frames(ans[plain], counter, word) if self.can else self.encode(ans[plain], counter, word)
            for j, f in zip(plain.tolist(), frames):
                per[j] = [f]
        for f_code in (SampleFormat.IMU6, SampleFormat.IMU9):
            sel = np.flatnonzero(fmt == f_code)
            if not sel.size:
                continue
            idx = ans[sel]
            recs = self._imu_records(f_code, idx, now_s, counts[sel], st[sel])
            nodes = self.node[idx]
            ctr = np.array([counter & 0xFF, counter >> 8], dtype=np.uint8)
            if self.can:
                fd = (self.imu_flags[idx] & int(ConfigImuFlag.FD)) != 0
                for j, node, rec, use_fd in zip(sel.tolist(), nodes.tolist(), recs, fd.tolist()):
                    per[j] = _imu_can(node, counter, rec.tobytes(), use_fd, f_code)
                continue
            size = IMU_RECORD_SIZE[f_code]
            body = np.empty((sel.size, 6 + size + 2), dtype=np.uint8)
            body[:, 0] = PROTOCOL_VERSION
            body[:, 1] = int(MsgType.IMU_SAMPLE)
            body[:, 2] = nodes & 0xFF
            body[:, 3] = nodes >> 8
            body[:, 4:6] = ctr
            body[:, 6:6 + size] = recs
            crc = crc16_rows(body[:, :6 + size])
            body[:, 6 + size] = crc >> 8
            body[:, 7 + size] = crc & 0xFF
            enc = cobs_encode_batch(body)
            for j, row in zip(sel.tolist(), enc):
                per[j] = [row.tobytes() + b"\x00"]
        return [f for fs in per for f in fs]

    def _imu_records(self, f_code, idx: np.ndarray, now_s: float, counts: np.ndarray,
                     status: np.ndarray) -> np.ndarray:
        """The IMU records (docs §16.1) of chips ``idx`` in format ``f_code`` with their accelerometer
        ``counts`` and ``status``: rows of 13 or 19 bytes, shape (m, size), uint8. An INVALID sample's
        gyroscope and magnetometer are 0 and its time unknown; a gyroscope or magnetometer axis at a
        rail sets SATURATED."""
        c, s_ = np.asarray(counts, dtype=np.int64), np.asarray(status, dtype=np.int64).copy()
        g, m, t = self.imu(now_s, idx, self.gyro_range[idx], self.mag_range[idx])
        g = np.asarray(g, dtype=np.int64).copy()
        m = None if f_code == SampleFormat.IMU6 else np.asarray(m, dtype=np.int64).copy()
        t = np.asarray(t, dtype=np.int64).copy()
        bad = (s_ & _INVALID) != 0
        for j in np.flatnonzero(self.imu_cal_on[idx] & ~bad).tolist():  # §17.3, on the calibrated chips
            gj, mj = self.views[int(idx[j])].corrected(g[j], None if m is None else m[j], c[j])
            g[j] = gj
            if m is not None:
                m[j] = mj
        g[bad] = 0
        t[bad] = TIME_UNKNOWN
        rails = ((g == 32767) | (g == -32768)).any(axis=1)
        if m is not None:
            m[bad] = 0
            rails |= ((m == 32767) | (m == -32768)).any(axis=1)
        s_ = np.where(bad, s_, s_ | (rails * _SAT_BIT))
        return np.frombuffer(pack_imu_records(c, s_, t, g, m), dtype=np.uint8).reshape(idx.size, -1)

    def sync_records(self, frame: Out, msg: Sync, now_s: float, f_code, sel: np.ndarray | None = None):
        """SYNC for a gateway packing IMU records (SNAPSHOT_IMU, docs §16.5): ``(idx, recs, other)`` —
        the chips in format ``f_code`` that answered and their records (rows of 13 or 19 bytes, as
        `_imu_records`), and ``other`` ``[(k, frames)]``: what the rest answered as they would send it
        (a chip in another format, a wrapped chip), in chip order."""
        extra = [(k, self.chips[k].handle(frame, now_s, msg)) for k in self._wrapped_in(sel)]
        ans, counts, status = self._answer(msg.counter, now_s, sel)
        st = np.zeros(ans.size, dtype=np.int64) if status is None else np.asarray(status, dtype=np.int64)
        mine = self.imu_format[ans] == int(f_code)
        idx = ans[mine]
        recs = (self._imu_records(f_code, idx, now_s, counts[mine], st[mine]) if idx.size
                else np.zeros((0, IMU_RECORD_SIZE[f_code]), dtype=np.uint8))
        if not mine.all():  # as per-chip mode sends them
            rest = ans[~mine]
            frames = self._imu_frames(rest, msg.counter, now_s, counts[~mine], None if status is None else st[~mine])
            fmt = self.imu_format[rest]
            if self.can:
                fd = (self.imu_flags[rest] & int(ConfigImuFlag.FD)) != 0
                n_per = np.where(fmt == 0, 1, np.where(fd, 1, np.where(fmt == 2, 3, 2)))
            else:
                n_per = np.ones(rest.size, dtype=np.int64)
            ends = np.cumsum(n_per)
            extra += [(int(k), frames[e - n:e]) for k, n, e in zip(rest.tolist(), n_per.tolist(), ends.tolist())]
            extra.sort(key=lambda t: t[0])
        return idx, recs, extra

    def _scalar_source(self, k: int):
        idx = np.array([k])

        def source(now_s: float):
            c, s = self.sensor(now_s, idx)
            return (int(c[0, 0]), int(c[0, 1]), int(c[0, 2])), int(s[0])
        return source

    # ------------------------------------------------------------------ life cycle and timers
    def _sel(self, sel) -> np.ndarray:
        return self._all if sel is None else sel

    def power_on(self, now_s: float, sel: np.ndarray | None = None) -> list[Out]:
        """Power the chips (all, or those of the boolean mask ``sel``): their boot frames."""
        out: list[Out] = []
        for k in np.flatnonzero(self._sel(sel)).tolist():
            out += self.chips[k].power_on(now_s)
        return out

    def poll(self, now_s: float, sel: np.ndarray | None = None) -> list[Out]:
        """Timers of every chip (of ``sel``), in chip order (as N `ChipModel.poll` calls)."""
        due = self._next_due
        if due is None:
            due = self._next_due = self._first_due()
        if now_s < due:
            return []
        self._next_due = None  # heartbeats move on below
        boot = self.state == _BOOT
        live = self.powered & self._plain & self._sel(sel)
        announce = live & boot & (now_s >= self.next_announce_s)
        hb = np.flatnonzero(live & ~boot & (self.heartbeat_ms != 0)
                            & (now_s >= np.nan_to_num(self.next_heartbeat_s, nan=np.inf)))
        scalar = np.flatnonzero(announce | (self._wrapped & self._sel(sel)))
        if not scalar.size and not hb.size:
            return []
        items: list[tuple[int, list]] = []
        chips = self.chips
        for k in scalar.tolist():
            r = chips[k].poll(now_s)
            if r:
                items.append((k, r))
        if hb.size:
            period = self.heartbeat_ms[hb] / 1000.0
            nxt = self.next_heartbeat_s[hb] + period  # protocol.state.next_deadline, vectorised
            self.next_heartbeat_s[hb] = np.where(nxt > now_s, nxt, now_s + period)
            frames = self._status_frames(hb, now_s)
            if not items:
                return frames
            items += [(k, [f]) for k, f in zip(hb.tolist(), frames)]
        items.sort(key=lambda t: t[0])
        return [f for _, r in items for f in r]

    def next_due(self) -> float:
        """The earliest time a chip's timer (a re-announce, a heartbeat) is due: `poll` returns
        nothing before it (-inf with fault wrappers: they are polled every time)."""
        due = self._next_due
        if due is None:
            due = self._next_due = self._first_due()
        return due

    def _first_due(self) -> float:
        """The earliest time any plain chip's timer is due (-inf with fault wrappers: they poll
        every time)."""
        if self._wrapped_idx:
            return -np.inf
        boot = self.state == _BOOT
        a = self.next_announce_s[self.powered & boot]
        h = self.next_heartbeat_s[self.powered & ~boot & (self.heartbeat_ms != 0)]
        h = h[~np.isnan(h)]
        return float(min(a.min() if a.size else np.inf, h.min() if h.size else np.inf))

    def _status_frames(self, idx: np.ndarray, now_s: float) -> list[Out]:
        """The STATUS heartbeat of chips ``idx``, batch-encoded (`ChipModel._status`, byte for byte)."""
        views = self.views
        cal_valid = np.array([any(c[2] for c in views[k].cal) for k in idx.tolist()], dtype=bool)
        st = self.state[idx]
        flags = ((cal_valid * int(StatusFlag.CAL_VALID)) | ((st == _FAULT) * int(StatusFlag.ADC_FAULT))
                 | (self.configured[idx] * int(StatusFlag.CONFIGURED))).astype(np.int64)
        up = np.maximum(0.0, now_s - self.boot_s[idx]).astype(np.int64) & 0xFFFFFFFF
        m = idx.size
        pay = np.empty((m, 8), dtype=np.uint8)
        pay[:, 0] = st
        pay[:, 1] = flags
        pay[:, 2] = self.rx_errors[idx]
        pay[:, 3] = self.missed_syncs[idx]
        for b in range(4):
            pay[:, 4 + b] = (up >> (8 * b)) & 0xFF
        node = self.node[idx]
        if self.can:
            pb = pay.tobytes()
            return [CanFrame(make_id(MsgType.STATUS, nd, Status.PRIORITY), pb[8 * i:8 * i + 8], False)
                    for i, nd in enumerate(node.tolist())]
        body = np.empty((m, 14), dtype=np.uint8)
        body[:, 0] = PROTOCOL_VERSION
        body[:, 1] = int(MsgType.STATUS)
        body[:, 2] = node & 0xFF
        body[:, 3] = node >> 8
        body[:, 4:12] = pay
        crc = crc16_rows(body[:, :12])
        body[:, 12] = crc >> np.uint16(8)
        body[:, 13] = crc & np.uint16(0xFF)
        out = np.zeros((m, 16), dtype=np.uint8)
        out[:, :15] = cobs_encode_batch(body)
        b = out.tobytes()
        return [b[i:i + 16] for i in range(0, len(b), 16)]

    # ------------------------------------------------------------------ frames
    def handle(self, frame: Out, now_s: float, decoded, sel: np.ndarray | None = None) -> list[Out]:
        """A frame every chip (of ``sel``) hears (broadcast, or undecodable): the answers in chip order."""
        if type(decoded) is Sync:
            return self.sync(frame, decoded, now_s, sel)
        out: list[Out] = []
        chips = self.chips
        for k in np.flatnonzero(self._sel(sel)).tolist():
            r = chips[k].handle(frame, now_s, decoded)
            if r:
                out += r
        return out

    def handle_node(self, node: int, frame: Out, now_s: float, decoded, sel: np.ndarray | None = None) -> list[Out]:
        """A frame addressed to ``node``: only the chips speaking from that node hear it (and, for an
        ASSIGN, the chips in BOOT whose previous provisional id it is: docs §3.3)."""
        out: list[Out] = []
        who = self.node == node
        if decoded.TYPE == MsgType.ASSIGN:
            who = who | ((self.prev_node == node) & (self.state == _BOOT))
        for k in np.flatnonzero(who & self._sel(sel)).tolist():
            out += self.chips[k].handle(frame, now_s, decoded)
        return out

    def _answer(self, counter: int, now_s: float, sel):
        """The vectorised SYNC for the plain chips: updates the state, returns ``(idx, counts,
        status)`` — the answering chips, their sample counts (m, 3) as sent (after FAULT and the
        range shift; the low 12 bits go on the wire) and SampleStatus bits (m,), or None when every
        one is 0 (`_words` makes the 40-bit sample words of them)."""
        if self._no_scalar:
            steady = self._steady
            if steady is None:
                steady = self._steady = bool((self._plain & self.powered & self.streaming
                                              & (self.state == _STREAMING)).all())
            if steady and sel is None:
                return (self._every, *self._answer_all(counter, now_s, self._every))
            if steady:  # one gateway's chips of a streaming sheet (five gateways: each SYNC five times)
                ans = np.flatnonzero(sel)
                if ans.size:
                    return (ans, *self._answer_some(counter, now_s, ans))
        st = self.state
        ans = np.flatnonzero(self._plain & self._sel(sel) & self.powered & self.streaming
                             & ((st == _STREAMING) | (st == _FAULT)))
        if ans.size == 0:
            return ans, np.zeros((0, 3), dtype=np.int64), None
        if ans.size == self.n and self._no_scalar and not (st == _FAULT).any():
            return (ans, *self._answer_all(counter, now_s, ans))
        self._all_last = None
        last = self.last_counter[ans]
        miss = self.missed_syncs[ans]
        gap = (counter - last - 1) & 0xFFFF
        add = (last >= 0) & (gap < 0x7FFF) & (miss < _SAT)
        self.missed_syncs[ans] = np.where(add, np.minimum(_SAT, miss + gap), miss)
        self.last_counter[ans] = counter
        n = ans.size
        xyz = np.zeros((n, 3), dtype=np.int64)
        sts = np.full(n, _INVALID, dtype=np.int64)
        live = st[ans] != _FAULT
        if live.any():
            li = ans[live]
            scal = self._scalar[li]
            c = np.zeros((li.size, 3), dtype=np.int64)
            s = np.zeros(li.size, dtype=np.int64)
            if not scal.all():
                bi = li[~scal]
                cb, sb = self.sensor(now_s, bi)
                c[~scal] = cb
                s[~scal] = sb
            for j in np.flatnonzero(scal).tolist():  # scalar sources, in chip order among themselves
                (x, y, z), sj = self.views[int(li[j])].sensor(now_s)
                c[j] = (x, y, z)
                s[j] = int(sj)
            bad = (s & _INVALID) != 0
            if bad.any():
                self.state[li[bad]] = _FAULT
                self._steady = None
                c[bad] = 0
            r = self.range[li]
            c = np.where(bad[:, None], c, c >> r[:, None])
            s = _saturated(c, s)
            s[bad] = _INVALID
            xyz[live] = c
            sts[live] = s
        return ans, xyz, sts

    def _answer_all(self, counter: int, now_s: float, ans: np.ndarray):
        """`_answer` when every chip answers with a fresh sample (the streaming steady state):
        the same arithmetic on whole arrays, no gathers; when every chip last answered the
        previous counter (the usual next SYNC) there is no gap to count. ``(counts, status)``."""
        last = self._all_last
        if last is None or (counter - last - 1) & 0xFFFF:
            last, miss = self.last_counter, self.missed_syncs
            gap = (counter - last - 1) & 0xFFFF
            add = (last >= 0) & (gap < 0x7FFF) & (miss < _SAT)
            if add.any():
                np.copyto(miss, np.minimum(_SAT, miss + gap), where=add)
        self.last_counter.fill(counter)
        self._all_last = counter
        c, s = self.sensor(now_s, ans)
        c = np.asarray(c, dtype=np.int64)
        s = np.asarray(s, dtype=np.int64)
        rng = self._range_any
        if rng is None:
            rng = self._range_any = bool(self.range.any())
        if not np.count_nonzero(s):  # every sample OK: no fault, no status bits (count_nonzero: the
            if rng:                  # cheapest test, a fraction of .any()'s fixed cost)
                c = c >> self.range[:, None]
            if c.size and (c.max() >= 2047 or c.min() <= -2048):  # SATURATED: from the counts sent (§5.2)
                return c, _saturated(c, s)
            return c, None
        if (s & _INVALID).any():
            bad = (s & _INVALID) != 0
            self.state[bad] = _FAULT
            self._steady = None
            c = c.copy()
            c[bad] = 0
        else:
            bad = None
        if rng:
            sh = c >> self.range[:, None]
            c = sh if bad is None else np.where(bad[:, None], c, sh)
        s = _saturated(c, s)
        if bad is not None:
            s[bad] = _INVALID  # an INVALID sample: counts 0, status INVALID alone (§8.6)
        return c, s

    def _answer_some(self, counter: int, now_s: float, ans: np.ndarray):
        """`_answer` for the chips ``ans`` (distinct, ascending) while every chip streams with a
        fresh sample: what its general path computes for them, without the masks over the whole
        array and the gathers a fault or a scalar source needs. ``(counts, status)``, status None
        when every one is 0 (the same sample words)."""
        self._all_last = None
        last = self.last_counter[ans]
        gap = (counter - last - 1) & 0xFFFF
        if gap.any():  # a SYNC missed since a chip's last answer (0 everywhere: nothing to add)
            miss = self.missed_syncs[ans]
            add = (last >= 0) & (gap < 0x7FFF) & (miss < _SAT)
            if add.any():
                self.missed_syncs[ans] = np.where(add, np.minimum(_SAT, miss + gap), miss)
        self.last_counter[ans] = counter
        c, s = self.sensor(now_s, ans)
        c = np.asarray(c, dtype=np.int64)
        s = np.asarray(s, dtype=np.int64)
        rng = self._range_any
        if rng is None:
            rng = self._range_any = bool(self.range.any())
        if not np.count_nonzero(s):
            if rng:
                c = c >> self.range[ans][:, None]
            if c.max() >= 2047 or c.min() <= -2048:
                return c, _saturated(c, s)
            return c, None
        bad = (s & _INVALID) != 0
        if bad.any():
            self.state[ans[bad]] = _FAULT
            self._steady = None
            c = c.copy()
            c[bad] = 0
        if rng:
            c = np.where(bad[:, None], c, c >> self.range[ans][:, None])
        s = _saturated(c, s)
        s[bad] = _INVALID
        return c, s

    @staticmethod
    def _words(counts: np.ndarray, status: np.ndarray | None) -> np.ndarray:
        """The 40-bit sample words (int64) of `_answer`'s counts and status."""
        word = (counts & 0xFFF) @ _FIELD_SHIFT
        if status is not None:
            word |= (status & 0xF) << 36
        return word

    def _wrapped_in(self, sel) -> list[int]:
        if sel is None:
            return self._wrapped_idx
        return [k for k in self._wrapped_idx if sel[k]]

    def encode(self, idx: np.ndarray, counter: int, word: np.ndarray) -> list[Out]:
        """The SAMPLE frames of chips ``idx`` (their node ids) for ``counter``, batch-encoded."""
        if self.can:
            return self._can_frames(idx, counter, word)
        if not idx.size:
            return []
        b = self._wire(idx, counter, *word_fields(word))
        return [b[i:i + 15] for i in range(0, len(b), 15)]

    def _can_frames(self, idx: np.ndarray, counter: int, word: np.ndarray) -> list[CanFrame]:
        """CAN: the SAMPLE frames of chips ``idx`` (identifiers kept per chip, the payloads of all
        of them cut from one byte string)."""
        ids = self._can_ids
        if ids is None:
            a = make_id(MsgType.SAMPLE, 0) | self.node
            ids = self._can_ids = (a, a.tolist())
        ids = ids[1] if idx.size == self.n else ids[0][idx].tolist()
        data = np.ascontiguousarray((word << 16) | (counter & 0xFFFF), dtype="<i8")  # counter, word: 7 bytes LE
        b = np.ndarray((data.size,), dtype="V7", buffer=data, strides=(8,)).tobytes()
        return [CanFrame(i, b[j:j + 7], False) for i, j in zip(ids, range(0, len(b), 7))]

    def _wire(self, idx: np.ndarray, counter: int, counts: np.ndarray, status: np.ndarray | None) -> bytes:
        """Serial: the SAMPLE frames of chips ``idx``, back to back."""
        enc = self._encoder
        if enc is None:
            enc = self._encoder = SampleEncoder(self.node)
        return enc.wire(counter, counts, status, None if idx.size == self.n else idx)

    def sync_wire(self, frame: Out, msg: Sync, now_s: float, sel: np.ndarray | None = None):
        """Serial SYNC without a Python object per frame: ``(bytes, n_frames)`` — every answer
        of `sync`, back to back — or None when `sync` must be used (CAN, or a chip with a fault
        wrapper among ``sel``, whose frames go in between)."""
        if self.can or self._wrapped_in(sel):
            return None
        if self._imu_active():
            return None  # IMU records: `sync` encodes them
        ans, counts, status = self._answer(msg.counter, now_s, sel)
        if not ans.size:
            return b"", 0
        return self._wire(ans, msg.counter, counts, status), int(ans.size)

    def sync(self, frame: Out, msg: Sync, now_s: float, sel: np.ndarray | None = None, *,
             owners: bool = False):
        """Every chip's (of ``sel``) answer to SYNC ``msg`` in chip order (per-chip mode). With
        ``owners`` also the chip index of each frame (an int array)."""
        c = msg.counter
        wrapped = self._wrapped_in(sel)
        if wrapped:
            extra = {k: self.chips[k].handle(frame, now_s, msg) for k in wrapped}
        ans, counts, status = self._answer(c, now_s, sel)
        imu_owners = None
        if ans.size and self._imu_active():
            frames = self._imu_frames(ans, c, now_s, counts, status)
            n_per = np.where(self.imu_format[ans] == 0, 1, 1 if not self.can else 0)
            if self.can:  # classic: 2 or 3 frames a record, FD: 1
                fmt, fd = self.imu_format[ans], (self.imu_flags[ans] & int(ConfigImuFlag.FD)) != 0
                n_per = np.where(fmt == 0, 1, np.where(fd, 1, np.where(fmt == 2, 3, 2)))
            imu_owners = np.repeat(ans, n_per)
        elif self.can:
            frames = self._can_frames(ans, c, self._words(counts, status))
        elif ans.size:
            b = self._wire(ans, c, counts, status)
            frames = [b[i:i + 15] for i in range(0, len(b), 15)]
        else:
            frames = []
        own = ans if imu_owners is None else imu_owners
        if wrapped:
            frames, own = self._merge(frames, own, extra)
        return (frames, own) if owners else frames

    def _merge(self, frames: list, ans: np.ndarray, extra: dict):
        """Insert the wrapped chips' outputs among the vectorised ones, in chip order."""
        keys = ans.tolist()
        items = [(k, 0, f) for k, f in zip(keys, frames)]
        for k, r in extra.items():
            items += [(k, 1 + i, f) for i, f in enumerate(r)]
        items.sort(key=lambda t: (t[0], t[1]))
        return [f for _, _, f in items], np.array([k for k, _, _ in items], dtype=np.int64)

    def sync_words(self, frame: Out, msg: Sync, now_s: float, sel: np.ndarray | None = None):
        """SYNC for a packing gateway: ``(idx, word, other)`` — the plain chips that answered and
        their 40-bit sample words (int64), and the wrapped chips' frames ``other`` as ``[(k, frames)]``."""
        if self._imu_active():
            raise NotImplementedError("a packing gateway of IMU records (SNAPSHOT_IMU, docs §16.5) is not "
                                      "simulated yet: run 6/9-axis chips per chip (no --pack)")
        extra = [(k, self.chips[k].handle(frame, now_s, msg)) for k in self._wrapped_in(sel)]
        ans, counts, status = self._answer(msg.counter, now_s, sel)
        return ans, self._words(counts, status), extra

    def sync_samples(self, frame: Out, msg: Sync, now_s: float, sel: np.ndarray | None = None):
        """SYNC for a packing gateway: ``(idx, word, counts (m, 3), status (m,), other)`` — the
        plain chips' sample words and their fields as arrays (counts as the wire carries them:
        12-bit two's complement), and the wrapped chips' frames ``other`` as ``[(k, frames)]``."""
        ans, word, extra = self.sync_words(frame, msg, now_s, sel)
        u = np.stack([(word >> s) & 0xFFF for s in (0, 12, 24)], axis=1)
        counts = ((u ^ 0x800) - 0x800).astype(np.int64)
        status = (word >> 36) & 0xF
        return ans, word, counts, status, extra

    def __len__(self) -> int:
        return self.n

    def __repr__(self) -> str:
        return f"ChipArray({self.n} chips, transport={self.transport!r})"


def _imu_can(node: int, counter: int, rec: bytes, fd: bool, fmt) -> list[CanFrame]:
    """One IMU record's CAN frames (docs §16.3, §16.4) from its 13/19 record bytes."""
    ctr = counter.to_bytes(2, "little")
    if fd:
        payload = ctr + rec
        pad = 16 if len(payload) <= 16 else 24
        return [CanFrame(make_id(MsgType.IMU_SAMPLE, node), payload + bytes(pad - len(payload)), True)]
    out = [CanFrame(make_id(MsgType.IMU_GYRO, node), ctr + rec[7:13], False)]
    if fmt == SampleFormat.IMU9:
        out.append(CanFrame(make_id(MsgType.IMU_MAG, node), ctr + rec[13:19], False))
    out.append(CanFrame(make_id(MsgType.IMU_ACCEL, node), ctr[:1] + rec[:7], False))
    return out


assert NODE_BROADCAST == 0

