"""A buffered SLCAN (Lawicel ASCII) bus for the host: python-can's ``slcan`` interface, read in chunks.

python-can's `can.interfaces.slcan.slcanBus` reads the serial port one byte per ``read(1)`` call and
hands back one line per receive; at 145 Hz a 14x14 sheet on nine classic buses is ~53,000 lines a
second, and nine such readers in one process do not even get through bring-up. `BufferedSlcanBus`
is the same bus (it subclasses it: bring-up, bit rates, send, version and serial-number queries are
python-can's) with another receive path:

* ``_read`` takes everything the port has in one ``read(in_waiting or 1)`` and splits the lines
  itself (a line ends with CR, or with BEL, the adapter's error reply, as python-can splits them);
  a line cut across reads is completed by the next one, whatever the chunking;
* frames are parsed with python-can's rules (``T``/``x``, ``t``, ``r``, ``R``, ``d``, ``D``, ``b``,
  ``B``; the same `can.Message` fields), but strictly: a damaged line (a character that is not hex,
  a data field shorter or longer than its DLC, a classic DLC over 8, an identifier out of range, a
  line that is no SLCAN frame or reply, bytes that are not ASCII, a line over `MAX_LINE` characters)
  is counted in `bad_lines` and skipped, never raised (python-can raises ``ValueError`` for bad hex
  and ``UnicodeDecodeError`` for non-ASCII bytes, and silently returns a short frame for a short
  line); the valid lines around it are kept. A received frame may end with the 4-digit timestamp of
  the ``Z1`` mode (python-can ignores it; so does this);
* a command (a frame the host sends) is written without python-can's `tcdrain` after it (`_write`);
* stale input is drained at open: before its first command the bus closes the channel (``C``) and
  reads and discards what the port delivers until it has been quiet for ``drain_quiet_s`` (at most
  ``drain_max_s``): the backlog an adapter kept streaming into the port for a host that is gone
  (counted in `stale_bytes`), which python-can would read byte by byte, for seconds, before the first
  live frame;
* `drain` returns every frame that is already buffered (or arrives within one read), parsed in one
  pass, without a `BusABC.recv` round per frame; `drain_blocks` the same frames with each run of
  7-byte classic extended frames (capsheet's SAMPLE) parsed by numpy into one `FrameBlock` of
  arrays instead of one `can.Message` per frame: `host.transport.CanTransport` uses it.

Everything on the wire is counted: ``bad_lines`` (damaged, skipped), ``nacks`` (BEL replies: the
adapter refused a command — python-can's own bring-up sends ``O`` twice, so one NACK after opening
is normal), ``stale_bytes`` (drained at open). `host.transport.CanTransport` reports ``bad_lines``
as ``SLCAN_BAD_LINE`` in `TransportStats.errors`.
"""

from __future__ import annotations

import select
import time
from collections import deque
from typing import Any

import numpy as np

from can import Message
from can.exceptions import error_check
from can.interfaces.slcan import slcanBus
from can.util import CAN_FD_DLC

from protocol.can import FrameBlock

__all__ = ["BufferedSlcanBus", "FrameBlock", "MAX_LINE", "parse_line"]

#: the longest line accepted, in characters without the terminator: ``B`` + 8 id + 1 DLC + 128 data
#: + 4 timestamp is 142; a longer run without a terminator is counted as one bad line and skipped
MAX_LINE = 160

_HEX = frozenset(b"0123456789ABCDEFabcdef")
_DEC = frozenset(b"0123456789")
#: frame letter -> (identifier digits, extended, remote, fd, bitrate switch, DLC is hex)
_FRAME_KINDS = {
    ord("T"): (8, True, False, False, False, False),
    ord("x"): (8, True, False, False, False, False),  # CANDapter's extended frame (python-can reads it)
    ord("t"): (3, False, False, False, False, False),
    ord("R"): (8, True, True, False, False, False),
    ord("r"): (3, False, True, False, False, False),
    ord("D"): (8, True, False, True, False, True),
    ord("d"): (3, False, False, True, False, True),
    ord("B"): (8, True, False, True, True, True),
    ord("b"): (3, False, False, True, True, True),
}
#: replies that are not frames: (first character, hex/decimal characters after it)
_REPLIES = {ord("z"): 0, ord("Z"): 0, ord("V"): 4, ord("v"): 4, ord("N"): 4, ord("F"): 2}
_BAD = object()  # parse_line's answer for a damaged line

# drain_blocks' fast parse: "T" + 8 id digits + "7" + 14 data digits
_FAST_LEN = 24
_FAST_COLS = np.arange(1, _FAST_LEN)
_ID_SHIFTS = np.arange(28, -1, -4, dtype=np.uint32)
_NIBBLE = np.full(256, 0xFF, dtype=np.uint8)  # ASCII -> hex digit value, 0xFF if none
for _c in b"0123456789":
    _NIBBLE[_c] = _c - 0x30
for _c in b"ABCDEF":
    _NIBBLE[_c] = _c - 0x41 + 10
    _NIBBLE[_c + 0x20] = _c - 0x41 + 10


def _is_hex(b: bytes) -> bool:
    return _HEX.issuperset(b)


def parse_line(line: bytes, now: float | None = None):
    """One SLCAN line (without its terminator) -> `can.Message`, None (a reply or an empty line),
    or the module's ``_BAD`` marker (a damaged line). Never raises.

    >>> m = parse_line(b"T0101000023412")
    >>> hex(m.arbitration_id), m.is_extended_id, m.dlc, m.data.hex()
    ('0x1010000', True, 2, '3412')
    >>> parse_line(b"z") is None, parse_line(b"T01010000234") is _BAD, parse_line(b"T0101000023G12") is _BAD
    (True, True, True)
    """
    if not line:
        return None
    kind = _FRAME_KINDS.get(line[0])
    if kind is None:
        n = _REPLIES.get(line[0])
        if n is not None and len(line) == 1 + n and (_is_hex(line[1:]) or (line[0] == 0x4E and line.isalnum())):
            return None  # the serial number (N) is any 4 letters or digits
        return _BAD
    n_id, extended, remote, fd, brs, hex_dlc = kind
    head = 1 + n_id
    if len(line) < head + 1:
        return _BAD
    ident = line[1:head]
    dlc_ch = line[head]
    if not _is_hex(ident) or dlc_ch not in (_HEX if hex_dlc else _DEC):
        return _BAD
    can_id = int(ident, 16)
    if can_id >= ((1 << 29) if extended else (1 << 11)):
        return _BAD
    dlc = int(chr(dlc_ch), 16)
    if not fd and dlc > 8:
        return _BAD
    length = CAN_FD_DLC[dlc]
    n_data = 0 if remote else 2 * length
    body = line[head + 1:head + 1 + n_data]
    rest = len(line) - (head + 1 + n_data)
    if len(body) != n_data or rest not in (0, 4) or not _is_hex(body) or (rest and not _is_hex(line[-4:])):
        return _BAD
    return Message(arbitration_id=can_id, is_extended_id=extended,
                   timestamp=time.time() if now is None else now, is_remote_frame=remote, is_fd=fd,
                   bitrate_switch=brs, dlc=length, data=None if remote else bytearray.fromhex(body.decode("ascii")))


class BufferedSlcanBus(slcanBus):
    """python-can's slcan bus with a chunked, counting receive path (module docstring).

    Parameters
    ----------
    channel : str
        The serial port (``/dev/ttyACM0``, a pty), as for ``slcanBus``.
    drain_quiet_s : float
        At open, stale input is read and discarded until the port has been quiet this long.
        0 skips the drain (the bus then sends exactly python-can's commands).
    drain_max_s : float
        ... but for at most this long (an adapter that streams on regardless).
    **kwargs
        Everything ``slcanBus`` takes (``bitrate``, ``sleep_after_open``, ``tty_baudrate``, ...).
    """

    def __init__(self, channel: Any, *args: Any, drain_quiet_s: float = 0.05, drain_max_s: float = 1.0,
                 **kwargs: Any) -> None:
        self.bad_lines = 0  #: damaged lines skipped (module docstring)
        self.nacks = 0  #: BEL replies (the adapter refused a command)
        self.stale_bytes = 0  #: bytes drained at open
        self._drain_quiet_s = drain_quiet_s
        self._drain_max_s = drain_max_s
        self._drained = drain_quiet_s <= 0
        self._lines: deque[bytes] = deque()  # complete lines, terminator included
        self._partial = bytearray()  # the start of a line not yet terminated
        self._skipping = False  # inside an over-long line: discard up to its terminator
        super().__init__(channel, *args, **kwargs)

    # ------------------------------------------------------------------ bytes -> lines
    def _fill(self, timeout: float | None) -> bool:
        """Read what the port has (waiting up to ``timeout`` for the first byte) into lines.
        True if anything was read."""
        port = self.serialPortOrig
        n = port.in_waiting
        if not n:
            if timeout is not None and timeout <= 0:
                return False
            try:
                fd = port.fileno()
            except Exception:  # noqa: BLE001 - loop:// and friends have no descriptor
                fd = None
            if fd is not None:
                r, _, _ = select.select([fd], [], [], timeout)
                if not r:
                    return False
                n = port.in_waiting
        data = port.read(n or 1)
        if not data:
            return False
        self._partial += data
        return True

    def _split(self) -> None:
        """Complete lines (CR or BEL at the end) of the byte buffer go to the line queue."""
        buf = self._partial
        start = 0
        end = len(buf)
        lines = self._lines
        while start < end:
            cr = buf.find(b"\r", start)
            bel = buf.find(b"\a", start)
            stop = cr if bel < 0 or (0 <= cr < bel) else bel
            if stop < 0:
                break
            if self._skipping:
                self._skipping = False
            else:
                lines.append(bytes(buf[start:stop + 1]))
            start = stop + 1
        del buf[:start]
        if len(buf) > MAX_LINE:
            if not self._skipping:
                self.bad_lines += 1
                self._skipping = True
            buf.clear()

    def _read(self, timeout: float | None) -> str | None:
        """python-can's hook: the next line, terminator included, as a str (or None on timeout).
        Used by python-can's ``get_version`` / ``get_serial_number``; frames go through
        `_recv_internal` / `drain`, which read the bytes directly."""
        line = self._next_line(timeout)
        return None if line is None else line.decode("ascii", "replace")

    def _next_line(self, timeout: float | None) -> bytes | None:
        if not self._lines:
            self._split()
        if self._lines:
            return self._lines.popleft()
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            self._fill(remaining)
            self._split()
            if self._lines:
                return self._lines.popleft()
            if deadline is not None and time.monotonic() >= deadline:
                return None

    # ------------------------------------------------------------------ lines -> frames
    def _parse(self, line: bytes, now: float | None = None) -> Message | None:
        """A queued line (terminator included) -> frame, or None (counted if damaged)."""
        if line[-1:] == b"\a":
            if len(line) > 1:
                self.bad_lines += 1  # BEL after text: a damaged line
            else:
                self.nacks += 1
            return None
        m = parse_line(line[:-1], now)
        if m is _BAD:
            self.bad_lines += 1
            return None
        return m

    def _recv_internal(self, timeout: float | None) -> tuple[Message | None, bool]:
        if self._queue.qsize():  # a line python-can's get_version put back
            line = self._queue.get_nowait().encode("ascii", "replace")
        else:
            line = self._next_line(timeout)
        if line is None:
            return None, False
        return self._parse(line), False

    def drain(self, timeout: float | None = 0.0, max_frames: int | None = None) -> list[Message]:
        """Every frame already buffered or in the port, in wire order, parsed in one pass; waits up
        to ``timeout`` (None: indefinitely) for the first byte if nothing is there. Filters apply as
        in `recv`. Damaged lines are counted (`bad_lines`) and skipped. At most ``max_frames``
        frames; the rest stay buffered for the next call."""
        self._take_queue()
        self._split()
        if not self._lines:
            self._fill(timeout)
        if self.serialPortOrig.in_waiting:
            self._fill(0)
        self._split()
        out: list[Message] = []
        lines = self._lines
        now = time.time()
        filtered = self._filters is not None
        while lines and (max_frames is None or len(out) < max_frames):
            m = self._parse(lines.popleft(), now)
            if m is not None and (not filtered or self._matches_filters(m)):
                out.append(m)
        return out

    def _take_queue(self) -> None:
        """Lines python-can's ``get_version`` put back go first."""
        back = []
        while self._queue.qsize():
            back.append(self._queue.get_nowait().encode("ascii", "replace"))
        self._lines.extendleft(reversed(back))

    def drain_blocks(self, timeout: float | None = 0.0, max_lines: int | None = None) -> list:
        """Like `drain`, for a receiver that takes arrays: runs of the commonest line, a classic
        extended frame of 7 data bytes (``Tiiiiiiii7dddddddddddddd``, a capsheet SAMPLE), come
        out as one `FrameBlock` each, parsed by numpy for the whole run; every other line as a
        `can.Message` from `parse_line`, in wire order. The same frames as `drain`, with the same
        counts (a line the fast parse does not accept goes through `parse_line`). At most
        ``max_lines`` lines per call (the rest stay buffered)."""
        if self._filters is not None:
            return self.drain(timeout, max_lines)
        self._take_queue()
        out: list = []
        now = time.time()
        lines = self._lines
        while lines:  # lines already split (by recv or get_version) come before the raw bytes
            m = self._parse(lines.popleft(), now)
            if m is not None:
                out.append(m)
        if not out and b"\r" not in self._partial and b"\a" not in self._partial:
            self._fill(timeout)
        if self.serialPortOrig.in_waiting:
            self._fill(0)
        raw = self._partial
        if self._skipping:  # the rest of an over-long or stale line
            cut = min((i for i in (raw.find(b"\r"), raw.find(b"\a")) if i >= 0), default=-1)
            if cut < 0:
                raw.clear()
                return out
            del raw[:cut + 1]
            self._skipping = False
        data = bytes(raw)
        arr = np.frombuffer(data, dtype=np.uint8)
        term = np.flatnonzero((arr == 13) | (arr == 7))
        if max_lines is not None:
            term = term[:max(0, max_lines - len(out))]
        if term.size:
            del raw[:int(term[-1]) + 1]
            out += self._parse_lines(data, arr, term, now)
        if len(raw) > MAX_LINE:
            self.bad_lines += 1
            self._skipping = True
            raw.clear()
        return out

    def _parse_lines(self, data: bytes, arr: np.ndarray, term: np.ndarray, now: float) -> list:
        starts = np.empty_like(term)
        starts[0] = 0
        starts[1:] = term[:-1] + 1
        fast = (term - starts == _FAST_LEN) & (arr[starts] == 0x54) & (arr[term] == 13)
        cand = np.flatnonzero(fast)
        if cand.size:
            rows = arr[starts[cand, None] + _FAST_COLS]  # (m, 23): 8 id digits, the DLC, 14 data digits
            nib = _NIBBLE[rows]
            ok = (rows[:, 8] == 0x37) & (nib[:, :8] < 16).all(axis=1) & (nib[:, 9:] < 16).all(axis=1)
            ids = (nib[:, :8].astype(np.uint32) << _ID_SHIFTS).sum(axis=1, dtype=np.uint32)
            ok &= ids < (1 << 29)
            fast[cand[~ok]] = False
            keep = ok.nonzero()[0]
            ids, nib = ids[keep], nib[keep]
            frame_data = (nib[:, 9::2] << 4) | nib[:, 10::2]
            row_of = np.cumsum(fast) - 1
        out: list = []
        edges = np.flatnonzero(np.diff(fast.astype(np.int8))) + 1
        bounds = [0, *edges.tolist(), int(term.size)]
        starts_l, term_l = starts.tolist(), term.tolist()
        for a, b in zip(bounds[:-1], bounds[1:]):
            if fast[a]:
                i, j = int(row_of[a]), int(row_of[b - 1]) + 1
                out.append(FrameBlock(ids[i:j], frame_data[i:j]))
                continue
            for k in range(a, b):
                m = self._parse(data[starts_l[k]:term_l[k] + 1], now)
                if m is not None:
                    out.append(m)
        return out

    # ------------------------------------------------------------------ open
    def _write(self, string: str) -> None:
        """python-can's command writer, without its ``flush()`` after every line: on a tty that is
        ``tcdrain``, which waits until the adapter has read the line, so every send (a SYNC on each
        bus, 145 times a second) waited for the other side's read loop. The line is still written
        whole (pyserial's ``write`` loops until it is, within ``write_timeout``)."""
        if not self._drained:
            self._drained = True
            self._put("C")  # an adapter left open by a host that is gone stops streaming
            self._drain_stale()
        self._put(string)

    def _put(self, string: str) -> None:
        with error_check("Could not write to serial device"):
            self.serialPortOrig.write(string.encode() + self.LINE_TERMINATOR)

    def _drain_stale(self) -> None:
        port = self.serialPortOrig
        t0 = last = time.monotonic()
        tail = b"\r"
        while True:
            now = time.monotonic()
            if now - last >= self._drain_quiet_s or now - t0 >= self._drain_max_s:
                break
            n = port.in_waiting
            if n:
                data = port.read(n)
                self.stale_bytes += len(data)
                tail = data[-1:] or tail
                last = time.monotonic()
            else:
                time.sleep(min(0.005, self._drain_quiet_s))
        self._buffer.clear()
        self._lines.clear()
        self._partial.clear()
        # stopped inside a line (an adapter streaming on): its rest is stale too, not a damaged line
        self._skipping = tail not in (b"\r", b"\a")

    def flush(self) -> None:
        """Discard buffered input (python-can's ``flush``, and this bus's line buffer)."""
        self._lines.clear()
        self._partial.clear()
        self._skipping = False
        super().flush()
