"""CAN mapping (docs/protocol.md §7): 29-bit identifier layout and payloads, classic and FD.

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

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .framing import DecodeError, ErrorReason
from .messages import (MESSAGE_TYPES, PROTOCOL_VERSION, Message, MsgType, PayloadError, Snapshot, Sync,  # noqa: F401 (doctest)
                       decode_payload, SAMPLE_WORD_SIZE)

__all__ = ["EchoFilter", "CanFrame", "FrameBlock", "CAN_CLASSIC_MTU", "CAN_FD_MTU", "FD_LENGTHS", "MAX_FD_SNAPSHOT_SAMPLES",
           "make_id", "split_id", "to_can", "from_can", "decode_can", "fd_length"]

CAN_CLASSIC_MTU = 8
CAN_FD_MTU = 64
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
#: SNAPSHOT samples in one CAN FD frame: (64 - 5) // 5
MAX_FD_SNAPSHOT_SAMPLES = (CAN_FD_MTU - Snapshot.HEADER_SIZE) // SAMPLE_WORD_SIZE
assert MAX_FD_SNAPSHOT_SAMPLES == 11

_PRIORITY_SHIFT, _TYPE_SHIFT, _VERSION_SHIFT = 26, 20, 16


class CanFrame(NamedTuple):
    """What python-can's ``can.Message`` needs: ``arbitration_id`` (29-bit, extended), ``data``, ``is_fd``."""

    arbitration_id: int
    data: bytes
    is_fd: bool


@dataclass(frozen=True, slots=True, eq=False)
class FrameBlock:
    """Consecutive classic extended data frames of 7 bytes, as arrays: what
    `host.slcan.BufferedSlcanBus.drain_blocks` hands over for a run of them, and
    `host.transport.CanTransport` decodes without a python-can message per frame.

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
    if type_code == MsgType.SNAPSHOT and len(data) >= Snapshot.HEADER_SIZE:
        need = Snapshot.HEADER_SIZE + SAMPLE_WORD_SIZE * data[4]
        expected = fd_length(need) if is_fd and need <= CAN_FD_MTU else need
        if len(data) != expected:
            return DecodeError(ErrorReason.BAD_LENGTH, f"SNAPSHOT with count {data[4]} needs "
                                                       f"{expected} bytes, got {len(data)}", excerpt)
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
