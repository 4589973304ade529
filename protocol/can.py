"""CAN mapping (docs/protocol.md §7): 29-bit identifier layout and payloads, classic and FD, and
`CanDecoder`, the sans-I/O receiver: CAN frames in, events out (`protocol.framing.StreamDecoder`'s
counterpart for CAN).

The payload is the message payload of docs §4 unchanged (CAN has its own CRC). The identifier::

    bits 28..26  priority   (per type, docs §7.1; 0 = wins arbitration)
    bits 25..20  type       (MsgType, 6 bits)
    bits 19..16  version    (PROTOCOL_VERSION, 4 bits)
    bits 15..0   node       (source for chip -> host, destination for host -> chip; 0 = broadcast)

Classic CAN carries payloads up to 8 bytes: every message but SNAPSHOT. SNAPSHOT needs CAN FD and
is padded with 0x00 up to the next valid FD length (its count field says how many samples).

>>> f = to_can(Sync(counter=0x1234))
>>> hex(f.arbitration_id), f.data.hex(), f.is_fd
('0x1010000', '3412', False)
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from .framing import DecodeError, ErrorReason
from .messages import (IMU_RECORD_SIZE, MESSAGE_TYPES, PROTOCOL_VERSION, ImuAccel, ImuGyro, ImuMag, ImuSample,
                       Message, MsgType, PayloadError, Sample, SampleBatch, SampleFormat, Snapshot, SnapshotImu,
                       Sync, decode_payload, SAMPLE_WORD_SIZE, unpack_sample_words)  # noqa: F401 (Sync: doctest)

__all__ = ["EchoFilter", "CanDecoder", "CanDecoderStats", "CanFrame", "FrameBlock", "CAN_CLASSIC_MTU", "CAN_FD_MTU", "FD_LENGTHS", "MAX_FD_SNAPSHOT_SAMPLES", "MAX_FD_IMU_RECORDS", "INCOMPLETE_IMU",
           "imu_can_frames",
           "make_id", "split_id", "to_can", "from_can", "decode_can", "fd_length"]

CAN_CLASSIC_MTU = 8
CAN_FD_MTU = 64
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
#: SNAPSHOT samples in one CAN FD frame: (64 - 5) // 5
MAX_FD_SNAPSHOT_SAMPLES = (CAN_FD_MTU - Snapshot.HEADER_SIZE) // SAMPLE_WORD_SIZE
assert MAX_FD_SNAPSHOT_SAMPLES == 11
#: SNAPSHOT_IMU records in one CAN FD frame by format (docs §16.5): (64 - 6) // 13 and // 19
MAX_FD_IMU_RECORDS = {f: (CAN_FD_MTU - SnapshotImu.HEADER_SIZE) // size for f, size in IMU_RECORD_SIZE.items()}
assert MAX_FD_IMU_RECORDS == {SampleFormat.IMU6: 4, SampleFormat.IMU9: 3}
#: IMU_SAMPLE on CAN FD: padded data length -> payload length (docs §16.3)
_FD_IMU_SAMPLE = {16: 15, 24: 21}

_PRIORITY_SHIFT, _TYPE_SHIFT, _VERSION_SHIFT = 26, 20, 16
#: the detail's start of the event a `CanDecoder` reports for classic IMU frames that make no record (§16.4)
INCOMPLETE_IMU = "incomplete IMU record"


class CanFrame(NamedTuple):
    """What python-can's ``can.Message`` needs: ``arbitration_id`` (29-bit, extended), ``data``, ``is_fd``."""

    arbitration_id: int
    data: bytes
    is_fd: bool


@dataclass(frozen=True, slots=True, eq=False)
class FrameBlock:
    """Consecutive classic extended data frames of 7 bytes, as arrays: what
    `host.transport.slcan.BufferedSlcanBus.drain_blocks` hands over for a run of them, and
    `host.transport.ports.CanTransport` decodes without a python-can message per frame.

    Attributes
    ----------
    arbitration_id : ndarray, shape (n,), uint32
        29-bit identifiers.
    data : ndarray, shape (n, 7), uint8
        Their data bytes.
    """

    arbitration_id: np.ndarray
    data: np.ndarray

    def __len__(self) -> int:
        return int(self.arbitration_id.shape[0])


def make_id(type_code: int, node: int, priority: int | None = None, version: int = PROTOCOL_VERSION) -> int:
    """The 29-bit identifier for a type and node; priority defaults to the type's (docs §7.1)."""
    if priority is None:
        priority = MESSAGE_TYPES[MsgType(type_code)].PRIORITY
    if not (0 <= priority < 8 and 0 <= type_code < 64 and 0 <= version < 16 and 0 <= node < 0x10000):
        raise ValueError(f"Invalid identifier parts: priority={priority} type={type_code} "
                         f"version={version} node={node}")
    return (priority << _PRIORITY_SHIFT) | (type_code << _TYPE_SHIFT) | (version << _VERSION_SHIFT) | node


def split_id(arbitration_id: int) -> tuple[int, int, int, int]:
    """``(priority, type, version, node)`` of a 29-bit identifier."""
    return ((arbitration_id >> _PRIORITY_SHIFT) & 0x7, (arbitration_id >> _TYPE_SHIFT) & 0x3F,
            (arbitration_id >> _VERSION_SHIFT) & 0xF, arbitration_id & 0xFFFF)


def fd_length(n: int) -> int:
    """Smallest CAN FD data length >= n."""
    for length in FD_LENGTHS:
        if length >= n:
            return length
    raise ValueError(f"Payload of {n} bytes exceeds CAN FD's {CAN_FD_MTU}")


def to_can(msg: Message, *, fd: bool | None = None) -> CanFrame:
    """A message as one CAN frame.

    ``fd=None`` uses FD only when the payload needs it; ``fd=False`` raises ValueError for a
    payload over 8 bytes; ``fd=True`` always sends FD.
    """
    payload = msg.payload()
    if fd is None:
        fd = len(payload) > CAN_CLASSIC_MTU
    if not fd and len(payload) > CAN_CLASSIC_MTU:
        raise ValueError(f"{msg.TYPE.name} payload of {len(payload)} bytes needs CAN FD "
                         f"(classic CAN carries {CAN_CLASSIC_MTU})")
    if fd:
        payload = payload + bytes(fd_length(len(payload)) - len(payload))
    return CanFrame(make_id(msg.TYPE, msg.node, msg.PRIORITY), payload, fd)


def imu_can_frames(msg: ImuSample, *, fd: bool = False) -> list[CanFrame]:
    """An IMU_SAMPLE as CAN frames (docs §16.3, §16.4): one FD frame, or on classic CAN IMU_GYRO
    (+ IMU_MAG) + IMU_ACCEL, in their sending order."""
    from .messages import imu_sample_to_can_parts
    if fd:
        return [to_can(msg, fd=True)]
    return [to_can(p, fd=False) for p in imu_sample_to_can_parts(msg)]


def decode_can(arbitration_id: int, data: bytes, *, is_extended_id: bool = True,
               is_fd: bool = False) -> Message | DecodeError:
    """One CAN frame -> message, or a `DecodeError` event. Never raises.

    A receiver accepts any priority bits (a conformance check holds senders to the table).
    """
    data = bytes(data)
    excerpt = data[:16]
    if not is_extended_id:
        return DecodeError(ErrorReason.BAD_FIELD, f"standard 11-bit identifier 0x{arbitration_id:X}: "
                                                  "capsheet uses 29-bit identifiers", excerpt)
    if not 0 <= arbitration_id < (1 << 29):
        return DecodeError(ErrorReason.BAD_FIELD, f"identifier 0x{arbitration_id:X} exceeds 29 bits", excerpt)
    _prio, type_code, version, node = split_id(arbitration_id)
    if version != PROTOCOL_VERSION:
        return DecodeError(ErrorReason.BAD_VERSION, f"peer speaks protocol version {version}, "
                                                    f"this is version {PROTOCOL_VERSION}", excerpt, version)
    if len(data) > (CAN_FD_MTU if is_fd else CAN_CLASSIC_MTU) or (is_fd and len(data) not in FD_LENGTHS):
        return DecodeError(ErrorReason.BAD_LENGTH, f"{len(data)} data bytes is not a valid "
                                                   f"{'CAN FD' if is_fd else 'classic CAN'} length", excerpt)
    need = None
    if type_code == MsgType.SNAPSHOT and len(data) >= Snapshot.HEADER_SIZE:
        need, what = Snapshot.HEADER_SIZE + SAMPLE_WORD_SIZE * data[4], f"SNAPSHOT with count {data[4]}"
    elif (type_code == MsgType.SNAPSHOT_IMU and len(data) >= SnapshotImu.HEADER_SIZE
          and data[5] in IMU_RECORD_SIZE):  # another format: BAD_FIELD from the payload decoder
        need = SnapshotImu.HEADER_SIZE + IMU_RECORD_SIZE[data[5]] * data[4]
        what = f"SNAPSHOT_IMU with format {data[5]} and count {data[4]}"
    elif type_code == MsgType.IMU_SAMPLE and is_fd:
        need = _FD_IMU_SAMPLE.get(len(data))
        if need is None:
            return DecodeError(ErrorReason.BAD_LENGTH, f"IMU_SAMPLE on CAN FD is 16 or 24 bytes, got {len(data)}",
                               excerpt)
        what = "IMU_SAMPLE"
    if need is not None:
        expected = fd_length(need) if is_fd and need <= CAN_FD_MTU else need
        if len(data) != expected:
            return DecodeError(ErrorReason.BAD_LENGTH, f"{what} needs {expected} bytes, got {len(data)}", excerpt)
        if any(data[need:]):
            return DecodeError(ErrorReason.BAD_FIELD, "CAN FD padding is not 0x00", excerpt)
        data = data[:need]
    try:
        return decode_payload(type_code, node, data)
    except PayloadError as exc:
        return DecodeError(ErrorReason[exc.reason], exc.detail, excerpt)


def from_can(arbitration_id: int, data: bytes, *, is_extended_id: bool = True, is_fd: bool = False) -> Message:
    """Like `decode_can` but raises ``ValueError`` with the reason for a bad frame."""
    out = decode_can(arbitration_id, data, is_extended_id=is_extended_id, is_fd=is_fd)
    if isinstance(out, DecodeError):
        raise ValueError(f"{out.reason.name}: {out.detail}")
    return out


class EchoFilter:
    """Recognise the echo of frames this node sent, on interfaces that hand a sender its own frames
    back (python-can's ``udp_multicast`` does, whatever ``receive_own_messages`` says).

    `sent` records each frame put on the bus (the last ``size``); `is_echo` answers True once per
    recorded frame whose identifier and data match, and forgets it. Sans-I/O.

    >>> f = EchoFilter()
    >>> f.sent(0x100, b"\\x01"); f.is_echo(0x100, b"\\x01"), f.is_echo(0x100, b"\\x01"), f.echoes
    (True, False, 1)
    """

    __slots__ = ("size", "echoes", "_q", "_n", "_ids")

    def __init__(self, size: int = 512) -> None:
        from collections import deque
        if not (isinstance(size, int) and size >= 1):
            raise ValueError(f"Invalid size: {size!r} (need an integer >= 1)")
        self.size = size
        self.echoes = 0
        self._q: deque = deque()
        self._n: dict = {}
        self._ids: dict = {}  # identifier -> frames recorded with it

    def __len__(self) -> int:
        """Frames recorded and not yet echoed (0: nothing to look for; a receiver may skip `is_echo`)."""
        return len(self._q)

    def identifiers(self):
        """The identifiers of the frames recorded and not yet echoed (a receiver that decodes frames
        in bulk looks up only the frames that carry one of them)."""
        return self._ids.keys()

    def _drop_id(self, can_id: int) -> None:
        k = self._ids[can_id] - 1
        if k:
            self._ids[can_id] = k
        else:
            del self._ids[can_id]

    def sent(self, can_id: int, data: bytes) -> None:
        key = (can_id, bytes(data))
        self._q.append(key)
        self._n[key] = self._n.get(key, 0) + 1
        self._ids[can_id] = self._ids.get(can_id, 0) + 1
        if len(self._q) > self.size:
            old = self._q.popleft()
            self._drop_id(old[0])
            k = self._n[old] - 1
            if k:
                self._n[old] = k
            else:
                del self._n[old]

    def is_echo(self, can_id: int, data: bytes) -> bool:
        key = (can_id, bytes(data))
        k = self._n.get(key, 0)
        if not k:
            return False
        if k > 1:
            self._n[key] = k - 1
        else:
            del self._n[key]
        self._q.remove(key)
        self._drop_id(can_id)
        self.echoes += 1
        return True


# --------------------------------------------------------------------------------------------
# The receiver: frames in, events out
# --------------------------------------------------------------------------------------------

@dataclass
class CanDecoderStats:
    """Counters of a `CanDecoder`: what came in, and what was dropped without an event.

    Attributes
    ----------
    bytes_in : int
        Data bytes of every data frame fed (remote and error frames carry none).
    frames : int
        Messages decoded (every SAMPLE of a `SampleBatch` counts).
    errors : Counter
        `DecodeError` events by `ErrorReason` (each was also returned as an event).
    error_frames : int
        CAN error frames (the bus signalled an error; the sender retransmits): dropped.
    fd_on_classic : int
        CAN FD frames on a decoder for a classic bus (``fd=False``): a configuration mismatch, dropped.
    remote_frames : int
        Remote frames (capsheet uses none): dropped.
    """

    bytes_in: int = 0
    frames: int = 0
    errors: Counter = field(default_factory=Counter)
    error_frames: int = 0
    fd_on_classic: int = 0
    remote_frames: int = 0


#: identifier bits 25..16 (type and version, docs §7) of a SAMPLE frame of this protocol version
_TYPE_VERSION_MASK = 0x3FF0000
_SAMPLE_TYPE_VERSION = make_id(MsgType.SAMPLE, 0, 0) & _TYPE_VERSION_MASK


class CanDecoder:
    """Feed CAN frames, get messages, `SampleBatch` runs and `DecodeError` events, in wire order.

    Sans-I/O (no python-can import): a frame is any object with python-can ``Message``'s
    attributes (``arbitration_id``, ``data``, ``is_extended_id``, ``is_fd``, ``is_error_frame``,
    ``is_remote_frame``), or a `FrameBlock` (a run of 7-byte classic extended frames as arrays).
    In one pass: runs of well-formed SAMPLE frames are collected and unpacked together by numpy
    (one `SampleBatch` per run, as `StreamDecoder(batch_samples=True)` gives them on serial);
    every other frame, and any SAMPLE frame `decode_can` would reject, goes through `decode_can`
    one by one. Feeding the frames all at once, one by one, or in any other grouping gives the
    same messages (batches are cut at call boundaries).

    Parameters
    ----------
    fd : bool
        The bus was opened for CAN FD. On a classic decoder an FD frame is a configuration
        mismatch: dropped and counted (`CanDecoderStats.fd_on_classic`), not decoded.
    echo : EchoFilter, optional
        Frames this node sent: a bus that hands them back (python-can's ``udp_multicast``) has
        them dropped here (``echo.echoes`` counts them). Default: a new, empty filter.

    Wire input never raises; error and remote frames are dropped and counted in `stats`.

    >>> from types import SimpleNamespace as F
    >>> def frame(msg):
    ...     f = to_can(msg)
    ...     return F(arbitration_id=f.arbitration_id, data=f.data, is_extended_id=True, is_fd=f.is_fd,
    ...              is_error_frame=False, is_remote_frame=False)
    >>> from protocol.messages import Ack, Sample
    >>> dec = CanDecoder()
    >>> ev = dec.feed([frame(Sample(5, 7, 1, 2, 3, 0)), frame(Sample(6, 7, 4, 5, 6, 0)), frame(Ack(5, MsgType.START, 0))])
    >>> [type(e).__name__ for e in ev], ev[0].node.tolist(), dec.stats.frames
    (['SampleBatch', 'Ack'], [5, 6], 3)
    """

    def __init__(self, *, fd: bool = False, echo: EchoFilter | None = None) -> None:
        self.fd = bool(fd)
        self.echo = EchoFilter() if echo is None else echo
        self.stats = CanDecoderStats()
        self._imu_open: dict[int, list] = {}  # node -> [IMU_GYRO, IMU_MAG or None]: a record being assembled

    def _incomplete(self, detail: str) -> DecodeError:
        self.stats.errors[ErrorReason.BAD_FIELD] += 1
        return DecodeError(ErrorReason.BAD_FIELD, f"{INCOMPLETE_IMU}: {detail}", b"")

    def _assemble(self, ev) -> list:
        """Classic CAN IMU frames (docs §16.4) -> the IMU_SAMPLE they stand for, or incomplete-record events."""
        node, opened = ev.node, self._imu_open
        if isinstance(ev, ImuGyro):
            out = []
            if node in opened:
                old = opened[node][0]
                out.append(self._incomplete(f"node {node} counter {old.counter} got no IMU_ACCEL before "
                                            f"the IMU_GYRO of counter {ev.counter}; dropped"))
            opened[node] = [ev, None]
            return out
        o = opened.get(node)
        if isinstance(ev, ImuMag):
            if o is None or o[0].counter != ev.counter or o[1] is not None:
                return [self._incomplete(f"IMU_MAG of node {node} counter {ev.counter} without its IMU_GYRO; dropped")]
            o[1] = ev
            return []
        opened.pop(node, None)
        if o is None:
            return [self._incomplete(f"IMU_ACCEL of node {node} (counter byte {ev.counter_lo}) without its "
                                     "IMU_GYRO; dropped")]
        g, m = o
        if (g.counter & 0xFF) != ev.counter_lo:
            return [self._incomplete(f"node {node}: IMU_ACCEL of counter byte {ev.counter_lo} does not close "
                                     f"the record of counter {g.counter}; both dropped")]
        mag = (None, None, None) if m is None else (m.mx, m.my, m.mz)
        return [ImuSample(node, g.counter, ev.x, ev.y, ev.z, ev.status, ev.time_us, g.gx, g.gy, g.gz, *mag)]

    def close(self) -> list:
        """End of the stream: an incomplete-record event for every IMU record still open (§16.4)."""
        out = [self._incomplete(f"node {node} counter {o[0].counter} still open at the end of the stream")
               for node, o in sorted(self._imu_open.items())]
        self._imu_open.clear()
        return out

    def feed(self, frames, echoes: list | None = None) -> list:
        """Decode ``frames`` (python-can-like messages and `FrameBlock` s, in wire order); return
        their events in wire order. ``echoes``: a list to which ``(arbitration_id, data)`` of
        every frame dropped as an echo of this node's own is appended (for a capture)."""
        events: list = []
        pieces: list = []  # (node, data rows) of the current run of SAMPLE frames, in order
        datas: list = []  # ... and its frames not yet in a piece (one by one)
        nodes: list[int] = []
        st = self.stats
        errors = st.errors
        echo = self.echo
        n_bytes = 0
        n_frames = 0

        def flush() -> None:
            nonlocal n_frames
            if datas:
                pieces.append(_rows(nodes, datas))
                datas.clear()
                nodes.clear()
            if pieces:
                batch = _sample_run(pieces)
                n_frames += len(batch)
                events.append(batch)
                pieces.clear()

        def one(aid: int, data, is_extended_id: bool, is_fd: bool) -> None:
            nonlocal n_frames
            if echo and echo.is_echo(aid, data):
                if echoes is not None:
                    echoes.append((aid, bytes(data)))
                return
            if is_fd and not self.fd:  # the bus carries CAN FD but was opened classic: a mismatch
                st.fd_on_classic += 1
                return
            if ((aid & _TYPE_VERSION_MASK) == _SAMPLE_TYPE_VERSION and len(data) == Sample.SIZE
                    and is_extended_id and aid < (1 << 29) and (aid & 0xFFFF) != 0xFFFF):
                datas.append(data)
                nodes.append(aid & 0xFFFF)
                return
            # every SAMPLE decode_can accepts passed the test above: what is left is no SAMPLE
            ev = decode_can(aid, data, is_extended_id=is_extended_id, is_fd=is_fd)
            flush()
            if isinstance(ev, DecodeError):
                errors[ev.reason] += 1
            else:
                n_frames += 1
                if isinstance(ev, (ImuGyro, ImuMag, ImuAccel)):
                    events.extend(self._assemble(ev))
                    return
            events.append(ev)

        for f in frames:
            if type(f) is FrameBlock:
                ids, rows = f.arbitration_id, f.data
                n_bytes += rows.size
                fast = ((ids & _TYPE_VERSION_MASK) == _SAMPLE_TYPE_VERSION) & ((ids & 0xFFFF) != 0xFFFF)
                if echo:
                    pending = [i for i in echo.identifiers() if (i & _TYPE_VERSION_MASK) == _SAMPLE_TYPE_VERSION]
                    if pending:
                        fast &= ~np.isin(ids, pending)
                if fast.all():
                    bounds = [0, len(ids)]
                else:
                    bounds = [0, *(np.flatnonzero(np.diff(fast.astype(np.int8))) + 1).tolist(), len(ids)]
                for a, b in zip(bounds[:-1], bounds[1:]):
                    if fast[a]:
                        if datas:
                            pieces.append(_rows(nodes, datas))
                            datas.clear()
                            nodes.clear()
                        pieces.append(((ids[a:b] & 0xFFFF).astype(np.uint16), rows[a:b]))
                    else:
                        for k in range(a, b):
                            one(int(ids[k]), rows[k].tobytes(), True, False)
                continue
            if f.is_error_frame:
                st.error_frames += 1  # the bus signalled an error (then retransmits)
                continue
            if f.is_remote_frame:
                st.remote_frames += 1
                continue
            n_bytes += len(f.data)
            one(f.arbitration_id, f.data, f.is_extended_id, f.is_fd)
        flush()
        st.bytes_in += n_bytes
        st.frames += n_frames
        return events


def _rows(nodes: list[int], datas: list) -> tuple[np.ndarray, np.ndarray]:
    """SAMPLE frames given one by one -> ``(node uint16 (n,), data uint8 (n, 7))``."""
    return (np.array(nodes, dtype=np.uint16),
            np.frombuffer(b"".join(datas), dtype=np.uint8).reshape(len(datas), Sample.SIZE))


def _sample_run(pieces: list) -> SampleBatch:
    """Consecutive well-formed SAMPLE frames (7 data bytes each: counter u16, sample word), given
    as ``(node, data rows)`` pieces, as one batch unpacked in one numpy pass: the batch of the
    `Sample` messages `decode_can` makes of them."""
    if len(pieces) == 1:
        node, d = pieces[0]
    else:
        node = np.concatenate([p[0] for p in pieces])
        d = np.concatenate([p[1] for p in pieces])
    counter = (d[:, 0].astype(np.uint16) | (d[:, 1].astype(np.uint16) << 8))
    counts, status = unpack_sample_words(np.ascontiguousarray(d[:, 2:]).reshape(-1))
    return SampleBatch(node, counter, counts, status)
