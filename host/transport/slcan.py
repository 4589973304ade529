"""The SLCAN (Lawicel ASCII) bus capsheet reads, as a python-can interface of its own: `SlcanBus`.

python-can's own ``slcan`` interface (`can.interfaces.slcan.slcanBus`) reads the serial port one
byte per ``read(1)`` call and hands back one line per receive; at 145 Hz a 14x14 sheet on nine
classic buses is ~53,000 lines a second, and nine such readers in one process do not even get
through bring-up. `SlcanBus` is a `can.BusABC` of its own, written to python-can's backend contract:
it implements ``_recv_internal`` and ``send`` (and ``shutdown``, ``fileno``), and python-can's
``BusABC.recv`` does the timeout loop and the filters. It is registered under the name
``capsheet_slcan`` through python-can's ``can.interface`` entry point (pyproject.toml), so

    bus = can.Bus(interface="capsheet_slcan", channel="/dev/ttyACM0", bitrate=1_000_000)

and python-can configuration files (``interface = capsheet_slcan``) open it, in any program.
`host.transport.ports.CanTransport` opens it for ``--can slcan:PORT`` (and ``capsheet_slcan:PORT``).

How it reads and writes:

* a receive takes everything the port has in one ``read(in_waiting or 1)`` and splits the lines
  itself (a line ends with CR, or with BEL, the adapter's error reply); a line cut across reads is
  completed by the next one, whatever the chunking;
* frames are parsed with python-can's rules (``T``/``x``, ``t``, ``r``, ``R``, ``d``, ``D``,
  ``b``, ``B``; the same `can.Message` fields), but strictly: a damaged line (a character that is
  not hex, a data field shorter or longer than its DLC, a classic DLC over 8, an identifier out of
  range, a line that is no SLCAN frame or reply, bytes that are not ASCII, a line over `MAX_LINE`
  characters) is counted in `bad_lines` and skipped, never raised (python-can raises ``ValueError``
  for bad hex and ``UnicodeDecodeError`` for non-ASCII bytes, and silently returns a short frame
  for a short line); the valid lines around it are kept. A received frame may end with the 4-digit
  timestamp of the ``Z1`` mode (ignored, as python-can does);
* a command is written whole without a ``tcdrain`` after it (python-can flushes after every line,
  which on a tty waits until the adapter has read it: every SYNC waited for the other side);
* stale input is drained at open: before its first command the bus closes the channel (``C``) and
  reads and discards what the port delivers until it has been quiet for ``drain_quiet_s`` (at most
  ``drain_max_s``): the backlog an adapter kept streaming into the port for a host that is gone
  (counted in `stale_bytes`), which a byte-by-byte reader would take seconds to get through;
* **the batched fast path** (public, documented): `SlcanBus.drain` returns every frame already
  buffered (or arriving within one read), parsed in one pass, without a ``recv`` round per frame;
  `SlcanBus.drain_blocks` the same frames with each run of 7-byte classic extended frames
  (capsheet's SAMPLE) parsed by numpy into one `protocol.can.FrameBlock` of arrays instead of one
  `can.Message` per frame. `host.transport.ports.CanTransport` receives through ``drain_blocks`` and
  `protocol.can.CanDecoder` decodes the blocks without a message per frame.

Everything on the wire is counted: `bad_lines` (damaged, skipped), `nacks` (BEL replies: the
adapter refused a command), `stale_bytes` (drained at open). `host.transport.ports.CanTransport` reports
the damaged lines as ``SLCAN_BAD_LINE`` in its ``stats.errors`` (`SlcanBus.take_bad_lines`).
"""

from __future__ import annotations

import select
import time
from collections import deque
from typing import Any

import numpy as np

from can import BusABC, Message
from can.exceptions import CanInitializationError, CanOperationError, error_check
from can.util import CAN_FD_DLC, len2dlc

from protocol.can import FrameBlock

from host.transport.portlock import PortBusy, open_exclusive

__all__ = ["SlcanBus", "BufferedSlcanBus", "INTERFACE", "MAX_LINE", "parse_line"]

#: the name python-can knows this bus by (the ``can.interface`` entry point in pyproject.toml)
INTERFACE = "capsheet_slcan"

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


#: bit rate -> the command that sets it (Lawicel ``Sn``; ``S9`` is 83.3 kbit/s, as python-can has it)
BITRATES = {10_000: "S0", 20_000: "S1", 50_000: "S2", 100_000: "S3", 125_000: "S4", 250_000: "S5",
            500_000: "S6", 750_000: "S7", 1_000_000: "S8", 83_300: "S9"}
#: CAN FD data bit rate -> command (CANable 2.0's extension, as python-can has it)
DATA_BITRATES = {2_000_000: "Y2", 5_000_000: "Y5"}


class SlcanBus(BusABC):
    """An SLCAN (Lawicel) adapter as a python-can bus, read in chunks (module docstring).

    Parameters
    ----------
    channel : str
        The serial port (``/dev/ttyACM0``, a pty, any pyserial URL); ``PORT@BAUD`` sets the tty
        baud rate, as for python-can's slcan.
    bitrate : int, optional
        CAN bit rate, one of `BITRATES` (``S0`` .. ``S9``); None: the adapter keeps its own.
    data_bitrate : int, optional
        CAN FD data bit rate, one of `DATA_BITRATES`.
    btr : str, optional
        ``"xxyy"``: BTR0/BTR1 bit timing (``sxxyy``), instead of ``bitrate``.
    fd : bool
        The bus carries CAN FD (python-can's ``fd`` argument; frames are parsed either way).
    listen_only : bool
        Open with ``L`` (listen only) instead of ``O``.
    tty_baudrate : int
        Baud rate of the serial port (real UARTs; ignored by ptys and USB CDC).
    sleep_after_open : float
        Seconds to wait after opening the port before the first command (python-can's default 2 s:
        some adapters reset when the port opens).
    drain_quiet_s, drain_max_s : float
        At open, stale input is read and discarded until the port has been quiet ``drain_quiet_s``
        (at most ``drain_max_s``); ``drain_quiet_s=0`` skips it.
    can_filters : list, optional
        python-can filters, applied by ``recv`` (and by `drain` / `drain_blocks`).
    """

    def __init__(self, channel: Any, *, bitrate: int | None = None, data_bitrate: int | None = None,
                 btr: str | None = None, timing=None, fd: bool = False, listen_only: bool = False,
                 tty_baudrate: int = 115200, sleep_after_open: float = 2.0, rtscts: bool = False,
                 drain_quiet_s: float = 0.05, drain_max_s: float = 1.0, can_filters=None, **kwargs: Any) -> None:
        import serial
        from can import BitTiming, BitTimingFd

        if not channel:
            raise ValueError("Must specify a serial port.")
        channel = str(channel)
        if "@" in channel:
            channel, _, baud = channel.rpartition("@")
            tty_baudrate = int(baud)
        # a python-can configuration file hands over strings
        bitrate = None if bitrate is None else int(bitrate)
        data_bitrate = None if data_bitrate is None else int(data_bitrate)
        tty_baudrate, sleep_after_open = int(tty_baudrate), float(sleep_after_open)
        drain_quiet_s, drain_max_s = float(drain_quiet_s), float(drain_max_s)
        fd, listen_only, rtscts = _flag(fd), _flag(listen_only), _flag(rtscts)
        if isinstance(timing, BitTimingFd):
            bitrate, data_bitrate = timing.nom_bitrate, timing.data_bitrate
        elif isinstance(timing, BitTiming):
            if timing.f_clock != 8_000_000:
                raise ValueError(f"Invalid timing: an SLCAN adapter's BTR registers run at f_clock 8 MHz, "
                                 f"not {timing.f_clock} Hz")
            btr = f"{timing.btr0:02X}{timing.btr1:02X}"
        if bitrate is not None and bitrate not in BITRATES:
            raise ValueError(f"Invalid bitrate {bitrate!r}, choose one of {', '.join(map(str, BITRATES))}")
        if data_bitrate is not None and data_bitrate not in DATA_BITRATES:
            raise ValueError(f"Invalid data bitrate {data_bitrate!r}, choose one of "
                             f"{', '.join(map(str, DATA_BITRATES))}")
        if bitrate is not None and btr is not None:
            raise ValueError("bitrate and btr are mutually exclusive")
        #: the adapter's tty as opened (`host.transport.portlock.DeviceIdentity`; None for a URL):
        #: `host.transport.ports.CanTransport` reconnects only to the same one
        self.identity = None
        self.bad_lines = 0  #: damaged lines skipped (module docstring)
        self.nacks = 0  #: BEL replies (the adapter refused a command)
        self.stale_bytes = 0  #: bytes drained at open
        self.fd = bool(fd)
        self._lines: deque[bytes] = deque()  # complete lines, terminator included
        self._partial = bytearray()  # the start of a line not yet terminated
        self._skipping = False  # inside an over-long line: discard up to its terminator
        # one session per adapter: the tty is taken exclusively, as a serial gateway's port is
        # (host/transport/portlock.py); a held one is refused before it is opened, naming the holder
        try:
            self._port, self.identity = open_exclusive(lambda excl: serial.serial_for_url(
                channel, baudrate=tty_baudrate, rtscts=rtscts, timeout=0, exclusive=excl), channel)
        except PortBusy as exc:
            raise CanInitializationError(str(exc)) from exc
        except Exception as exc:  # noqa: BLE001 - SerialException, OSError, ValueError
            raise CanInitializationError(f"Cannot open {channel!r}: {exc}") from exc
        try:
            time.sleep(sleep_after_open)
            with error_check(exception_type=CanInitializationError):
                self._write("C")  # an adapter left open by a host that is gone stops streaming
                if drain_quiet_s > 0:
                    self._drain_stale(drain_quiet_s, drain_max_s)
                if bitrate is not None:
                    self._write(BITRATES[bitrate])
                if btr is not None:
                    self._write("s" + btr)
                if data_bitrate is not None:
                    self._write(DATA_BITRATES[data_bitrate])
                self._write("L" if listen_only else "O")
        except BaseException:
            self._port.close()
            raise
        self.channel_info = f"SLCAN adapter on {channel}"
        super().__init__(channel, can_filters=can_filters, **kwargs)

    # ------------------------------------------------------------------ python-can's contract
    def _recv_internal(self, timeout: float | None) -> tuple[Message | None, bool]:
        """The next frame within ``timeout`` (None: wait), and False (python-can applies the
        filters). Replies and damaged lines are consumed on the way."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            line = self._next_line(remaining)
            if line is None:
                return None, False
            m = self._parse(line)
            if m is not None:
                return m, False
            if deadline is not None and time.monotonic() >= deadline and not self._lines:
                return None, False

    def send(self, msg: Message, timeout: float | None = None) -> None:
        """Write ``msg`` as one SLCAN line (whole; ``timeout``: the port's write timeout)."""
        if timeout != self._port.write_timeout:
            self._port.write_timeout = timeout
        aid = msg.arbitration_id
        ident = f"{aid:08X}" if msg.is_extended_id else f"{aid:03X}"
        if msg.is_remote_frame:
            line = ("R" if msg.is_extended_id else "r") + ident + f"{msg.dlc:d}"
        elif msg.is_fd:
            kind = ("B" if msg.is_extended_id else "b") if msg.bitrate_switch else ("D" if msg.is_extended_id else "d")
            line = kind + ident + f"{len2dlc(msg.dlc):X}" + msg.data.hex().upper()
        else:
            line = ("T" if msg.is_extended_id else "t") + ident + f"{msg.dlc:d}" + msg.data.hex().upper()
        with error_check("Could not write to serial device", CanOperationError):
            self._write(line)

    def shutdown(self) -> None:
        """Close the channel (``C``) and the port. Safe to call twice."""
        super().shutdown()
        try:
            self._write("C")
        except Exception:  # noqa: BLE001 - the port may be gone already
            pass
        with error_check("Could not close serial socket"):
            self._port.close()

    def fileno(self) -> int:
        try:
            return int(self._port.fileno())
        except Exception as exc:  # noqa: BLE001 - loop:// and friends have none
            raise NotImplementedError(f"fileno is not available for this port: {exc}") from None

    # ------------------------------------------------------------------ the adapter's queries
    def get_version(self, timeout: float | None) -> tuple[int | None, int | None]:
        """Hardware and software version (``V``), or ``(None, None)`` after ``timeout``."""
        line = self._query("V", 4, timeout)
        return (None, None) if line is None else (int(line[1:3]), int(line[3:5]))

    def get_serial_number(self, timeout: float | None) -> str | None:
        """The adapter's serial number (``N``), or None after ``timeout``."""
        line = self._query("N", 4, timeout)
        return None if line is None else line[1:5].decode("ascii", "replace")

    def _query(self, cmd: str, n: int, timeout: float | None) -> bytes | None:
        """Send ``cmd`` and wait for its reply line; the frames that arrive meanwhile stay queued."""
        self._write(cmd)
        held: list[bytes] = []
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            while True:
                remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
                line = self._next_line(remaining)
                if line is None:
                    return None
                if line[:1] == cmd.encode() and len(line) == n + 2:
                    return line
                held.append(line)
        finally:
            self._lines.extendleft(reversed(held))

    @property
    def in_waiting(self) -> int:
        """Bytes the port holds that this bus has not read yet."""
        return int(self._port.in_waiting)

    def take_bad_lines(self) -> int:
        """Damaged lines skipped since the last call (the count starts again from 0)."""
        n, self.bad_lines = self.bad_lines, 0
        return n

    # ------------------------------------------------------------------ the batched fast path
    def drain(self, timeout: float | None = 0.0, max_frames: int | None = None) -> list[Message]:
        """Every frame already buffered or in the port, in wire order, parsed in one pass; waits up
        to ``timeout`` (None: indefinitely) for the first byte if nothing is there. Filters apply as
        in ``recv``. Damaged lines are counted (`bad_lines`) and skipped. At most ``max_frames``
        frames; the rest stay buffered for the next call."""
        self._split()
        if not self._lines:
            self._fill(timeout)
        if self._port.in_waiting:
            self._fill(0)
        self._split()
        out: list[Message] = []
        lines = self._lines
        now = time.time()
        while lines and (max_frames is None or len(out) < max_frames):
            m = self._parse(lines.popleft(), now)
            if m is not None:
                out.append(m)
        return self._filtered(out)

    def drain_blocks(self, timeout: float | None = 0.0, max_lines: int | None = None) -> list:
        """Like `drain`, for a receiver that takes arrays: runs of the commonest line, a classic
        extended frame of 7 data bytes (``Tiiiiiiii7dddddddddddddd``, a capsheet SAMPLE), come
        out as one `protocol.can.FrameBlock` each, parsed by numpy for the whole run; every other
        line as a `can.Message`, in wire order. The same frames as `drain`, with the same counts (a
        line the fast parse does not accept goes through `parse_line`). At most ``max_lines`` lines
        per call (the rest stay buffered). With filters set, it is `drain` (no blocks)."""
        if self.filters is not None:
            return self.drain(timeout, max_lines)
        out: list = []
        now = time.time()
        lines = self._lines
        while lines:  # lines already split (by recv or a query) come before the raw bytes
            m = self._parse(lines.popleft(), now)
            if m is not None:
                out.append(m)
        if not out and b"\r" not in self._partial and b"\a" not in self._partial:
            self._fill(timeout)
        if self._port.in_waiting:
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

    def flush(self) -> None:
        """Discard buffered input: what the port holds and this bus's lines."""
        self._lines.clear()
        self._partial.clear()
        self._skipping = False
        with error_check("Could not flush"):
            self._port.reset_input_buffer()

    # ------------------------------------------------------------------ bytes -> lines
    def _filtered(self, frames: list[Message]) -> list[Message]:
        """``frames`` that pass the bus's python-can filters (public `BusABC.filters`)."""
        flt = self.filters
        if flt is None:
            return frames
        return [m for m in frames if _matches(m, flt)]

    def _fill(self, timeout: float | None) -> bool:
        """Read what the port has (waiting up to ``timeout`` for the first byte) into the buffer.
        True if anything was read."""
        port = self._port
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
        """One command line, written whole (pyserial's ``write`` loops until it is), no tcdrain."""
        self._port.write(string.encode() + b"\r")

    def _drain_stale(self, quiet_s: float, max_s: float) -> None:
        port = self._port
        t0 = last = time.monotonic()
        tail = b"\r"
        while True:
            now = time.monotonic()
            if now - last >= quiet_s or now - t0 >= max_s:
                break
            n = port.in_waiting
            if n:
                data = port.read(n)
                self.stale_bytes += len(data)
                tail = data[-1:] or tail
                last = time.monotonic()
            else:
                time.sleep(min(0.005, quiet_s))
        self._lines.clear()
        self._partial.clear()
        # stopped inside a line (an adapter streaming on): its rest is stale too, not a damaged line
        self._skipping = tail not in (b"\r", b"\a")


def _flag(v) -> bool:
    """A boolean argument, also as a configuration file writes it (``true``, ``1``, ``no`` ...)."""
    if isinstance(v, str):
        return v.strip().lower() in ("1", "true", "yes", "on")
    return bool(v)


def _matches(msg: Message, filters) -> bool:
    """python-can's filter rule (``can_id``, ``can_mask``, optional ``extended``), as documented
    for `can.BusABC.set_filters`: a frame passes if any filter matches."""
    for f in filters:
        if "extended" in f and f["extended"] != msg.is_extended_id:
            continue
        if (msg.arbitration_id ^ f["can_id"]) & f["can_mask"] == 0:
            return True
    return False


#: the name this bus had when it subclassed python-can's slcanBus
BufferedSlcanBus = SlcanBus
