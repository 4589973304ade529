"""What a transport received and sent, for whoever subscribes (`Capture`, handed over by
`host.transport.ports.Transport.begin_capture`), and `RawFrame`, one CAN frame of a
`protocol.can.FrameBlock` with python-can ``Message``'s attributes. Kept apart from the transports
themselves (host/transport/ports.py re-exports both by their old names)."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Any, NamedTuple

from protocol.can import FrameBlock

__all__ = ["Capture", "RawFrame"]


# --------------------------------------------------------------------------------------------
# Capture: what a transport received and sent, for whoever subscribes
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True, slots=True, eq=False)
class Capture:
    """One unit of traffic of a transport, as `Transport.begin_capture` hands it over.

    Attributes
    ----------
    transport : Transport
        Who moved it (``transport.name`` names the port or bus).
    direction : str
        ``"rx"`` (read from the wire) or ``"tx"`` (written to it).
    timestamp : float
        Host ``time.monotonic()`` seconds when it was read (after the read returned) or written.
    wall_time : float
        ``time.time()`` at the same instant (what log files stamp).
    kind : str
        ``"serial"`` or ``"can"``: what ``raw`` holds.
    raw : bytes or tuple
        Serial: the bytes as read or written (rx: one read, cut anywhere; tx: whole frames).
        CAN rx: the frames one receive drained, in wire order, as the bus delivered them
        (python-can ``Message`` s, and `protocol.can.FrameBlock` s from the SLCAN bus's fast
        path), the echoes of this host's own frames included. CAN tx: ``(message,)``, the
        python-can ``Message`` written.
    events : tuple
        Rx: what the decoder made of this input, exactly the events `Transport.recv` returns for
        it (a serial frame cut across reads comes with the read that completes it). Tx: the
        `protocol.Message` sent, or ``()`` for a raw send (`SerialTransport.send_bytes`,
        `CanTransport.send_frame`).
    echoes : tuple of (int, bytes)
        CAN rx: ``(arbitration_id, data)`` of the frames of ``raw`` recognised as this host's own
        handed back (python-can's ``udp_multicast`` does): dropped from ``events``. Else ``()``.
    """

    transport: Any
    direction: str
    timestamp: float
    wall_time: float
    kind: str
    raw: Any
    events: tuple = ()
    echoes: tuple = ()

    def frames(self, *, echoes: bool = False) -> list:
        """CAN: the frames of ``raw`` one by one, in wire order: python-can messages as they are,
        each row of a `protocol.can.FrameBlock` as a `RawFrame` (stamped ``wall_time``); the
        echoes of this host's own frames left out unless ``echoes``. Serial: ``[]``."""
        if self.kind != "can":
            return []
        out: list = []
        for f in self.raw:
            if type(f) is FrameBlock:
                out += [RawFrame(aid, row, timestamp=self.wall_time)
                        for aid, row in zip(f.arbitration_id.tolist(), map(bytes, f.data))]
            else:
                out.append(f)
        if echoes or not self.echoes:
            return out
        left = Counter(self.echoes)
        kept = []
        for f in out:
            key = (f.arbitration_id, bytes(f.data))
            if left.get(key) and not (f.is_error_frame or f.is_remote_frame):
                left[key] -= 1
                continue
            kept.append(f)
        return kept


class RawFrame(NamedTuple):
    """One received CAN frame with python-can ``Message``'s attributes (what `Capture.frames`
    makes of a `protocol.can.FrameBlock` row)."""

    arbitration_id: int
    data: bytes
    is_extended_id: bool = True
    is_fd: bool = False
    is_error_frame: bool = False
    is_remote_frame: bool = False
    bitrate_switch: bool = False
    timestamp: float = 0.0
