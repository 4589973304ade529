"""An SLCAN (Lawicel ASCII) USB-CAN adapter, emulated on a pty, bridging to the sheet's chips.

The host opens it with python-can's own ``slcan`` interface, unchanged::

    bus = can.Bus(interface="slcan", channel=device.path, bitrate=1_000_000, sleep_after_open=0)

`SlcanAdapter` is the sans-I/O codec of one adapter (bytes from the host in, reply bytes out,
CAN frames to the bus out; CAN frames from the bus in, ASCII lines out); `SlcanDevice` runs one
adapter per bus on ptys. Commands (each ends with CR; the adapter answers CR for OK and BEL
for an error, as a Lawicel CAN232/CANUSB and a CANable do):

======== ==========================================================================================
``Sn``   bit rate n = 0..8 (10 k .. 1 M; python-can also sends ``S9`` for 83.3 k): closed only
``sxxyy`` BTR0/BTR1 bit timing: closed only
``Yn``   CAN FD data bit rate (CANable 2.0 extension): closed only; an empty command is OK
``O``    open (``L``: open listen-only: frames from the host are refused with BEL)
``C``    close
``tiiildd..`` / ``Tiiiiiiiildd..``  send a standard / extended frame (answer ``z``/``Z`` + CR)
``d``/``D``/``b``/``B``  CAN FD frame, DLC as one hex digit (``b``/``B``: bit rate switch)
``r``/``R`` remote frame (sent on, ignored by the chips)
``V``    version: ``V1013`` (hardware 10, software 13);  ``v``: ``v0113``
``N``    serial number: ``NCS01``
``F``    status flags (``F%02X``: bit 0 RX FIFO full, bit 3 data overrun, bit 7 bus error); read clears
``Zn``   timestamps off (0) / on (1): a received frame then ends with 4 hex digits, ms mod 60000
``M``/``m``/``X``/``W``/``Q``/``U`` acceptance code/mask, auto-poll, ... : accepted, no effect
======== ==========================================================================================

Received frames (from the chips) go to the host only while the channel is open, as ``T`` lines
(``D``/``B`` for FD frames). An error frame on the bus sets the bus-error flag of ``F``
(Lawicel has no line for it); the device counts it in ``error_frames``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from protocol.can import CanFrame

from .devices import PtyGroup, PtyGroupDevice
from .faults import ERROR_FRAME
from .gateway import Gateway

__all__ = ["SlcanAdapter", "SlcanDevice", "DLC_TO_LEN", "LEN_TO_DLC"]

DLC_TO_LEN = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
LEN_TO_DLC = {n: i for i, n in enumerate(DLC_TO_LEN)}
_OK, _ERR = b"\r", b"\a"
_MAX_LINE = 200
_FLAG_RX_FULL, _FLAG_OVERRUN, _FLAG_BUS_ERROR = 0x01, 0x08, 0x80


class SlcanAdapter:
    """Lawicel protocol state of one adapter (sans-I/O).

    Parameters
    ----------
    send_to_bus : callable(CanFrame, remote: bool, extended: bool)
        What to do with a frame the host transmits.
    fd : bool
        Accept and produce CAN FD frames.
    """

    def __init__(self, send_to_bus: Callable[[CanFrame, bool, bool], None], *, fd: bool = False) -> None:
        self.send_to_bus = send_to_bus
        self.fd = fd
        self.is_open = False
        self.listen_only = False
        self.bitrate_code: str | None = None
        self.timestamps = False
        self.flags = 0
        self.error_frames = 0
        self.bad_commands = 0
        self._line = bytearray()
        self._discard = False

    # ------------------------------------------------------------------ host -> adapter
    def feed(self, data: bytes, now_s: float = 0.0) -> bytes:
        """Bytes from the host; returns the reply bytes."""
        out = bytearray()
        buf = self._line
        for b in data:
            if b in (0x0D, 0x0A):
                if self._discard:
                    self._discard = False
                    buf.clear()
                    out += _ERR
                    continue
                if b == 0x0A and not buf:
                    continue  # CR LF: the LF is not a command
                out += self._command(bytes(buf).decode("ascii", "replace"), now_s)
                buf.clear()
            else:
                if len(buf) >= _MAX_LINE:
                    self._discard = True
                    buf.clear()
                if not self._discard:
                    buf.append(b)
        return bytes(out)

    def _command(self, line: str, now_s: float) -> bytes:
        if not line:
            return _OK
        c = line[0]
        try:
            if c in "tTdDbBrR":
                return self._transmit(line)
            if c == "S":
                if self.is_open or len(line) != 2 or line[1] not in "012345678" + "9":
                    return self._bad()
                self.bitrate_code = line
                return _OK
            if c == "s":
                if self.is_open or len(line) != 5:
                    return self._bad()
                int(line[1:], 16)
                self.bitrate_code = line
                return _OK
            if c == "Y":
                return _OK if not self.is_open else self._bad()
            if c in "OL":
                if self.is_open:
                    return self._bad()
                self.is_open, self.listen_only = True, c == "L"
                return _OK
            if c == "C":
                self.is_open = False
                return _OK
            if c == "V":
                return b"V1013\r"
            if c == "v":
                return b"v0113\r"
            if c == "N":
                return b"NCS01\r"
            if c == "F":
                f, self.flags = self.flags, 0
                return f"F{f:02X}\r".encode()
            if c == "Z":
                if line[1:] not in ("0", "1"):
                    return self._bad()
                self.timestamps = line[1:] == "1"
                return _OK
            if c in "MmXWQU":
                return _OK
        except (ValueError, IndexError):
            return self._bad()
        return self._bad()

    def _bad(self) -> bytes:
        self.bad_commands += 1
        return _ERR

    def _transmit(self, line: str) -> bytes:
        if not self.is_open or self.listen_only:
            return self._bad()
        c = line[0]
        extended = c in "TDBR"
        n_id = 8 if extended else 3
        can_id = int(line[1:1 + n_id], 16)
        if can_id >= (1 << 29 if extended else 1 << 11):
            return self._bad()
        dlc_ch = line[1 + n_id]
        fd = c in "dDbB"
        if fd and not self.fd:
            return self._bad()
        dlc = int(dlc_ch, 16 if fd else 10)
        n = DLC_TO_LEN[dlc] if fd else dlc
        if n > 8 and not fd:
            return self._bad()
        remote = c in "rR"
        data = b"" if remote else bytes.fromhex(line[2 + n_id:2 + n_id + 2 * n])
        if len(data) != (0 if remote else n) or (not remote and len(line) != 2 + n_id + 2 * n):
            return self._bad()
        self.send_to_bus(CanFrame(can_id, data, fd), remote, extended)
        return b"Z\r" if extended else b"z\r"

    # ------------------------------------------------------------------ bus -> host
    def frames_to_host(self, frames: list, now_s: float) -> bytes:
        """ASCII lines for frames received from the bus (nothing while closed).

        A batch of classic frames of 7 data bytes (a SYNC's SAMPLE answers) is formatted by numpy
        in one pass, byte for byte what the per-frame loop writes; anything else goes through it."""
        if self.is_open and not self.timestamps and len(frames) > 8:
            fast = _sample_lines(frames)
            if fast is not None:
                return fast
        out = []
        for f in frames:
            if f is ERROR_FRAME:
                self.error_frames += 1
                self.flags |= _FLAG_BUS_ERROR
                continue
            if not self.is_open:
                continue
            if f.is_fd:
                line = f"D{f.arbitration_id:08X}{LEN_TO_DLC[len(f.data)]:X}{f.data.hex().upper()}"
            else:
                line = f"T{f.arbitration_id:08X}{len(f.data):d}{f.data.hex().upper()}"
            if self.timestamps:
                line += f"{int(now_s * 1000) % 60000:04X}"
            out.append(line)
        return ("\r".join(out) + "\r").encode() if out else b""


_HEX_DIGITS = np.frombuffer(b"0123456789ABCDEF", dtype=np.uint8)
_ID_SHIFTS = np.arange(28, -1, -4, dtype=np.uint32)


def _sample_lines(frames: list) -> bytes | None:
    """``T`` lines of classic extended frames with 7 data bytes each, formatted in one numpy pass;
    None if ``frames`` holds anything else (an error frame, an FD frame, another length)."""
    if ERROR_FRAME in frames or any(f.is_fd or len(f.data) != 7 for f in frames):
        return None
    n = len(frames)
    ids = np.fromiter((f.arbitration_id for f in frames), dtype=np.uint32, count=n)
    data = b"".join([f.data for f in frames])
    out = np.empty((n, 25), dtype=np.uint8)
    out[:, 0] = 0x54  # T
    out[:, 1:9] = _HEX_DIGITS[(ids[:, None] >> _ID_SHIFTS) & 0xF]
    out[:, 9] = 0x37  # DLC 7
    d = np.frombuffer(data, dtype=np.uint8).reshape(n, 7)
    out[:, 10:24:2] = _HEX_DIGITS[d >> 4]
    out[:, 11:24:2] = _HEX_DIGITS[d & 0xF]
    out[:, 24] = 0x0D
    return out.tobytes()


class SlcanDevice(PtyGroupDevice):
    """One emulated SLCAN adapter per bus, each on its own pty, chips split across the buses.

    ``device.path`` (first bus) / ``device.paths``: stable symlinks to open with
    ``can.Bus(interface="slcan", channel=path)``. Needs a sheet with ``transport="can"``.
    """

    name = "slcan"

    def __init__(self, sheet, *, n_buses: int = 1, symlink_paths: list[str] | None = None, **kw) -> None:
        if sheet.transport != "can":
            raise ValueError(f"SlcanDevice needs a sheet with transport='can', got {sheet.transport!r}")
        super().__init__(sheet, **kw)
        self.blocks = sheet.split(n_buses)
        self.gateways = [self.gateway_class(sheet, blk, packed=self.packed, sync_rate_hz=self.sync_rate_hz, stream=b,
                                 as_node=self.gateway_node)
                         for b, blk in enumerate(self.blocks)]
        self.ports = PtyGroup("slcan", n_buses, symlink_paths)
        self.adapters = [SlcanAdapter(self._sender(b), fd=sheet.fd) for b in range(n_buses)]
        self.paths = self.ports.paths
        self.path = self.paths[0]

    def _sender(self, b: int):
        def send(frame: CanFrame, remote: bool, extended: bool) -> None:
            if remote or not extended:
                return  # not capsheet traffic
            if self.verbose is not None:
                self.verbose("rx", frame)
            self.gateways[b].receive(frame, self.now())
        return send

    def _received(self, b: int, data: bytes, t: float) -> None:
        reply = self.adapters[b].feed(data, t)
        if reply:
            self.ports[b].write(reply)

    def _send(self, bus: int, frames: list) -> None:
        data = self.adapters[bus].frames_to_host(frames, self.now())
        if data:
            self.ports[bus].write(data, len(frames))

    def _go_down(self) -> None:
        super()._go_down()
        for a in self.adapters:
            a.is_open = False

    def describe(self) -> str:
        return f"SLCAN adapter{'s' if len(self.paths) > 1 else ''} on {', '.join(self.paths)}"
