"""All the chips of a sheet as arrays: one SYNC answered by every chip in one numpy step.

`ChipArray` holds the per-chip state the hot paths need (power, state, node id, link, START seen,
last counter, missed SYNCs, range, timers) in arrays of length N. Its two hot paths are vectorised:

* **SYNC** (`ChipArray.sync`): which chips answer, the missed-SYNC bookkeeping, one batch read of
  the sensors, the FAULT transition of an INVALID sample, the range shift, the 40-bit sample
  words, and — per-chip mode — every SAMPLE frame encoded at once (`_SampleCodec`: the CRC as a
  sum of per-byte table terms, COBS by a table keyed on where the zeros are, two 64-bit lanes a
  frame; `ChipArray.sync_wire` gives the frames as one byte string), or — packed mode
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

Sans-I/O and time as an argument, as `chip.ChipModel`.
"""

from __future__ import annotations

import binascii
from typing import Callable, Sequence

import numpy as np

from protocol.can import CanFrame, make_id
from protocol.chip_interface import DEFAULT_CAPABILITIES, Out, check_chip_args
from protocol.constants import SampleStatus
from protocol.messages import NODE_BROADCAST, PROTOCOL_VERSION, ChipState, MsgType, Status, StatusFlag, Sync

from .chip import ChipModel
from .faults import FaultSpec, FaultStats, wrap_chip

__all__ = ["ChipArray", "ArrayChip", "BatchSensor", "encode_samples_serial", "crc16_ccitt_batch",
           "cobs_encode_batch"]

#: ``(now_s, idx) -> (counts (m, 3) int64 ±2 g ADC counts, status (m,) int64 SampleStatus bits)``
BatchSensor = Callable[[float, np.ndarray], tuple[np.ndarray, np.ndarray]]

_BOOT, _IDLE, _STREAMING, _FAULT = (int(ChipState.BOOT), int(ChipState.IDLE), int(ChipState.STREAMING),
                                    int(ChipState.FAULT))
_INVALID = int(SampleStatus.INVALID)
_SAT = 255
_FIELD_SHIFT = np.array([1, 1 << 12, 1 << 24], dtype=np.int64)  # x, y, z into the sample word


# ---------------------------------------------------------------------------------------------
# batch encoding
# ---------------------------------------------------------------------------------------------

def _crc_table() -> np.ndarray:
    t = np.zeros(256, dtype=np.uint16)
    for b in range(256):
        c = b << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) if c & 0x8000 else (c << 1)
        t[b] = c & 0xFFFF
    return t


_CRC_TABLE = _crc_table()


def crc16_ccitt_batch(rows: np.ndarray) -> np.ndarray:
    """CRC-16/CCITT-FALSE (``binascii.crc_hqx(row, 0xFFFF)``) of every row of ``rows`` (m, k) uint8.

    >>> import binascii
    >>> rows = np.frombuffer(b"123456789" * 2, np.uint8).reshape(2, 9)
    >>> [hex(int(c)) for c in crc16_ccitt_batch(rows)], hex(binascii.crc_hqx(b"123456789", 0xFFFF))
    (['0x29b1', '0x29b1'], '0x29b1')
    """
    crc = np.full(rows.shape[0], 0xFFFF, dtype=np.uint16)
    for j in range(rows.shape[1]):
        crc = (crc << np.uint16(8)) ^ _CRC_TABLE[(crc >> np.uint16(8)) ^ rows[:, j]]
    return crc


def cobs_encode_batch(rows: np.ndarray) -> np.ndarray:
    """COBS (``cobs.cobs.encode``) of every row of ``rows`` (m, k) uint8, k < 254: (m, k + 1).

    >>> from cobs import cobs
    >>> rows = np.array([[0, 1, 0, 2], [3, 4, 5, 6]], np.uint8)
    >>> [bytes(r) for r in cobs_encode_batch(rows)] == [cobs.encode(bytes(r)) for r in rows]
    True
    """
    m, k = rows.shape
    if k >= 254:
        raise ValueError(f"Invalid row length {k} (COBS batch needs < 254)")
    zero = np.concatenate([rows == 0, np.ones((m, 1), dtype=bool)], axis=1)  # a virtual zero at k
    pos = np.where(zero, np.arange(k + 1), k + 1)
    nxt = np.minimum.accumulate(pos[:, ::-1], axis=1)[:, ::-1]  # index of the next zero at or after j
    out = np.empty((m, k + 1), dtype=np.uint8)
    out[:, 0] = nxt[:, 0] + 1
    after = nxt[:, 1:] - np.arange(k)  # for a zero at i: distance to the next zero after it
    out[:, 1:] = np.where(zero[:, :k], after, rows)
    return out


def _crc_position_tables(length: int) -> tuple[np.ndarray, int]:
    """CRC-16/CCITT-FALSE of a ``length``-byte message as a sum of per-byte terms.

    The CRC register update is linear over GF(2), so for messages of one length
    ``crc(m) = c0 ^ t[0][m[0]] ^ t[1][m[1]] ^ ... ^ t[length-1][m[length-1]]``, with ``t[j][b]`` the
    CRC (init 0) of byte ``b`` at position ``j`` and zeros elsewhere, and ``c0`` the CRC (init
    0xFFFF) of ``length`` zero bytes. Returns ``(t (length, 256) uint16, c0)``.
    """
    t = np.zeros((length, 256), dtype=np.uint16)
    for j in range(length):
        c = _CRC_TABLE.copy()  # byte b at position j, init 0: the state after it is TABLE[b]
        for _ in range(length - 1 - j):  # then the zero bytes after it
            c = (c << np.uint16(8)) ^ _CRC_TABLE[c >> np.uint16(8)]
        t[j] = c
    return t, binascii.crc_hqx(bytes(length), 0xFFFF)


def _pair(t: np.ndarray, j: int) -> np.ndarray:
    """``t[j][v & 0xFF] ^ t[j + 1][v >> 8]`` for every 16-bit little-endian value v (65536,)."""
    return (t[j + 1][:, None] ^ t[j][None, :]).ravel()


def _cobs_table(k: int) -> np.ndarray:
    """COBS of a ``k``-byte row, by where its zeros are: row ``z`` (bit i set: byte i is 0) holds
    the code bytes of the encoding at their places and 0 at the copied bytes, so that
    ``COBS(row) = table[z] | (0, *row)`` — the code bytes sit exactly where the row's zeros are."""
    z = np.arange(1 << k, dtype=np.int64)
    zero = ((z[:, None] >> np.arange(k)) & 1).astype(bool)
    enc = cobs_encode_batch(np.where(zero, 0, 1).astype(np.uint8))
    enc[:, 1:][~zero] = 0
    return enc


class _SampleCodec:
    """SAMPLE frames as two little-endian 64-bit lanes per frame, with whole-column arithmetic.

    One SAMPLE on the wire, as a 16-byte row (the last byte is padding)::

        0 COBS code | 1 version | 2 type | 3-4 node | 5-6 counter | 7-11 word | 12-13 CRC | 14 0x00

    * CRC: linear over GF(2) (`_crc_position_tables`): a term for the node (kept per chip), one
      for the counter (per SYNC) and one per byte of the word, each stored
      already at the CRC's place in lane 1 (bits 32-47, high byte first), so they are only XORed.
    * COBS: the same table entries carry, at bit 48 + i, whether body byte i (0-12, before COBS)
      is 0; the CRC's two bytes add theirs by a lookup each; the 13-bit zero pattern then looks
      up every code byte of the frame at once (`_cobs_table`). The code bytes sit exactly where
      the zeros are (and at byte 0), so they are ORed into the lanes.

    int64 throughout (bit 63 wraps as in uint64; only values below 2**61 are shifted right).
    """

    def __init__(self) -> None:
        t, c0 = _crc_position_tables(11)  # body bytes 0-10: version, type, node, counter, word
        t = t.astype(np.int64)

        def term(lo: int, hi: int | None, pos: int) -> np.ndarray:
            """Lane-1 entries by the value of body bytes ``pos`` (and ``pos + 1``): CRC term and
            zero flags."""
            v = np.arange(256 if hi is None else 65536, dtype=np.int64)
            b0, b1 = v & 0xFF, v >> 8
            crc = t[lo][b0] ^ (t[hi][b1] if hi is not None else 0)
            e = ((crc >> 8) << 32) | ((crc & 0xFF) << 40) | ((b0 == 0).astype(np.int64) << (48 + pos))
            if hi is not None:
                e |= (b1 == 0).astype(np.int64) << (48 + pos + 1)
            return e
        const = c0 ^ int(t[0][PROTOCOL_VERSION]) ^ int(t[1][int(MsgType.SAMPLE)])
        self.node = term(2, 3, 2) ^ ((const >> 8) << 32 | (const & 0xFF) << 40)
        self.counter = term(4, 5, 4)
        # the word's five bytes: a 256-entry table each (2 kB, in the L1 cache; 16-bit tables of
        # 512 kB each missed the cache on nearly every lookup of a SYNC)
        self.w0, self.w1, self.w2, self.w3, self.w4 = (term(6 + b, None, 6 + b) for b in range(5))
        b = np.arange(256, dtype=np.int64)  # CRC bytes: high at lane-1 bits 32-39, low at 40-47
        self.crc_hi_zero = (b == 0).astype(np.int64) << 11
        self.crc_lo_zero = (b == 0).astype(np.int64) << 12
        self.lane0 = PROTOCOL_VERSION << 8 | int(MsgType.SAMPLE) << 16
        cobs16 = np.zeros((1 << 13, 16), dtype=np.uint8)
        cobs16[:, :14] = _cobs_table(13)
        self.cobs = cobs16.view("V16")[:, 0]  # (8192,) 16-byte rows, gathered whole
        self.m8, self.s8, self.s16, self.s24, self.s32, self.s40, self.s48, self.s56 = (
            np.int64(0xFF), np.int64(8), np.int64(16), np.int64(24), np.int64(32), np.int64(40), np.int64(48),
            np.int64(56))
        self.crc_bits = np.int64(0xFFFF << 32)

    def node_terms(self, node: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What depends on the node alone: ``(lane-0 bytes 1-4, the node's lane-1 entry)``."""
        nd = np.asarray(node).astype(np.int64)
        return self.lane0 | (nd << 24), self.node[nd]

    def encode(self, base0: np.ndarray, node1: np.ndarray, counter: int, word: np.ndarray) -> np.ndarray:
        """(m, 2) int64 lanes of the frames; ``base0``, ``node1`` from `node_terms`."""
        w = word if word.dtype == np.int64 else word.astype(np.int64)
        c = counter & 0xFFFF
        m8 = self.m8
        s = node1 ^ self.counter[c]
        s ^= self.w0[w & m8]
        s ^= self.w1[(w >> self.s8) & m8]
        s ^= self.w2[(w >> self.s16) & m8]
        s ^= self.w3[(w >> self.s24) & m8]
        s ^= self.w4[w >> self.s32]
        zeros = (s >> self.s48) | self.crc_hi_zero[(s >> self.s32) & m8]
        zeros |= self.crc_lo_zero[(s >> self.s40) & m8]
        out = self.cobs[zeros].view("<i8").reshape(-1, 2)  # the code bytes (a fresh array)
        out[:, 0] |= base0 | (c << 40)
        out[:, 0] |= w << self.s56
        out[:, 1] |= w >> self.s8
        out[:, 1] |= s & self.crc_bits
        return out


_CODEC: _SampleCodec | None = None


def _codec() -> _SampleCodec:
    global _CODEC
    if _CODEC is None:
        _CODEC = _SampleCodec()
    return _CODEC


def encode_samples_serial(node: np.ndarray, counter: int, word: np.ndarray) -> np.ndarray:
    """Every SAMPLE frame (version, SAMPLE, node, counter, 5-byte word, CRC, COBS, 0x00) as rows
    of a (m, 15) uint8 array: the bytes `protocol.framing.encode` gives for each.

    ``node`` (m,) ints < 65536, ``word`` (m,) 40-bit sample words (int64 or uint64)."""
    tb = _codec()
    base0, node1 = tb.node_terms(node)
    return samples_rows(tb.encode(base0, node1, counter, np.asarray(word)))


def samples_rows(lanes: np.ndarray) -> np.ndarray:
    """The (m, 2) lanes of `_SampleCodec.encode` as (m, 15) uint8 frames (a view)."""
    return lanes.astype("<i8", copy=False).view(np.uint8).reshape(-1, 16)[:, :15]


def samples_wire(lanes: np.ndarray) -> bytes:
    """The (m, 2) lanes of `_SampleCodec.encode`: the m frames back to back, as the wire has them."""
    lanes = np.ascontiguousarray(lanes, dtype="<i8")
    # one 15-byte item per 16-byte row: a single copy loop (a (m, 15) uint8 slice copies row by row)
    return np.ndarray((lanes.shape[0],), dtype="V15", buffer=lanes, strides=(16,)).tobytes()


# ---------------------------------------------------------------------------------------------
# the per-chip view: a ChipModel whose state lives in the arrays
# ---------------------------------------------------------------------------------------------

#: the array's derived values (None: derive again) that a field written through a view invalidates
_STALE_ON_SET = {
    "node": ("_node_terms",),
    "last_counter": ("_all_last",),
    "state": ("_steady", "_next_due"),
    "powered": ("_steady", "_next_due"),
    "streaming": ("_steady",),
    "range": ("_range_any",),
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

    def __init__(self, arr: "ChipArray", k: int, uid: int, sensor, *, transport: str, fd: bool,
                 capabilities: int, calibration) -> None:
        self._arr, self._k = arr, k
        super().__init__(uid, sensor, transport=transport, fd=fd, capabilities=capabilities,
                         calibration=calibration)

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
                 faults: FaultSpec | None = None, fault_stats: FaultStats | None = None) -> None:
        n = self.n = len(uids)
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
        # derived values, None until needed (and again after a view writes what they come from)
        self._node_terms: tuple[np.ndarray, np.ndarray] | None = None  # `_SampleCodec.node_terms` of `node`
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
                                        capabilities=capabilities, calibration=calibrations[k]))
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
            _codec()  # the SAMPLE tables now, not in the first SYNC's answer time

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
            self.next_heartbeat_s[hb] = np.maximum(self.next_heartbeat_s[hb] + period, now_s)
            frames = self._status_frames(hb, now_s)
            if not items:
                return frames
            items += [(k, [f]) for k, f in zip(hb.tolist(), frames)]
        items.sort(key=lambda t: t[0])
        return [f for _, r in items for f in r]

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
        crc = crc16_ccitt_batch(body[:, :12])
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
        """A frame addressed to ``node``: only the chips speaking from that node hear it."""
        out: list[Out] = []
        for k in np.flatnonzero((self.node == node) & self._sel(sel)).tolist():
            out += self.chips[k].handle(frame, now_s, decoded)
        return out

    def _answer(self, counter: int, now_s: float, sel):
        """The vectorised SYNC for the plain chips: updates the state, returns ``(idx, word)``."""
        if sel is None and self._no_scalar:
            steady = self._steady
            if steady is None:
                steady = self._steady = bool((self._plain & self.powered & self.streaming
                                              & (self.state == _STREAMING)).all())
            if steady:
                return self._every, self._answer_all(counter, now_s, self._every)
        st = self.state
        ans = np.flatnonzero(self._plain & self._sel(sel) & self.powered & self.streaming
                             & ((st == _STREAMING) | (st == _FAULT)))
        if ans.size == 0:
            return ans, np.zeros(0, dtype=np.int64)
        if ans.size == self.n and self._no_scalar and not (st == _FAULT).any():
            return ans, self._answer_all(counter, now_s, ans)
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
            xyz[live] = c
            sts[live] = s
        word = ((xyz[:, 0] & 0xFFF) | ((xyz[:, 1] & 0xFFF) << 12) | ((xyz[:, 2] & 0xFFF) << 24)
                | ((sts & 0xF) << 36))
        return ans, word

    def _answer_all(self, counter: int, now_s: float, ans: np.ndarray) -> np.ndarray:
        """`_answer` when every chip answers with a fresh sample (the streaming steady state):
        the same arithmetic on whole arrays, no gathers; when every chip last answered the
        previous counter (the usual next SYNC) there is no gap to count."""
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
        if not s.any():  # every sample OK: no fault, no status bits
            rng = self._range_any
            if rng is None:
                rng = self._range_any = bool(self.range.any())
            if rng:
                c = c >> self.range[:, None]
            return (c & 0xFFF) @ _FIELD_SHIFT
        if (s & _INVALID).any():
            bad = (s & _INVALID) != 0
            self.state[bad] = _FAULT
            self._steady = None
            c = c.copy()
            c[bad] = 0
        else:
            bad = None
        rng = self._range_any
        if rng is None:
            rng = self._range_any = bool(self.range.any())
        if rng:
            sh = c >> self.range[:, None]
            c = sh if bad is None else np.where(bad[:, None], c, sh)
        return ((c & 0xFFF) @ _FIELD_SHIFT) | ((s & 0xF) << 36)

    def _wrapped_in(self, sel) -> list[int]:
        if sel is None:
            return self._wrapped_idx
        return [k for k in self._wrapped_idx if sel[k]]

    def encode(self, idx: np.ndarray, counter: int, word: np.ndarray) -> list[Out]:
        """The SAMPLE frames of chips ``idx`` (their node ids) for ``counter``, batch-encoded."""
        if self.can:
            nodes = self.node[idx].tolist()
            cb = counter.to_bytes(2, "little")
            return [CanFrame(make_id(MsgType.SAMPLE, nd), cb + w.to_bytes(5, "little"), False)
                    for nd, w in zip(nodes, word.tolist())]
        if not idx.size:
            return []
        b = self._wire(idx, counter, word)
        return [b[i:i + 15] for i in range(0, len(b), 15)]

    def _wire(self, idx: np.ndarray, counter: int, word: np.ndarray) -> bytes:
        """Serial: the SAMPLE frames of chips ``idx``, back to back."""
        tb = _codec()
        terms = self._node_terms
        if terms is None:
            terms = self._node_terms = tb.node_terms(self.node)
        base0, node1 = terms
        if idx.size != self.n:
            base0, node1 = base0[idx], node1[idx]
        return samples_wire(tb.encode(base0, node1, counter, word))

    def sync_wire(self, frame: Out, msg: Sync, now_s: float, sel: np.ndarray | None = None):
        """Serial SYNC without a Python object per frame: ``(bytes, n_frames)`` — every answer
        of `sync`, back to back — or None when `sync` must be used (CAN, or a chip with a fault
        wrapper among ``sel``, whose frames go in between)."""
        if self.can or self._wrapped_in(sel):
            return None
        ans, word = self._answer(msg.counter, now_s, sel)
        if not ans.size:
            return b"", 0
        return self._wire(ans, msg.counter, word), int(ans.size)

    def sync(self, frame: Out, msg: Sync, now_s: float, sel: np.ndarray | None = None, *,
             owners: bool = False):
        """Every chip's (of ``sel``) answer to SYNC ``msg`` in chip order (per-chip mode). With
        ``owners`` also the chip index of each frame (an int array)."""
        c = msg.counter
        wrapped = self._wrapped_in(sel)
        if wrapped:
            extra = {k: self.chips[k].handle(frame, now_s, msg) for k in wrapped}
        ans, word = self._answer(c, now_s, sel)
        frames = self.encode(ans, c, word)
        own = ans
        if wrapped:
            frames, own = self._merge(frames, ans, extra)
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
        extra = [(k, self.chips[k].handle(frame, now_s, msg)) for k in self._wrapped_in(sel)]
        ans, word = self._answer(msg.counter, now_s, sel)
        return ans, word, extra

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


assert NODE_BROADCAST == 0
